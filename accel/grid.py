"""Uniform grid: the density rule, cell lists in compressed-row form, empty-space distances.

**Resolution** (Cleary & Wyvill, "Analysis of an algorithm for fast ray tracing using
uniform space subdivision", The Visual Computer 1988, show O(N) cells to be the right
order; the grid papers of Wald, Ize, Kensler, Knoll & Parker, "Ray tracing animated scenes
using coherent grid traversal", SIGGRAPH 2006, and Ize, Wald, Robertson & Parker, "An
evaluation of parallel grid construction for ray tracing dynamic scenes", RT 2006, choose
the resolution by this density rule): about ``density * N`` cells in all for N
triangles, shared out in proportion to the box's extents,

    n_a = ceil(extent_a * cbrt(density * N / volume))        (a = x, y, z),

clamped to ``[1, max_resolution]``. A flat or thin box (an axis that would get less than
one cell, such as the zero extent of a planar mesh) gets one cell on that axis, and the
``density * N`` cells are shared out over the other axes instead (``ceil(extent_a *
sqrt(density * N / area))`` for a planar mesh), so the volume never divides by zero.

**Local frame**: the grid is built and stored relative to ``frame =
accel.geometry.frame_origin(triangles)`` (a point of the triangles' bounding box: the one
nearest the coordinate origin, 0 when the box holds it). Every geometric decision (the
box, the resolution, the cell planes, the margins, which cells reference which triangles)
is taken on the corners ``triangles - frame``, exact in float64 (``accel.geometry.
local_corners``), and the grid row holds local coordinates; the traversal moves each ray
into the frame (``o - frame``, ``jrt.engine``), while the triangle kernels keep reading
the stored world-coordinate ``triangles``, so the hits stay brute force's. Why: every
margin below is relative to the magnitude of the coordinates it protects, and in world
coordinates a scene far from the coordinate origin got margins of its distance, not of
its size (the camel, 69k triangles 1.4 units across, moved by (1000, -700, 1300): 74 s,
125 MB and 171,873 non-empty cells, against 0.5 s, 6.2 MiB and 27k at the origin). In
the frame the magnitudes are the scene's extent (and the ray origin's distance from the
frame), wherever the scene sits, and the build is translation-invariant. The margins
still cover what they must: the watertight and Möller–Trumbore kernels round relative to
``|v - o|`` (the corners seen from the ray origin), which does not depend on where the
scene sits, and moving the ray origin into the frame rounds it by 2^-24 of ``|o -
frame|``: an ulp of the origin's local coordinates, among the few ulps the margins cover
(``jrt.grid``), 2^-8 of the margin's 2^-16. (The plane-and-barycentric kernel rounds
``O + tD`` and ``d - N.O`` in world coordinates, by ulps of the scene's distance from the
coordinate origin: far from it, that kernel's hits can stray from the triangle by more
than the margins, and on such rays the grid may then differ from brute force.)

**Cells**: cell (i, j, k) is the box ``[P_x(i), P_x(i+1)] x [P_y(j), P_y(j+1)] x
[P_z(k), P_z(k+1)]`` (local coordinates) with the planes ``P_a(m) = lo_a + m * size_a``
evaluated in float32 as the traversal does (where XLA contracts it into a fused
multiply-add the plane moves by an ulp, which the widening absorbs). The box ``[lo, hi]``
is the bounds of the local corners rounded outward to float32 (``accel.geometry.
float32_down`` and ``float32_up``), so it holds every corner. A triangle is referenced by
every cell whose widened box it overlaps by the exact separating-axis test (``accel.
geometry.triangles_overlap_boxes`` on the float64 local corners, touching counts). The
widening is ``accel.geometry.widen_boxes`` (CELL_MARGIN = 2^-16 of the cell's corners
and size) plus CELL_MARGIN of the grid box's largest local corner coordinate (at least
half the box's largest extent, since the box holds the frame): near the frame a cell's
own corners are small, and the margin must still cover the rounding of the traversal's
crossing distances, a few ulps of the ray's travel through the scene (see ``jrt.grid``).
So a hit the walk meets in a cell, or a few ulps beside it, is never missed.

**Empty-space distances** (for the traversal's leaps, Cohen & Sheffer's "proximity
clouds", The Visual Computer 1994): every cell stores its Chebyshev distance in cells to
the nearest non-empty cell, capped at ``max_skip`` (0 for a non-empty cell), so the cube of
``2d - 1`` cells a side around a cell at distance ``d`` is empty. Computed level by level
by dilating the non-empty cells one cell at a time (three 1-D passes a level).

**Build** (vectorised NumPy, O(R log R) for R references, plus O(max_skip * cells)): per
axis the widened cell intervals; each triangle's candidate cells are the ranges of cells
whose widened interval meets the triangle's bounds on each axis (``np.searchsorted``),
narrowed slab by slab (``_candidates``): per x slab of cells the part of the triangle
inside the slab bounds its y and z cells, and per (x, y) column its part inside the y slab
bounds the z cells further, so a long thin triangle gets about the cells it crosses, not
every cell of its bounding box (the slivers scene, 1,000 needles: 21k candidates where
their boxes hold 421k; 50,000 needles: 3.9M where the boxes hold 738M, more than the
memory). The candidate (triangle, cell) pairs, enumerated with ``np.repeat`` over those
ranges, are tested with the separating-axis test (``accel.geometry.overlap_rows``; a
triangle with a single candidate cell lies in it and skips the test); one sort of the
keys (cell, triangle row) orders the surviving pairs by cell, rows ascending within a
cell.

**Layout** (``layout`` is empty: the resolution and the box travel in ``grid``, so every
grid of the same array shapes shares one compiled traversal):

``grid`` float32 [16], 64 bytes, in the local frame (coordinates relative to ``frame``):

    bytes  0-11  floats 0-2    lo: the grid box's lower corner (x, y, z), the bounds of
                               the local corners rounded down to float32 (0 for a mesh
                               without triangles)
    bytes 12-23  floats 3-5    hi: the box's upper corner, rounded up
    bytes 24-35  floats 6-8    size: the cell size per axis, float32((hi - lo) / n)
                               (0 on a flat axis)
    bytes 36-47  floats 9-11   inv_size: float32(n / (hi - lo)) (0 on a flat axis)
    bytes 48-59  floats 12-14  n: the resolution (nx, ny, nz), int32 bit patterns
    bytes 60-63  float  15     zero (padding to 64 bytes)

``cell_start`` int32 [nx * ny * nz + 1], 4 bytes a cell: cell ``c = i + nx * (j + ny * k)``
references the slots ``cell_start[c] .. cell_start[c+1] - 1`` of ``references``
(``cell_start[0] = 0``, non-decreasing, the last entry the number of references R).

``skip`` int8 [nx * ny * nz], 1 byte a cell: the empty-space distance above.

``references`` int32 [max(R, 1)], 4 bytes a reference: rows of ``triangles``, grouped by
cell, ascending within a cell (a mesh without triangles keeps one unused zero entry, so
that the traversal's gathers stay in range).

``triangles`` float32 [T, 3, 3] (36 bytes a row) and ``triangle_ids`` int32 [T] (4 bytes):
the non-degenerate faces in face order, as ``accel.brute`` (world coordinates).

``frame`` float32 [3], 12 bytes: the origin of the local frame in world coordinates
(``accel.geometry.frame_origin``; zeros for a mesh without triangles). The engine moves
every ray origin into it (``o - frame``) before the grid's box and cell tests.

**Parameters**: ``density`` (lambda; default 8: the upper end of the 1-8 range of the
papers above; pbrt's grid accelerator (Pharr & Humphreys, 1st and 2nd editions:
``round(3 cbrt(N) extent_a / max extent)`` cells per axis, clamped to 64) gives the camel,
unclamped, the same 38 x 121 x 123 cells as density 8 here; with the leaps over empty
cells, densities 4 to 32 traced the camel within the noise of a shared machine, about
15 %, of each other),
``max_resolution`` (cells per axis at most; default 512, which bounds a long thin scene's
grid) and ``max_skip`` (the cap on the stored distance; default 16: a step leaves an
empty cube of up to 31 cells a side, advancing up to 16 cells along an axis, and on the
camel a larger cap saves under 3 % of the steps; 0 or 1 stores no leap, and the traversal
is the plain cell-by-cell DDA).

**Grid cost** (the grid's counterpart of the SAH cost, with the BVH's constants C_T = 1/2
per cell visited and C_I = 1 per triangle test, no early termination, no leaps): a random
line meeting the grid box meets a convex cell inside it with probability ``area(cell) /
area(box)`` (Crofton's formula), so it visits ``E_cells = cells * area(cell) / area(box)``
cells and tests ``E_tests = R * area(cell) / area(box)`` triangles; ``sah_cost = C_T *
E_cells + C_I * E_tests``.
"""

