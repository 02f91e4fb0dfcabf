"""Shading normals: per-corner normals smoothed across soft edges only ("auto smooth").

A triangle mesh samples a surface that is smooth in places and creased in others (a box's
edges, a fan's rim, a CAD part's fillets against its flat faces). Interpolating one normal
per vertex rounds every crease into a blob with a dark seam; one normal per face shows every
facet. The usual compromise of modelling tools (Blender's "auto smooth", 3ds Max smoothing
groups) is a normal per *corner* (face, vertex), averaged only over the faces around that
vertex whose normal lies within a crease angle of the corner's own face normal:

    n(f, k) = normalise( sum over faces g around vertex v = faces[f, k] with
                         angle(n_g, n_f) <= crease of  alpha(g, v) * n_g )

with ``n_g`` the unit normal of face g and ``alpha(g, v)`` the angle of g at its corner v.

**Merged by position.** "Around the vertex" means around the *position*: vertices are merged
by exact float32 coordinates (``np.unique`` on rows, -0.0 taken as 0.0) before the faces are
gathered, so an STL file (every triangle has its own three vertices) and an OBJ file of the
same surface (shared vertices) get the same normals, summed in the same order.

**Angle weighting** (Thürmer & Wüthrich, "Computing vertex normals from polygonal facets",
J. Graphics Tools 3(1), 1998): a face counts by the angle it spans at the vertex, so the
normal depends on the surface around the vertex and not on how it was cut into triangles: a
flat polygon split into triangles that all meet at the vertex weighs as the polygon itself
(the angles add up), whereas area weighting would favour whichever triangle reaches
farthest from the vertex (the long thin triangles of CAD tessellations). On a finely
tessellated smooth surface both converge to the true normal.

**Degenerate faces.** A face of zero area (``cross(e1, e2) == 0`` in float64) has no normal:
it gives no weight to its neighbours, and its own corners take the angle-weighted mean of the
faces around the position (no crease test: it has no direction to compare), or +z where no
face of non-zero area shares the position. Such faces are never hit (:mod:`jrt.mesh`); the
rule only keeps every output a unit vector, never NaN.

Cost: ``sum over positions of valence**2`` face pairs (about six per corner on a closed
mesh; a fan of k triangles around one vertex adds k**2), processed in bounded batches on the
host (NumPy, float64), once per mesh.

**Moving vertices.** Which faces smooth into a corner is decided by the crease test, a
piecewise constant function of the vertices. :func:`smoothing_pairs` records those
decisions; :func:`corner_normals_from_pairs` evaluates the same sums for any vertex
positions in JAX (float32), so that a renderer whose vertices are parameters shades the
moved mesh and differentiates its normals, the crease decisions held fixed.
"""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from accel.geometry import mesh_arrays

#: Default crease angle in degrees (Blender's auto-smooth default is 30°).
DEFAULT_CREASE_ANGLE = 30.0

#: Face pairs handled per NumPy batch (bounds the temporary memory to about 150 MB).
_PAIRS_PER_BATCH = 1 << 20

#: Slack on the cosine test, so that coplanar faces pass with crease 0 despite rounding.
_COS_SLACK = 1e-12


def _check_angle(crease_angle) -> float:
    try:
        angle = float(crease_angle)
    except (TypeError, ValueError):
        raise ValueError(f"crease_angle must be a number of degrees in [0, 180], "
                         f"got {crease_angle!r}") from None
    if isinstance(crease_angle, bool) or not 0.0 <= angle <= 180.0:
        raise ValueError(f"crease_angle must be a number of degrees in [0, 180], "
                         f"got {crease_angle!r}")
    return angle


def merged_corners(vertices: Float[np.ndarray, "v 3"],
                   faces: Int[np.ndarray, "f 3"]) -> Int[np.ndarray, "f 3"]:
    """int64 [F, 3]: for each corner, the index of its position among the distinct vertex
    positions (exact coordinates, sorted; -0.0 equals 0.0)."""
    v = np.asarray(vertices, np.float64) + 0.0  # -0.0 + 0.0 == +0.0: one key per position
    _, inverse = np.unique(v, axis=0, return_inverse=True)
    return inverse.reshape(-1)[np.asarray(faces, np.int64)]


def face_geometry(vertices, faces) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """float64 unit face normals [F, 3] (0 for degenerate faces), corner angles [F, 3]
    (radians, 0 for degenerate faces) and the bool [F] mask of faces with non-zero area."""
    p = np.asarray(vertices, np.float64)[np.asarray(faces, np.int64)]  # [F, 3, 3]
    n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    length = np.linalg.norm(n, axis=1)
    valid = (length > 0) & np.isfinite(length)
    unit = np.where(valid[:, None], n / np.where(valid, length, 1.0)[:, None], 0.0)
    e_next = p[:, [1, 2, 0]] - p  # corner k to corner k+1
    e_prev = p[:, [2, 0, 1]] - p  # corner k to corner k-1
    angle = np.arctan2(np.linalg.norm(np.cross(e_next, e_prev), axis=2),
                       (e_next * e_prev).sum(axis=2))
    return unit, np.where(valid[:, None], angle, 0.0), valid


