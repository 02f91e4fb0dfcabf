"""trimesh's ray interface, answered by jrt: :class:`RayMeshIntersector`.

    import trimesh, jrt.trimesh
    mesh = trimesh.load("camel.off")
    mesh.ray = jrt.trimesh.RayMeshIntersector(mesh)      # structure="bvh", kernel="watertight"
    inside = mesh.contains(points)                       # trimesh's own code now casts with jrt

The methods and their return conventions are trimesh's (``trimesh.ray.ray_triangle``'s
and ``ray_pyembree``'s ``RayMeshIntersector``): ``intersects_id``, ``intersects_location``
(``locations, index_ray, index_tri``), ``intersects_first``, ``intersects_any`` and
``contains_points``, NumPy arrays in and out (``int64`` indices, ``float64`` locations),
lists, float64, directions of any length and a single ray accepted. trimesh's functions
that cast rays (``Trimesh.contains``, ``proximity.signed_distance``, ...) call these
through ``mesh.ray``.

What differs, for the better:

* **Every hit, exactly once.** Multiple hits come from :func:`jrt.all_hits`, one traversal
  that collects every triangle a ray meets (Embree's binding casts again from just past
  each hit, which can skip a coincident face or loop at large coordinates, and asks for a
  ``max_hits``). A ray through a shared edge or vertex has one hit there (the watertight
  kernel finds no gap, and hits within 2^-20 of ``t`` are one, on the lowest face index),
  so a hit count is a crossing count and ``contains_points`` needs no second guess.
* ``max_hits`` (default: all of them) caps the hits reported per ray, nearest first.

Rays are traced in float32, as all of jrt (trimesh's own intersector works in float64):
at coordinates near 1e4 a location is good to about 1e-3. Directions are normalised in
float64 first (trimesh does the same), so a zero direction is refused with the ray named.
Degenerate faces (zero area) are never hit. Results are ordered by ray, then by distance.
"""

from __future__ import annotations

import numpy as np

import accel
from jrt.all_hits import all_hits
from jrt.kernels import DEFAULT_KERNEL
from jrt.trace import closest_hit, occluded

#: trimesh's default direction for ``contains_points`` (``trimesh.ray.ray_util``): not
#: aligned with any axis, so that rays seldom run along a CAD model's faces.
CONTAINS_DIRECTION = np.array([0.4395064455, 0.617598629942, 0.652231566745])
#: ``max_hits`` of the first pass for every hit of each ray: most rays cross a mesh a few
#: times, and the few with more are traced again with room for their count.
FIRST_PASS_HITS = 4
#: ``max_hits`` of ``contains_points``' rays: only their counts are read, which are exact
#: whatever it is; rays that meet more triangles than its lanes keep are traced again.
CONTAINS_HITS = 4
#: The directions tried next, in turn, for points whose forward and backward rays disagree
#: (each unit, irrational-looking, not axis-aligned).
RETRY_DIRECTIONS = np.array([[-0.5773502692, 0.7071067812, 0.4082482905],
                             [0.2672612419, -0.5345224838, 0.8017837257]])


def _rays(ray_origins, ray_directions):
    """float64 [N, 3] origins and unit directions (one ray or one of either broadcast)."""
    o = np.asarray(ray_origins, dtype=np.float64)
    d = np.asarray(ray_directions, dtype=np.float64)
    o, d = o.reshape(-1, 3), d.reshape(-1, 3)
    if len(o) != len(d):
        if len(o) == 1 or len(d) == 1:
            o, d = np.broadcast_arrays(o, d)
        else:
            raise ValueError(f"ray_origins ({len(o)} rays) and ray_directions ({len(d)} "
                             f"rays) must have one row per ray (or one of them a single row)")
    with np.errstate(invalid="ignore", divide="ignore"):
        length = np.linalg.norm(d, axis=1, keepdims=True)
        unit = np.where(length > 0, d / length, d)  # a zero direction stays zero: refused
    return np.ascontiguousarray(o), np.ascontiguousarray(unit)