from __future__ import annotations

import time

import numpy as np

from accel.geometry import (
    CELL_MARGIN,
    degenerate_mask,
    local_frame,
    overlap_rows,
    triangle_vertices,
    widen_boxes,
)
from accel.registry import StructureKind, world_planes
from accel.structure import Structure

#: Cells per triangle (lambda); see the module docstring.
DEFAULT_DENSITY = 8.0
#: Cells per axis at most.
DEFAULT_MAX_RESOLUTION = 512
MAX_RESOLUTION_LIMIT = 1024
#: Cap on the stored distance to the nearest non-empty cell (int8).
DEFAULT_MAX_SKIP = 16
MAX_SKIP_LIMIT = 127
#: The SAH constants of ``accel.bvh``, for a comparable cost.
TRAVERSAL_COST = 0.5
INTERSECTION_COST = 1.0
GRID_FLOATS = 16
#: Candidate (triangle, cell) pairs tested per separating-axis call (bounds the memory of
#: the float64 temporaries to a few hundred MB).
_CHUNK = 1 << 20
def _check_params(density, max_resolution, max_skip):
    if isinstance(density, bool) or not (
            isinstance(density, int | float | np.integer | np.floating)
            and np.isfinite(density) and 0 < density <= 1e4):
        raise ValueError(f"grid: density must be a positive finite number of at most 1e4, "
                         f"got {density!r}")
    if isinstance(max_resolution, bool) or not (
            isinstance(max_resolution, int | np.integer)
            and 1 <= max_resolution <= MAX_RESOLUTION_LIMIT):
        raise ValueError(f"grid: max_resolution must be an integer in "
                         f"[1, {MAX_RESOLUTION_LIMIT}], got {max_resolution!r}")
    if isinstance(max_skip, bool) or not (
            isinstance(max_skip, int | np.integer) and 0 <= max_skip <= MAX_SKIP_LIMIT):
        raise ValueError(f"grid: max_skip must be an integer in [0, {MAX_SKIP_LIMIT}], "
                         f"got {max_skip!r}")