def _corner_pairs(vertices, faces, angle: float, unit, valid):
    """Batches ``(first, last, query, partner, keep)`` of the corner pairs sharing a
    position, for the corners ``[first, last)`` (corner ``c = 3 f + k``): each query
    corner with every corner at its position, its own included, and whether the partner's
    face is smoothed into it (within the crease of the query's face; a degenerate face
    takes every neighbour). Batches of about ``_PAIRS_PER_BATCH`` pairs bound the memory."""
    n_corners = 3 * len(faces)
    cos_t = math.cos(math.radians(angle)) - _COS_SLACK
    # Corners grouped by position (stable: by face, then corner, in a group).
    group = merged_corners(vertices, faces).reshape(-1)
    order = np.argsort(group, kind="stable")
    size = np.bincount(group)
    start = np.concatenate([[0], np.cumsum(size)[:-1]])
    pairs = size[group]  # partners of each corner: every corner at its position
    ends = np.cumsum(pairs)
    first = 0
    while first < n_corners:
        # The corners [first, last) whose partners fit one batch (at least one corner).
        base = ends[first - 1] if first else 0
        last = max(int(np.searchsorted(ends, base + _PAIRS_PER_BATCH, side="right")),
                   first + 1)
        count = pairs[first:last]
        query = np.repeat(np.arange(first, last), count)
        offset = np.arange(len(query)) - np.repeat(np.cumsum(count) - count, count)
        partner = order[start[group[query]] + offset]
        f_query, f_partner = query // 3, partner // 3
        cos = (unit[f_query] * unit[f_partner]).sum(axis=1)
        keep = (cos >= cos_t) | (f_query == f_partner) | ~valid[f_query]
        yield first, last, query, partner, keep
        first = last


