"""Host-side geometry helpers shared by the builders (NumPy only)."""

from __future__ import annotations

import numpy as np


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
    """bool [F]: faces of zero area (repeated or collinear corners). They are never hit."""
    return doubled_areas(vertices, faces) == 0.0


def bounds(vertices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(lower, upper) corners of the axis-aligned bounding box, float32 [3] each."""
    v = np.asarray(vertices, np.float32)
    return v.min(axis=0), v.max(axis=0)


#: Relative widening of a cell (a node's region, a grid cell) when deciding which
#: triangles it references. A triangle whose hit point lies within this distance of a
#: cell is referenced by the cell, so the few ulps by which a kernel's computed hit point
#: strays from the triangle (and a ray's computed crossing of a cell face) never let a
#: hit fall between two cells. Matches the traversal's ``jrt.engine.BOX_MARGIN``.
CELL_MARGIN = 2.0**-16


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
    is conservative. Vectorised over K (triangles [K, 3, 3], boxes [K, 3]).
    """
    tri = np.asarray(triangles, np.float64)
    lo = np.asarray(lo, np.float64)
    hi = np.asarray(hi, np.float64)
    center = 0.5 * (lo + hi)
    half = 0.5 * (hi - lo)
    v = tri - center[:, None, :]  # the box centred at the origin
    # 1. Box face normals: the triangle's bounds against the box's.
    overlap = np.all((v.min(axis=1) <= half) & (v.max(axis=1) >= -half), axis=1)
    # 2. The triangle's normal.
    e = np.stack([v[:, 1] - v[:, 0], v[:, 2] - v[:, 1], v[:, 0] - v[:, 2]], axis=1)
    normal = np.cross(e[:, 0], e[:, 1])
    radius = np.sum(np.abs(normal) * half, axis=1)
    offset = np.sum(normal * v[:, 0], axis=1)
    overlap &= np.abs(offset) <= radius
    # 3. Cross products of the box's axes with the triangle's edges.
    for axis in range(3):
        unit = np.zeros(3)
        unit[axis] = 1.0
        for edge in range(3):
            a = np.cross(unit, e[:, edge])  # [K, 3]
            p = np.einsum("kj,kij->ki", a, v)  # the three corners projected
            r = np.sum(np.abs(a) * half, axis=1)
            overlap &= (p.min(axis=1) <= r) & (p.max(axis=1) >= -r)
    return overlap


def leaf_bits_for(max_count: int, slots: int) -> int:
    """Bits for a leaf's count in a leaf reference ``~((first << bits) | count)``.

    ``slots`` is the number of rows (triangles or references) a leaf's ``first`` may
    point into. Raises when the code would not fit in an int32.
    """
    bits = max(int(max_count).bit_length(), 1)
    if (int(slots) + 1) << bits >= 2**31:
        raise ValueError(f"{slots} leaf rows with leaves of up to {max_count} do not fit "
                         "an int32 leaf reference")
    return bits


def leaf_references(first: np.ndarray, count: np.ndarray, bits: int) -> np.ndarray:
    """int32 leaf references ``~((first << bits) | count)`` (negative; count 0: empty)."""
    first = np.asarray(first, np.int64)
    count = np.asarray(count, np.int64)
    return (~((first << bits) | count)).astype(np.int32)