class RayMeshIntersector:
    """trimesh's ``RayMeshIntersector`` interface over a jrt structure (module docstring).

    Args:
        mesh: a ``trimesh.Trimesh`` (anything with ``vertices``, ``faces`` and ``bounds``).
        structure: the acceleration structure (``accel.names()``), built on first use and
            again whenever the mesh's geometry changes.
        kernel: the ray–triangle kernel (``jrt.KERNELS``).
        **params: the structure's build parameters (``accel.parameters(structure)``).
    """

    def __init__(self, mesh, structure: str = "bvh", kernel: str = DEFAULT_KERNEL,
                 **params):
        if structure not in accel.names():
            raise ValueError(f"unknown structure {structure!r}; allowed: "
                             f"{', '.join(accel.names())}")
        self.mesh = mesh
        self.structure_name = structure
        self.kernel = kernel
        self.params = params
        self._built = None
        self._key = None

    @property
    def structure(self):
        """The jrt structure over the mesh's current geometry."""
        vertices = np.asarray(self.mesh.vertices)
        faces = np.asarray(self.mesh.faces)
        key = (vertices.shape, faces.shape, hash(vertices.tobytes()), hash(faces.tobytes()))
        if key != self._key:
            self._built = accel.build(self.structure_name, vertices, faces, **self.params)
            self._key = key
        return self._built

    def intersects_id(self, ray_origins, ray_directions, multiple_hits: bool = True,
                      max_hits: int | None = None, return_locations: bool = False,
                      **kwargs):
        """Triangles hit by the rays: ``index_tri, index_ray`` (int64 [h]), and
        ``locations`` (float64 [h, 3]) with ``return_locations``. With ``multiple_hits``
        every hit of each ray (at most ``max_hits``, nearest first), else its first."""
        o, d = _rays(ray_origins, ray_directions)
        if len(o) == 0:
            empty = np.zeros(0, np.int64)
            return (empty, empty, np.zeros((0, 3))) if return_locations else (empty, empty)
        if multiple_hits:
            index_ray, index_tri, t = self._all(o, d, max_hits)
        else:
            hits = self._closest(o, d)
            triangle = np.asarray(hits.triangle)
            index_ray = np.flatnonzero(triangle >= 0)
            index_tri = triangle[index_ray].astype(np.int64)
            t = np.asarray(hits.t, np.float64)[index_ray]
        index_ray = index_ray.astype(np.int64)
        if not return_locations:
            return index_tri, index_ray
        return index_tri, index_ray, o[index_ray] + t[:, None] * d[index_ray]

    def _closest(self, o, d):
        """jrt's closest hits of float64 rays (traced in float32)."""
        return closest_hit(self.structure, o.astype(np.float32), d.astype(np.float32),
                           kernel=self.kernel)

    def _all(self, o, d, max_hits):
        """Every hit (at most ``max_hits`` a ray): ray, face, t, by ray then distance."""
        if max_hits is not None and (isinstance(max_hits, bool) or int(max_hits) != max_hits
                                     or max_hits < 1):
            raise ValueError(f"max_hits must be a positive integer or None (all hits), "
                             f"got {max_hits!r}")
        width = FIRST_PASS_HITS if max_hits is None else int(max_hits)
        o32, d32 = o.astype(np.float32), d.astype(np.float32)
        record = all_hits(self.structure, o32, d32, width, kernel=self.kernel)
        t, triangle = np.asarray(record.t), np.asarray(record.triangle)
        count = np.asarray(record.count)
        if max_hits is None and (count > width).any():
            # Room for every hit of the rays that have more (their counts are exact).
            more = np.flatnonzero(count > width)
            wide = all_hits(self.structure, o32[more], d32[more], int(count[more].max()),
                            kernel=self.kernel)
            t = np.pad(t, ((0, 0), (0, wide.t.shape[1] - width)), constant_values=np.inf)
            triangle = np.pad(triangle, ((0, 0), (0, wide.t.shape[1] - width)),
                              constant_values=-1)
            t[more], triangle[more] = np.asarray(wide.t), np.asarray(wide.triangle)
        index_ray, slot = np.nonzero(triangle >= 0)  # row-major: by ray, then distance
        return index_ray, triangle[index_ray, slot].astype(np.int64), \
            t[index_ray, slot].astype(np.float64)

    def intersects_location(self, ray_origins, ray_directions, **kwargs):
        """``locations`` (float64 [h, 3]), ``index_ray``, ``index_tri`` (int64 [h]) of the
        hits (every hit by default: ``multiple_hits``, ``max_hits`` as
        :meth:`intersects_id`)."""
        index_tri, index_ray, locations = self.intersects_id(
            ray_origins, ray_directions, return_locations=True, **kwargs)
        return locations, index_ray, index_tri

    def intersects_first(self, ray_origins, ray_directions, **kwargs):
        """int64 [N]: the face each ray hits first, -1 for none."""
        o, d = _rays(ray_origins, ray_directions)
        if len(o) == 0:
            return np.zeros(0, np.int64)
        return np.asarray(self._closest(o, d).triangle).astype(np.int64)

    def intersects_any(self, ray_origins, ray_directions, **kwargs):
        """bool [N]: does each ray hit the mesh?"""
        o, d = _rays(ray_origins, ray_directions)
        if len(o) == 0:
            return np.zeros(0, bool)
        return np.asarray(occluded(self.structure, o.astype(np.float32),
                                   d.astype(np.float32), kernel=self.kernel))

    def contains_points(self, points):
        """bool [N]: is each point inside the (closed) mesh?

        Crossing parity along a ray, as trimesh's: a point inside its bounding box casts a
        ray forward and one backward; an odd count of crossings is inside. Where the two
        disagree (an open mesh, a point on the surface) and neither ray leaves into free
        space, the point is tried again along other directions; a point still undecided
        takes the forward ray's answer. A point outside the bounding box is outside. A
        point on the surface (which trimesh leaves undefined) does not cross its own face
        (a hit needs ``t > 0``): on a convex mesh it is outside."""
        points = np.asarray(points, dtype=np.float64)
        if points.size == 0:
            return np.zeros(0, bool)
        if points.ndim != 2 or points.shape[1] != 3:
            raise ValueError(f"points must have shape [N, 3], got {points.shape}")
        lo, hi = np.asarray(self.mesh.bounds, np.float64)
        contains = np.zeros(len(points), bool)
        todo = np.flatnonzero(np.all((points >= lo) & (points <= hi), axis=1))
        for k, direction in enumerate([CONTAINS_DIRECTION, *RETRY_DIRECTIONS]):
            if todo.size == 0:
                break
            p = points[todo]
            both = np.concatenate([np.tile(direction, (len(p), 1)),
                                   np.tile(-direction, (len(p), 1))]).astype(np.float32)
            record = all_hits(self.structure, np.concatenate([p, p]).astype(np.float32),
                              both, CONTAINS_HITS, kernel=self.kernel)
            forward, backward = np.asarray(record.count).reshape(2, -1)
            odd = forward % 2 == 1
            # Agreeing rays, or the last direction, decide by parity; a ray that leaves
            # into free space (no hit) decides "outside".
            trusted = (odd == (backward % 2 == 1)) | (k == len(RETRY_DIRECTIONS))
            decided = trusted | (forward == 0) | (backward == 0)
            contains[todo[decided]] = (odd & trusted)[decided]
            todo = todo[~decided]
        return contains