def resolution(extent, count: int, density: float, max_resolution: int) -> np.ndarray:
    """int64 [3]: cells per axis for ``count`` triangles in a box of ``extent`` [3].

    The density rule of the module docstring: ``ceil(extent_a * s)`` with ``s`` chosen so
    that the cells number about ``density * count``; an axis that would get less than one
    cell (a flat or thin axis) gets one, and ``s`` is recomputed over the other axes.
    """
    extent = np.maximum(np.asarray(extent, np.float64), 0.0)
    res = np.ones(3, np.int64)
    if count == 0:
        return res
    cells = float(density) * count
    thick = extent > 0
    scale = 0.0
    for _ in range(3):  # at most three axes turn thin
        k = int(thick.sum())
        if k == 0:
            return res
        scale = (cells / np.prod(extent[thick])) ** (1.0 / k)
        still = thick & (extent * scale >= 1.0)
        if (still == thick).all():
            break
        thick = still
    if thick.any():
        res[thick] = np.ceil(np.minimum(extent[thick] * scale, max_resolution))
    return np.clip(res, 1, max_resolution)


def grid_row(lo: np.ndarray, hi: np.ndarray, res: np.ndarray) -> np.ndarray:
    """The ``grid`` array (layout in the module docstring)."""
    lo = np.asarray(lo, np.float32)
    hi = np.asarray(hi, np.float32)
    extent = hi.astype(np.float64) - lo.astype(np.float64)
    flat = extent <= 0
    row = np.zeros(GRID_FLOATS, np.float32)
    row[0:3], row[3:6] = lo, hi
    row[6:9] = np.where(flat, 0.0, extent / res)
    row[9:12] = np.where(flat, 0.0, res / np.where(flat, 1.0, extent))
    row.view(np.int32)[12:15] = res
    return row