def corner_normals(
    vertices: Float[np.ndarray, "v 3"],
    faces: Int[np.ndarray, "f 3"],
    crease_angle: float = DEFAULT_CREASE_ANGLE,
) -> Float[np.ndarray, "f 3 3"]:
    """float32 [F, 3, 3]: the unit shading normal of corner k of face f (see the module doc).

    ``crease_angle`` in degrees, [0, 180]: faces meeting at a vertex are smoothed together
    when their normals differ by at most this angle; 0 gives flat faces, 180 smooths
    everything (angle-weighted vertex normals on merged positions, except that a face
    folded back against its neighbours, whose sum turns away from it, shades flat). At a
    hit with barycentrics (u, v) the shading normal is ``normalise((1-u-v) n0 + u n1 + v n2)``.
    """
    angle = _check_angle(crease_angle)
    vertices, faces = mesh_arrays(vertices, faces)
    n_faces = len(faces)
    if n_faces == 0:
        return np.zeros((0, 3, 3), np.float32)
    unit, weight, valid = face_geometry(vertices, faces)
    flat_weight = weight.reshape(-1)
    total = np.zeros((3 * n_faces, 3))
    for first, last, query, partner, keep in _corner_pairs(vertices, faces, angle, unit, valid):
        w = np.where(keep, flat_weight[partner], 0.0)
        for axis in range(3):
            total[first:last, axis] = np.bincount(
                query - first, weights=w * unit[partner // 3, axis], minlength=last - first)
    total = total.reshape(n_faces, 3, 3)
    length = np.linalg.norm(total, axis=2, keepdims=True)
    out = total / np.where(length > 0, length, 1.0)
    # Fallbacks: a face whose weighted sum vanishes or turns against its own normal (faces
    # folded back on each other, with a crease near 180) shades flat; a corner with nothing
    # at all (a degenerate face alone at its position) gets +z.
    facing = (out * unit[:, None, :]).sum(axis=2)
    flat = valid[:, None] & ((length[..., 0] == 0) | (facing <= 0))
    out = np.where(flat[..., None], unit[:, None, :], out)
    empty = ~valid[:, None] & (length[..., 0] == 0)
    out = np.where(empty[..., None], np.array([0.0, 0.0, 1.0]), out)
    return out.astype(np.float32)


def smoothing_pairs(vertices: Float[np.ndarray, "v 3"], faces: Int[np.ndarray, "f 3"],
                    crease_angle: float = DEFAULT_CREASE_ANGLE) -> Int[np.ndarray, "2 p"]:
    """int32 [2, P]: the pairs ``(corner, partner)`` that :func:`corner_normals` sums, the
    partner's face smoothed into the corner's (corners ``c = 3 f + k``; every corner is
    its own partner). With them held fixed, :func:`corner_normals_from_pairs` gives the
    corner normals of moved vertices as a differentiable JAX function: which faces smooth
    together is piecewise constant in the vertices, as a ray's hit triangle is."""
    angle = _check_angle(crease_angle)
    vertices, faces = mesh_arrays(vertices, faces)
    if len(faces) == 0:
        return np.zeros((2, 0), np.int32)
    unit, _, valid = face_geometry(vertices, faces)
    kept = [np.stack([query[keep], partner[keep]])
            for _, _, query, partner, keep in _corner_pairs(vertices, faces, angle, unit, valid)]
    return np.concatenate(kept, axis=1).astype(np.int32)


def corner_normals_from_pairs(vertices: Float[Array, "v 3"], faces: Int[Array, "f 3"],
                              pairs: Int[Array, "2 p"]) -> Float[Array, "f 3 3"]:
    """float32 [F, 3, 3]: :func:`corner_normals` in JAX, for the smoothing ``pairs`` of
    :func:`smoothing_pairs` (the faces smoothed together held fixed): the same
    angle-weighted sums and fallbacks, in float32, differentiable with respect to the
    vertices. NaN-free: a degenerate face's normal and angles, and a vanishing sum, are
    masked on their inputs before any division or square root (the "double where")."""
    p = jnp.asarray(vertices, jnp.float32)[faces]  # [F, 3, 3]
    cross = jnp.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    square = jnp.sum(cross * cross, axis=1)
    valid = square > 0
    unit = jnp.where(valid[:, None],
                     cross / jnp.sqrt(jnp.where(valid, square, 1.0))[:, None], 0.0)
    e_next, e_prev = p[:, (1, 2, 0)] - p, p[:, (2, 0, 1)] - p
    sine = jnp.cross(e_next, e_prev)
    sine = jnp.sum(sine * sine, axis=2)  # > 0 at every corner of a face of non-zero area
    ok = valid[:, None] & (sine > 0)
    angle = jnp.where(ok, jnp.arctan2(jnp.sqrt(jnp.where(ok, sine, 1.0)),
                                      jnp.where(ok, jnp.sum(e_next * e_prev, axis=2), 1.0)),
                      0.0)
    corner, partner = pairs[0], pairs[1]
    total = jnp.zeros((3 * faces.shape[0], 3), jnp.float32).at[corner].add(
        angle.reshape(-1)[partner][:, None] * unit[partner // 3])
    total = total.reshape(-1, 3, 3)
    square = jnp.sum(total * total, axis=2)
    some = square > 0
    out = jnp.where(some[..., None],
                    total / jnp.sqrt(jnp.where(some, square, 1.0))[..., None], 0.0)
    facing = jnp.sum(out * unit[:, None, :], axis=2)
    flat = valid[:, None] & (~some | (facing <= 0))
    out = jnp.where(flat[..., None], unit[:, None, :], out)
    empty = ~valid[:, None] & ~some
    return jnp.where(empty[..., None], jnp.float32([0.0, 0.0, 1.0]), out)


def crease_edges(vertices: Float[np.ndarray, "v 3"], faces: Int[np.ndarray, "f 3"],
                 crease_angle: float = DEFAULT_CREASE_ANGLE) -> tuple[int, int, np.ndarray]:
    """(creases, edges, dihedral): how many interior edges (two faces of non-zero area
    sharing the two positions) have a dihedral angle above ``crease_angle`` degrees, how
    many interior edges there are, and float64 [E] the angle (degrees) between the two face
    normals of each such edge. A non-manifold edge (three faces or more) counts each pair
    of faces adjacent in the sorted order."""
    angle = _check_angle(crease_angle)
    unit, _, valid = face_geometry(vertices, faces)
    corner = merged_corners(vertices, faces)
    a, b = corner, corner[:, [1, 2, 0]]
    key = np.stack([np.minimum(a, b), np.maximum(a, b)], axis=-1).reshape(-1, 2)
    face = np.repeat(np.arange(len(faces)), 3)
    keep = valid[face] & (key[:, 0] != key[:, 1])
    key, face = key[keep], face[keep]
    order = np.lexsort((key[:, 1], key[:, 0]))
    key, face = key[order], face[order]
    same = np.all(key[1:] == key[:-1], axis=1)
    cos = np.clip((unit[face[1:]] * unit[face[:-1]]).sum(axis=1)[same], -1.0, 1.0)
    dihedral = np.degrees(np.arccos(cos))
    return int((dihedral > angle).sum()), int(len(dihedral)), dihedral


__all__ = ["DEFAULT_CREASE_ANGLE", "corner_normals", "corner_normals_from_pairs",
           "crease_edges", "face_geometry", "merged_corners", "smoothing_pairs"]
