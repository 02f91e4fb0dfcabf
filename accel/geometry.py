"""Host-side geometry helpers shared by the builders (NumPy only)."""

from __future__ import annotations

import numpy as np


def mesh_arrays(vertices, faces) -> tuple[np.ndarray, np.ndarray]:
    """``vertices`` [V, 3] and ``faces`` [F, 3] as arrays, refused with the shape or the face
    index that is wrong (every builder and ``jrt.corner_normals`` index vertices by faces)."""
    vertices = np.asarray(vertices)
    faces = np.asarray(faces)
    if vertices.ndim != 2 or vertices.shape[1] != 3:
        raise ValueError(f"vertices must have shape [V, 3], got {vertices.shape}")
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"faces must have shape [F, 3], got {faces.shape}")
    if faces.size and (faces.min() < 0 or faces.max() >= len(vertices)):
        raise ValueError(f"face indices must be in 0..{len(vertices) - 1}, got "
                         f"{int(faces.min())}..{int(faces.max())}")
    return vertices, faces


def triangle_vertices(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """float32 [F, 3, 3]: the three corners of every face."""
    return np.ascontiguousarray(np.asarray(vertices, np.float32)[np.asarray(faces)])


def doubled_areas(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """float64 [F]: |(x_j - x_i) x (x_k - x_i)| (seed, Proposition 3.1), twice the area.

    Evaluated in float64 from the float32 corners, so that "zero" means the corners are
    truly collinear (or repeated) in the stored float32 geometry.
    """
    corners = triangle_vertices(vertices, faces).astype(np.float64)
    normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    return np.linalg.norm(normal, axis=1)


def degenerate_mask(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """bool [F]: faces of zero area (repeated or collinear corners). They are never hit.

    The cross product's components are written out (``np.cross`` ran 4x slower), and its
    squared norm compared with 0, as ``doubled_areas(...) == 0`` does."""
    c = triangle_vertices(vertices, faces).astype(np.float64)
    e1, e2 = c[:, 1] - c[:, 0], c[:, 2] - c[:, 0]
    x = e1[:, 1] * e2[:, 2] - e1[:, 2] * e2[:, 1]
    y = e1[:, 2] * e2[:, 0] - e1[:, 0] * e2[:, 2]
    z = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    return x * x + y * y + z * z == 0.0


def bounds(vertices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(lower, upper) corners of the axis-aligned bounding box, float32 [3] each."""
    v = np.asarray(vertices, np.float32)
    return v.min(axis=0), v.max(axis=0)


def frame_origin(triangles: np.ndarray) -> np.ndarray:
    """float32 [3]: the origin of a structure's local frame, the point of the triangles'
    bounding box nearest the coordinate origin (the origin itself when the box holds it,
    zeros when there are no triangles).

    Cells, planes and boxes are built and stored relative to it, and the traversal moves
    each ray's origin into the same frame (``o - frame``, ``jrt.engine``). Every margin
    (:data:`CELL_MARGIN` here, ``jrt.engine.BOX_MARGIN`` there) grows with the magnitude
    of the coordinates it protects. Measured from a point of the scene's own box, that
    magnitude is at most the box's diagonal (plus the ray origin's distance from the
    box), not where the scene happens to sit: a mesh 1e3 or 1e6 times its size away from
    the coordinate origin builds the same cells, with as many references, as at the
    origin. A scene whose box holds the coordinate origin keeps world coordinates (the
    frame is 0, and nothing is rounded), so detail near the origin keeps its resolution
    too. The triangle kernels read the stored float32 triangles in world coordinates, so
    the hits stay brute force's.
    """
    tri = np.asarray(triangles, np.float32).reshape(-1, 3)
    if tri.shape[0] == 0:
        return np.zeros(3, np.float32)
    columns = np.ascontiguousarray(tri.T)  # a reduction along axis 0 of [N, 3] ran 10x slower
    return np.clip(np.float32(0), columns.min(axis=1), columns.max(axis=1)).astype(np.float32)


def local_corners(triangles: np.ndarray, frame: np.ndarray) -> np.ndarray:
    """float64 [..., 3]: ``triangles - frame``, exactly.

    Both are float32, so their difference has at most 24 significant bits plus the
    exponent gap between them, and float64 holds it exactly whenever that gap is under 29
    binades, and exactly (0 is subtracted) when the frame is the coordinate origin. A gap
    larger than that needs a corner within 2^-29 of the frame's magnitude of 0 while the
    frame, a point of the box nearest 0, is not 0: on that axis the box then holds both,
    so the frame's magnitude is at most the box's extent, and the difference is rounded by
    at most 2^-53 of it, 2^-37 of any margin (2^-16 of the extent). The builders decide
    every reference on these coordinates.
    """
    return np.asarray(triangles, np.float32).astype(np.float64) - np.asarray(
        frame, np.float32).astype(np.float64)


def local_frame(triangles: np.ndarray):
    """A structure's frame and its geometry there: (``frame`` float32 [3], the corners
    ``triangles - frame`` exactly, float64 [T, 3, 3], their box float32 [2, 3] rounded
    outward so that it holds every corner; zeros when there are no triangles)."""
    frame = frame_origin(triangles)
    corners = local_corners(triangles, frame)
    if not corners.shape[0]:
        return frame, corners, np.zeros((2, 3), np.float32)
    # One column at a time (a strided 1-D reduction): NumPy reduces [T, 3, 3] over its
    # first two axes 20x slower (6 ms a bound on the camel).
    rows = corners.reshape(-1, 3)
    lo = np.array([rows[:, i].min() for i in range(3)])
    hi = np.array([rows[:, i].max() for i in range(3)])
    return frame, corners, np.stack([float32_down(lo), float32_up(hi)]).astype(np.float32)


def float32_down(x: np.ndarray) -> np.ndarray:
    """The largest float32 <= x (float64 in): a lower bound stored in float32."""
    x = np.asarray(x, np.float64)
    y = x.astype(np.float32)
    return np.where(y.astype(np.float64) > x, np.nextafter(y, np.float32(-np.inf)), y)


def float32_up(x: np.ndarray) -> np.ndarray:
    """The smallest float32 >= x (float64 in): an upper bound stored in float32."""
    x = np.asarray(x, np.float64)
    y = x.astype(np.float32)
    return np.where(y.astype(np.float64) < x, np.nextafter(y, np.float32(np.inf)), y)


#: Relative widening of a cell (a node's region, a grid cell) when deciding which
#: triangles it references. A triangle whose hit point lies within this distance of a
#: cell is referenced by the cell, so the few ulps by which a kernel's computed hit point
#: strays from the triangle (and a ray's computed crossing of a cell face) never let a
#: hit fall between two cells. Matches the traversal's ``jrt.engine.BOX_MARGIN``.
CELL_MARGIN = 2.0**-16


def triangle_boxes(corners: np.ndarray):
    """(lo, hi) [T, 3]: each triangle's bounding box (corners [T, 3, 3]), elementwise over
    its three corners (a reduction along the short middle axis is a strided loop per row:
    20 ms against a few on the camel)."""
    v0, v1, v2 = corners[:, 0], corners[:, 1], corners[:, 2]
    return np.minimum(np.minimum(v0, v1), v2), np.maximum(np.maximum(v0, v1), v2)


def triangle_extents(corners: np.ndarray) -> np.ndarray:
    """float64 [T]: the largest side of each triangle's bounding box (corners [T, 3, 3])."""
    c = np.asarray(corners, np.float64)
    if not c.shape[0]:
        return np.zeros(0)
    lo, hi = triangle_boxes(c)
    side = hi - lo
    return np.maximum(np.maximum(side[:, 0], side[:, 1]), side[:, 2])


def reference_margin(size, extent):
    """How far outside a cell a triangle is still referenced by it: :data:`CELL_MARGIN` of
    the cell's ``size`` (along the axis or normal in question) plus the triangle's own
    ``extent`` (:func:`triangle_extents`), broadcast.

    This is what the margin protects, and nothing else: a kernel's computed hit point
    strays from the triangle by its rounding, a few 2^-24 of the distances it subtracts
    (``v - o``, Woop et al.'s shear; at most ``gamma_n (|q - o| + extent)``, q the hit
    point). The part that grows with the ray's travel ``|q - o|`` is covered at run time,
    where the ray is known: the traversals widen every plane and box by ``BOX_MARGIN``
    (2^-16) of the origin's and the plane's magnitude in the structure's frame, and every
    interval by 2^-16 of t (``jrt.engine``). The part that grows with the triangle's
    size is covered here, 2^-16 of it (32 times gamma_5 of float32). Neither depends on
    where the scene sits, nor on how far apart its objects are: two camels 1e3 apart
    build the cells of one camel twice, with no more references.
    """
    return CELL_MARGIN * (np.asarray(size, np.float64) + np.asarray(extent, np.float64))


def widen_boxes(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Boxes [..., 3] grown by :data:`CELL_MARGIN` of their corners' magnitude and size.

    float64 in, float64 out: the margin scales with ``|corner|`` (the rounding of a point
    is relative to its magnitude) plus the box's extent on that axis.
    """
    lo = np.asarray(lo, np.float64)
    hi = np.asarray(hi, np.float64)
    size = np.maximum(hi - lo, 0.0)
    return (lo - CELL_MARGIN * (np.abs(lo) + size),
            hi + CELL_MARGIN * (np.abs(hi) + size))


def triangles_overlap_boxes(triangles: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """bool [K]: does triangle k touch the closed box [lo[k], hi[k]]? Exact in float64.

    The separating axis test of Akenine-Möller ("Fast 3D triangle-box overlap testing",
    JGT 2001): the triangle and the box are disjoint iff their projections on one of 13
    axes are: the box's 3 face normals, the triangle's normal, and the 9 cross products
    of a box edge direction with a triangle edge. Touching counts as overlapping (the
    comparisons are strict), so a triangle lying in a box face belongs to the box. A
    degenerate triangle (zero normal, parallel edges) is tested by the same axes; the
    zero axes separate nothing, so it is kept whenever its bounds touch the box, which
    is conservative. Vectorised over K (triangles [K, 3, 3], boxes [K, 3]); computed by
    :func:`overlap_rows`.
    """
    tri = np.asarray(triangles, np.float64)
    corners = np.ascontiguousarray(tri.reshape(-1, 9).T)  # row 3 i + a: corner i, axis a
    return overlap_rows(corners, np.asarray(lo, np.float64).T, np.asarray(hi, np.float64).T)


#: Pairs per block of the separating-axis test (``overlap_rows``): small enough for its
#: temporaries (8 bytes a pair each) to stay in a core's cache.
_SAT_BLOCK = 1 << 15


def overlap_rows(corners: np.ndarray, lo, hi) -> np.ndarray:
    """bool [K]: :func:`triangles_overlap_boxes` on component rows, the layout the
    builders hold their corners in.

    ``corners`` float64 [9, K] (row ``3 i + a``: corner i's coordinate on axis a), ``lo``
    and ``hi`` three float64 [K] rows (or [3, K]). The 13 separating axes: ``unit_a x e``
    has one zero and two signed components of ``e``, so its projections are two products.
    It works on contiguous [K] rows (no [K, 3] reductions, ``np.cross`` or ``einsum``,
    which ran an order of magnitude slower), and tests each axis only on the pairs no
    earlier axis separated (the answer is the AND of all the axes, so the order of
    elimination does not change it). The pairs go through in blocks of ``_SAT_BLOCK``,
    whose few dozen temporaries stay in the cache (on the camel's octree this halved the
    time of the test).
    """
    out = np.empty(corners.shape[1], bool)
    for start in range(0, corners.shape[1], _SAT_BLOCK):
        part = slice(start, start + _SAT_BLOCK)
        out[part] = _overlap_block(corners[:, part], [b[part] for b in lo],
                                   [b[part] for b in hi])
    return out


def _overlap_block(corners, lo, hi):
    """``overlap_rows`` on one block."""
    k = corners.shape[1]
    centre = [0.5 * (lo[a] + hi[a]) for a in range(3)]
    half = [0.5 * (hi[a] - lo[a]) for a in range(3)]
    v = [corners[3 * i + a] - centre[a] for i in range(3) for a in range(3)]
    # 1. The box's faces: the triangle's bounds against the box's.
    keep = np.ones(k, bool)
    for a in range(3):
        keep &= np.minimum(np.minimum(v[a], v[3 + a]), v[6 + a]) <= half[a]
        keep &= np.maximum(np.maximum(v[a], v[3 + a]), v[6 + a]) >= -half[a]
    alive = np.flatnonzero(keep)
    v = [c[alive] for c in v]
    hx, hy, hz = (h[alive] for h in half)
    # 2. The triangle's normal, e0 x e1 (np.cross's products and order).
    e = [[v[3 * ((j + 1) % 3) + a] - v[3 * j + a] for a in range(3)] for j in range(3)]
    (e0x, e0y, e0z), (e1x, e1y, e1z) = e[0], e[1]
    nx, ny, nz = e0y * e1z - e0z * e1y, e0z * e1x - e0x * e1z, e0x * e1y - e0y * e1x
    radius = np.abs(nx) * hx + np.abs(ny) * hy + np.abs(nz) * hz
    offset = nx * v[0] + ny * v[1] + nz * v[2]
    ok = np.abs(offset) <= radius
    # 3. unit_a x e_j: x: (0, -ez, ey); y: (ez, 0, -ex); z: (-ey, ex, 0). The pairs still
    # undecided are gathered after each group of three axes (and after the normal's).
    for a in range(3):
        sel = np.flatnonzero(ok)
        alive, ok = alive[sel], ok[sel]
        v = [c[sel] for c in v]
        e = [[c[sel] for c in ej] for ej in e]
        hx, hy, hz = hx[sel], hy[sel], hz[sel]
        for j in range(3):
            ex, ey, ez = e[j]
            if a == 0:
                p = [ey * v[3 * i + 2] - ez * v[3 * i + 1] for i in range(3)]
                r = np.abs(ez) * hy + np.abs(ey) * hz
            elif a == 1:
                p = [ez * v[3 * i] - ex * v[3 * i + 2] for i in range(3)]
                r = np.abs(ez) * hx + np.abs(ex) * hz
            else:
                p = [ex * v[3 * i + 1] - ey * v[3 * i] for i in range(3)]
                r = np.abs(ey) * hx + np.abs(ex) * hy
            ok &= np.minimum(np.minimum(p[0], p[1]), p[2]) <= r
            ok &= np.maximum(np.maximum(p[0], p[1]), p[2]) >= -r
    keep[:] = False
    keep[alive[ok]] = True
    return keep


#: The fewest bits a leaf reference gives its count (leaves of up to 15 rows). The bits
#: are part of a structure's static layout, so each value compiles a traversal of its own:
#: with this floor the structures of small meshes, whose largest leaves hold 1 to 15 rows,
#: share one (``jrt.trace.padded_structure`` pads their arrays to the same lengths).
MIN_LEAF_BITS = 4


def leaf_bits_for(first: np.ndarray, count: np.ndarray, slots: int) -> int:
    """Bits for a leaf's count in a leaf reference ``~((first << bits) | count)``, from the
    leaves' ``first`` rows and ``count`` (entries of count 0 encode nothing): enough for the
    largest count, and at least :data:`MIN_LEAF_BITS` where that fits ``slots``, the number
    of rows (triangles or references) the leaves point into.

    Raises when some leaf's code would not fit in an int32. Only the leaves' largest first
    row bounds that: a tree whose root is one leaf of every row has 0.
    """
    max_count = int(np.max(count, initial=0))
    bits = max(max_count.bit_length(), 1)
    max_first = int(np.max(np.where(np.asarray(count) > 0, first, 0), initial=0))
    if (max_first + 1) << bits >= 2**31:
        raise ValueError(f"{slots} leaf rows with leaves of up to {max_count} do not fit "
                         "an int32 leaf reference")
    if (int(slots) + 1) << MIN_LEAF_BITS < 2**31:
        bits = max(bits, MIN_LEAF_BITS)
    return bits


def leaf_references(first: np.ndarray, count: np.ndarray, bits: int) -> np.ndarray:
    """int32 leaf references ``~((first << bits) | count)`` (negative; count 0: empty)."""
    first = np.asarray(first, np.int64)
    count = np.asarray(count, np.int64)
    return (~((first << bits) | count)).astype(np.int32)