def planes(lo: np.ndarray, size: np.ndarray, n: int) -> np.ndarray:
    """float32 [n + 1]: ``lo + m * size`` for m = 0..n, in float32 as the traversal."""
    return np.float32(lo) + np.arange(n + 1, dtype=np.float32) * np.float32(size)


def widened_intervals(row: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per axis, the widened float64 [n] lower and upper bounds of the cells.

    ``widen_boxes`` (CELL_MARGIN of the cell's corners and size) plus CELL_MARGIN of the
    grid box's largest corner coordinate, all in the local frame (the row's coordinates):
    near the frame a cell's own corners are small, and the margin must still cover the
    rounding of a crossing distance, a few ulps of the ray's travel through the scene
    (see ``jrt.grid``).
    """
    res = row.view(np.int32)[12:15]
    scale = CELL_MARGIN * float(np.abs(row[0:6].astype(np.float64)).max())
    out = []
    for axis in range(3):
        p = planes(row[axis], row[6 + axis], int(res[axis])).astype(np.float64)
        lo3 = np.zeros((res[axis], 3))
        hi3 = np.zeros((res[axis], 3))
        lo3[:, axis], hi3[:, axis] = p[:-1], p[1:]
        wlo, whi = widen_boxes(lo3, hi3)  # the margin is per axis: only this axis matters
        out.append((wlo[:, axis] - scale, whi[:, axis] + scale))
    return out


def empty_distance(occupied: np.ndarray, res, cap: int) -> np.ndarray:
    """int8 [cells]: Chebyshev distance, in cells, to the nearest occupied cell, at most
    ``cap`` (0 for an occupied cell; ``cap`` where none lies nearer, or none at all).

    Level by level: the occupied set dilated by one cell (a 3x3x3 cube, as three 1-D
    passes) reaches the cells at distance k on pass k; O(cap * cells).
    """
    nx, ny, nz = (int(r) for r in res)
    reach = np.asarray(occupied, bool).reshape(nz, ny, nx)
    dist = np.where(reach, 0, cap).astype(np.int8)
    for k in range(1, cap):
        if reach.all():
            break
        grown = reach.copy()
        for axis in range(3):
            lower = [slice(None)] * 3
            upper = [slice(None)] * 3
            lower[axis], upper[axis] = slice(None, -1), slice(1, None)
            step = grown.copy()
            step[tuple(upper)] |= grown[tuple(lower)]
            step[tuple(lower)] |= grown[tuple(upper)]
            grown = step
        dist[grown & ~reach] = k
        reach = grown
    return dist.reshape(-1)


def _candidate_ranges(tri_lo, tri_hi, intervals):
    """Per triangle and axis, the first and last cell whose widened interval meets the
    triangle's bounds: int64 [T, 3] each."""
    first = np.empty(tri_lo.shape, np.int64)
    last = np.empty(tri_lo.shape, np.int64)
    for axis, (wlo, whi) in enumerate(intervals):
        n = wlo.shape[0]
        # Both bound arrays are increasing in the cell index (the margin grows by less
        # than a cell from one cell to the next).
        first[:, axis] = np.searchsorted(whi, tri_lo[:, axis], side="left")
        last[:, axis] = np.searchsorted(wlo, tri_hi[:, axis], side="right") - 1
        np.clip(first[:, axis], 0, n - 1, out=first[:, axis])
        np.clip(last[:, axis], 0, n - 1, out=last[:, axis])
    return first, np.maximum(last, first)


def _expand(first, last):
    """(row, value) for every value in ``first[row] .. last[row]`` (rows in order, values
    ascending; an empty range, ``last < first``, gives none): int64 [sum of widths] each."""
    width = np.maximum(last - first + 1, 0)
    row = np.repeat(np.arange(width.shape[0]), width)
    value = np.arange(row.shape[0]) - np.repeat(np.cumsum(width) - width, width) + first[row]
    return row, value


def _slab_ranges(v, rows, axis, s0, s1, intervals, first, last, eps):
    """Per row, the cells the triangle's part inside the slab ``s0 <= x_axis <= s1`` can
    meet on the two other axes: ((axis b, first, last), (axis c, first, last)).

    ``v`` float64 [9, T] (row ``3 i + a``: corner i, axis a); ``rows`` the triangle of each
    row; ``first``, ``last`` [T, 3] the triangle's own candidate ranges, which bound the
    result. The part of a triangle inside a slab is a convex polygon whose corners are the
    triangle's corners inside the slab and the points where its edges cross the slab's two
    planes (Sutherland-Hodgman clipping); its bounds on b and c are those points'. They
    are computed in float64 (a crossing ``p + (s - p_a) / (q_a - p_a) (q - p)`` is off by
    a few 2^-53 of the coordinates) and widened by ``eps``, far more than that, so they
    hold every cell the exact separating-axis test can accept; that test still decides
    each candidate, so the references are those that testing every cell of the
    triangle's bounding box gives.
    """
    out = []
    others = [b for b in range(3) if b != axis]
    inf = np.full(rows.shape[0], np.inf)
    lo = {b: inf.copy() for b in others}
    hi = {b: -inf for b in others}
    va = [v[3 * i + axis][rows] for i in range(3)]
    vb = {b: [v[3 * i + b][rows] for i in range(3)] for b in others}
    for i in range(3):
        inside = (va[i] >= s0) & (va[i] <= s1)
        for b in others:
            lo[b] = np.where(inside, np.minimum(lo[b], vb[b][i]), lo[b])
            hi[b] = np.where(inside, np.maximum(hi[b], vb[b][i]), hi[b])
        j = (i + 1) % 3
        pa, qa = va[i], va[j]
        d = qa - pa
        safe = np.where(d == 0, 1.0, d)
        for s in (s0, s1):
            cross = (np.minimum(pa, qa) <= s) & (np.maximum(pa, qa) >= s) & (d != 0)
            t = np.clip((s - pa) / safe, 0.0, 1.0)
            for b in others:
                x = vb[b][i] + t * (vb[b][j] - vb[b][i])
                lo[b] = np.where(cross, np.minimum(lo[b], x), lo[b])
                hi[b] = np.where(cross, np.maximum(hi[b], x), hi[b])
    for b in others:
        wlo, whi = intervals[b]
        n = wlo.shape[0]
        f = np.searchsorted(whi, lo[b] - eps, side="left")
        g = np.searchsorted(wlo, hi[b] + eps, side="right") - 1
        # No point (rounding at a touching slab): the triangle's own range, safely.
        empty = lo[b] > hi[b]
        f = np.where(empty, first[rows, b], np.clip(np.maximum(f, first[rows, b]), 0, n - 1))
        g = np.where(empty, last[rows, b], np.minimum(g, last[rows, b]))
        out.append((b, f, g))
    return out


def _candidates(v, first, last, intervals, eps):
    """(triangle, ix, iy, iz) of the candidate cells, by triangle: int64 each.

    Not every cell of a triangle's bounding box: per x slab of cells the triangle's part
    in that slab (``_slab_ranges``) bounds its y and z cells, and per (x, y) column its
    part in the y slab bounds the z cells further. A long thin triangle (the slivers
    scene's needles) then gets about the cells it crosses, not the cube of cells around
    it; a triangle one cell wide on x (or y) keeps its bounds there, which clipping would
    not narrow.
    """
    wide = last > first  # [T, 3]: more than one candidate cell on the axis
    tri, ix = _expand(first[:, 0], last[:, 0])
    f = first[tri]
    g = last[tri]
    clip = np.flatnonzero((wide[:, 0] & (wide[:, 1] | wide[:, 2]))[tri])
    if clip.size:
        wlo, whi = intervals[0]
        for b, lo, hi in _slab_ranges(v, tri[clip], 0, wlo[ix[clip]], whi[ix[clip]],
                                      intervals, first, last, eps):
            f[clip, b], g[clip, b] = lo, hi
    row, iy = _expand(f[:, 1], g[:, 1])
    tri, ix = tri[row], ix[row]
    fz, gz = f[row, 2], g[row, 2]
    clip = np.flatnonzero(wide[:, 1][tri] & (gz > fz))
    if clip.size:
        wlo, whi = intervals[1]
        (_, lo, hi), = (r for r in _slab_ranges(v, tri[clip], 1, wlo[iy[clip]],
                                                 whi[iy[clip]], intervals, first, last, eps)
                        if r[0] == 2)
        fz[clip], gz[clip] = np.maximum(fz[clip], lo), np.minimum(gz[clip], hi)
    row, iz = _expand(fz, gz)
    return tri[row], ix[row], iy[row], iz


def _references(local: np.ndarray, row: np.ndarray):
    """(cell, triangle row) of every reference, sorted by cell then row: int64 [R] each.

    ``local``: float64 [T, 3, 3], the triangles' corners in the grid's frame (the grid
    row's coordinates).
    """
    res = row.view(np.int32)[12:15].astype(np.int64)
    t_count = local.shape[0]
    if t_count == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    tri64 = np.asarray(local, np.float64)
    v = np.ascontiguousarray(tri64.reshape(t_count, 9).T)
    intervals = widened_intervals(row)
    c = [v[3 * i:3 * i + 3] for i in range(3)]  # [3, T] rows: faster than [T, 3, 3] min
    first, last = _candidate_ranges(np.minimum(np.minimum(c[0], c[1]), c[2]).T,
                                    np.maximum(np.maximum(c[0], c[1]), c[2]).T, intervals)
    # 2^-30 of the box's magnitude: far above the float64 rounding of a slab crossing,
    # far below the cells.
    eps = 2.0**-30 * float(np.abs(row[0:6].astype(np.float64)).max())
    tri, ix, iy, iz = _candidates(v, first, last, intervals, eps)
    # A triangle whose bounds meet a single widened cell lies in that cell: no test.
    keep = np.ones(tri.shape[0], bool)
    multi = np.flatnonzero((last > first).any(axis=1)[tri])
    for start in range(0, multi.shape[0], _CHUNK):
        sel = multi[start:start + _CHUNK]
        t, c = tri[sel], (ix[sel], iy[sel], iz[sel])
        keep[sel] = overlap_rows(v[:, t], [intervals[a][0][c[a]] for a in range(3)],
                                [intervals[a][1][c[a]] for a in range(3)])
    # Sorted by cell, rows ascending within a cell: one sort of the unique keys
    # cell * T + row (faster than a stable argsort and two gathers).
    key = np.sort((ix + res[0] * (iy + res[1] * iz))[keep] * t_count + tri[keep])
    cell = key // t_count
    return cell, key - cell * t_count


def build(
    vertices: np.ndarray,
    faces: np.ndarray,
    *,
    density: float = DEFAULT_DENSITY,
    max_resolution: int = DEFAULT_MAX_RESOLUTION,
    max_skip: int = DEFAULT_MAX_SKIP,
) -> Structure:
    """Build a uniform grid over the non-degenerate faces.

    Args:
        density: cells per triangle (lambda of the density rule).
        max_resolution: cells per axis at most.
        max_skip: cap on the stored distance to the nearest non-empty cell, which bounds
            a leap over empty cells to ``max_skip`` cells along an axis; 0 or 1: no
            leaps (a plain cell-by-cell DDA).
    """
    _check_params(density, max_resolution, max_skip)
    start_time = time.perf_counter()
    keep = ~degenerate_mask(vertices, faces)
    ids = np.flatnonzero(keep).astype(np.int32)
    tris = triangle_vertices(vertices, np.asarray(faces)[ids])
    t_count = tris.shape[0]
    # Every decision is taken in the local frame (module docstring): the corners relative
    # to a point of their box, exactly, in float64; the box stored in float32 rounded
    # outward, so that it still holds every corner.
    frame, local, (lo, hi) = local_frame(tris)
    res = resolution(hi.astype(np.float64) - lo.astype(np.float64), t_count, density,
                     max_resolution)
    row = grid_row(lo, hi, res)
    cells = int(res.prod())
    cell, refs = _references(local, row)
    per_cell = np.bincount(cell, minlength=cells)
    cell_start = np.zeros(cells + 1, np.int64)
    np.cumsum(per_cell, out=cell_start[1:])
    if cell_start[-1] >= 2**31:
        raise ValueError(f"grid: {cell_start[-1]} references do not fit int32 offsets; "
                         "lower the density")
    references = refs.astype(np.int32) if refs.size else np.zeros(1, np.int32)
    arrays = {
        "grid": row,
        "cell_start": cell_start.astype(np.int32),
        "skip": empty_distance(per_cell > 0, res, max_skip),
        "references": references,
        "triangles": tris,
        "triangle_ids": ids,
        "frame": frame,
    }
    return Structure(kind="grid", arrays=arrays, layout=(), stats=_stats(
        arrays, res, per_cell, int(refs.size), density=density,
        max_resolution=max_resolution, max_skip=max_skip, degenerate=int((~keep).sum()),
        start_time=start_time))


def _stats(arrays, res, per_cell, references, *, density, max_resolution, max_skip,
           degenerate, start_time):
    cells = int(res.prod())
    filled = per_cell[per_cell > 0]
    row = arrays["grid"]
    extent = row[3:6].astype(np.float64) - row[0:3].astype(np.float64)
    size = extent / res

    def area(e):
        return 2.0 * (e[0] * e[1] + e[1] * e[2] + e[2] * e[0])

    box_area = area(extent)
    ratio = area(size) / box_area if box_area > 0 else 1.0
    expected_cells = cells * ratio
    expected_tests = references * ratio
    return {
        "build_seconds": time.perf_counter() - start_time,
        "density": float(density),
        "max_resolution": int(max_resolution),
        "max_skip": int(max_skip),
        "triangles": int(arrays["triangles"].shape[0]),
        "degenerate_skipped": degenerate,
        "resolution": tuple(int(r) for r in res),
        "cells": cells,
        "nodes": cells,
        "non_empty_cells": int(filled.size),
        "leaves": int(filled.size),
        "depth": 1,
        "references": references,
        "references_per_cell_mean": float(references / cells),
        "references_per_leaf_mean": float(filled.mean()) if filled.size else 0.0,
        "references_per_leaf_max": int(filled.max()) if filled.size else 0,
        "expected_cells_visited": float(expected_cells),
        "expected_triangle_tests": float(expected_tests),
        "sah_cost": float(TRAVERSAL_COST * expected_cells + INTERSECTION_COST * expected_tests),
        "bytes": int(sum(a.nbytes for a in arrays.values())),
    }


def stored_planes(structure: Structure) -> list[np.ndarray]:
    """Per axis, the walls between the grid's cells (world coordinates, float32 as the
    traversal computes them: ``lo + m * size``)."""
    g = np.asarray(structure["grid"])
    lo, size, res = g[0:3], g[6:9], g[12:15].view(np.int32)
    walls = []
    for a in range(3):
        m = np.arange(int(res[a]) + 1, dtype=np.float32)
        walls.append((lo[a] + m * size[a]).astype(np.float32))
    return world_planes(structure, walls)


KIND = StructureKind(
    name="grid", build=build,
    arrays=frozenset({"cell_start", "grid", "references", "skip", "triangles",
                      "triangle_ids", "frame"}),
    traversal="jrt.grid:traversal", planes=stored_planes,
    rows=frozenset({"cell_start", "skip", "references", "triangles", "triangle_ids"}),
    summary="uniform grid: cells of equal size, walked cell by cell (3D-DDA)")
