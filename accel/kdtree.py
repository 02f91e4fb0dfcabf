"""SAH kd-tree with perfect splits (Wald & Havran 2006), binned, built level by level.

A kd-tree cuts space, not the triangle set: every node is a box (its *cell*), split by an
axis-aligned plane into two boxes, and a triangle is referenced by every leaf whose cell
it overlaps, so one triangle may sit in many leaves (``references``).

**Cost model.** The surface area heuristic of MacDonald & Booth (1990) with Wald & Havran's
empty-space bonus ("On building fast kd-trees for ray tracing, and on doing that in
O(N log N)", IEEE RT 2006, eq. 4): splitting a cell V at plane p costs

    C(p) = lambda(p) * (K_T + K_I * (SA(V_L) N_L + SA(V_R) N_R) / SA(V)),

lambda(p) = 1 - ``empty_bonus`` (their 0.8) when N_L or N_R is 0, else 1, against K_I * N
for a leaf. A node becomes a leaf when no candidate beats the leaf, when it holds at most
``max_leaf_size`` references, or at depth ``max_depth``, by default round(8 + 1.3 log2 N)
(pbrt's rule: Pharr, Jakob & Humphreys, *Physically Based Rendering*, 3rd ed., section 4.4).

**Perfect splits** (Wald & Havran; Havran's thesis 2000): every reference
carries its triangle clipped to the node's (widened, below) cell, a convex polygon of at
most 9 vertices kept in a pool, and that polygon's bounding box; the SAH counts N_L and
N_R from those boxes, and a reference that straddles the chosen plane has its polygon
clipped by the plane (Sutherland & Hodgman 1974) once for each child whose widened bound
its box reaches past (elsewhere the clip would return it unchanged), which is the
triangle clipped to the child's cell, since a cell is the intersection of the half-spaces
above it. A long triangle is thus neither counted nor referenced where it does not reach.
The polygons are clipped in groups of equal vertex count, on only as many slots.

**Binned** (as accel.bvh, and Wald's binned kd-tree variant, Shevtsov, Soupikov & Kapustin,
"Highly parallel fast kd-tree construction", Eurographics 2007): the candidates along an
axis are the ``bins + 1`` boundaries of ``bins`` equal bins spanning the node's references
(their clipped boxes). Boundary 0 and boundary ``bins`` are moved just outside the
geometry (by 2^-14 of the room cut off plus the node's largest triangle), where they cut
off empty space: a reference whose box
merely touched such a plane would otherwise go to the empty side as well (references are
decided against widened cells, below). N_L counts the references whose box starts in a
lower bin, N_R those ending in a higher one (``np.bincount`` over the nodes of a level, by
axis, node and bin, ``accel.plane_tree.SEARCH_CHUNK`` nodes at a time), so a level costs
O(references + nodes x bins) NumPy work, with no per-node loop.

**Which side a reference goes to.** For exact traversal a triangle must be referenced by
every leaf whose cell, widened by its margin, it overlaps: ``CELL_MARGIN`` (2^-16) of the
cell's size and of the triangle's own extent (``accel.geometry.reference_margin``, which
says why that suffices with the traversal's run-time margins). A reference goes to each
child whose bound on the split axis, widened by that margin (the child's size across the
plane), its polygon reaches (the polygon's box overlaps it); the polygons are clipped by
those widened bounds, so a polygon always holds the part of its triangle in the node's
widened cell and
the test is exact (``tests/test_kdtree.py`` checks it against the separating-axis test,
``accel.geometry.triangles_overlap_boxes``, leaf by leaf). Triangles lying *in* the plane
(clipped box with min == max == the plane on the split axis) go to one side only, the one
of lower SAH cost (Wald & Havran's rule; the left side only when strictly cheaper).
That is still exact: a ray hits such a triangle at its crossing of the plane, where the
traversal's intervals for the two children overlap (``jrt.planes``), so the leaf that
holds it is visited. Two leaf children of a node get adjacent slots in ``references``
(the traversal hands both to the leaf loop as one range).

**The build** works level by level, every node of a level at once; the bookkeeping of
nodes, leaves and rows, the cost model and the parameters' checks are ``accel.plane_tree``'s,
shared with the BSP tree. **Its cost**: a level's work is O(references of the level) NumPy
passes (binning, prefix sums, the straddlers' clipping), and there are at most
``max_depth`` levels: O(N log N) overall.

Layout (``nodes`` float32 [M, 4], 16 bytes a row, one row per *interior* node, both child
references in the parent as accel.bvh, so a leaf costs no traversal step of its own):

    bytes  0-3   float 0   split coordinate (float32)
    bytes  4-7   float 1   split axis 0, 1, 2 (int32 bit pattern)
    bytes  8-11  float 2   child 0's reference (int32 bit pattern): the cell below the plane
    bytes 12-15  float 3   child 1's reference: the cell above the plane

A reference ``r >= 0`` is an interior row; ``r < 0`` a leaf ``~r = (first << leaf_bits) |
count`` (``accel.geometry.leaf_references``) over slots ``first .. first+count-1`` of
``references`` (int32 [R], triangle rows); ``r = -1`` (count 0) an empty leaf. Row 0 is the
root, rows in breadth-first order. A tree that is a single leaf has one root row with the
plane at the upper face of the scene box, child 0 that leaf and child 1 empty; a mesh
without triangles, one row with two empty leaves. ``bounds`` float32 [2, 3] is the root
cell, the exact float32 bounding box of the triangles (zeros when there are none, and then
``references`` holds one unused slot: the engine gathers a slot even when no leaf names one).
``triangles`` [T, 3, 3] and ``triangle_ids`` [T] hold the non-degenerate faces in mesh
order.
"""

from __future__ import annotations

import time

import numpy as np

from accel.geometry import reference_margin, triangle_boxes
from accel.plane_tree import (
    DEFAULT_EMPTY_BONUS,
    DEFAULT_INTERSECTION_COST,
    DEFAULT_MAX_LEAF_SIZE,
    DEFAULT_TRAVERSAL_COST,
    EMPTY_CUT_GAP,
    MIN_EMPTY_CUT,
    LevelBuild,
    TreeRows,
    check_params,
    default_max_depth,
    half_area,
    search_level,
    split_cost,
    tree_triangles,
)
from accel.registry import StructureKind, world_planes
from accel.structure import Structure
from accel.threads import thread_map, threads_for

#: Defaults: 32 bins (Shevtsov et al. 2007 use 32; Wald 2007 found 16-32 within a few
#: percent of a full sweep); the cost constants, the empty-space bonus and the leaf size are
#: ``accel.plane_tree``'s (measured with this tree: see there).
DEFAULT_BINS = 32
ROW_FLOATS = 4
#: Vertices a clipped polygon may have: a triangle clipped to a box has at most 9.
POLYGON_SLOTS = 10

__all__ = ["DEFAULT_BINS", "DEFAULT_EMPTY_BONUS", "DEFAULT_INTERSECTION_COST",
           "DEFAULT_MAX_LEAF_SIZE", "DEFAULT_TRAVERSAL_COST", "KIND", "ROW_FLOATS", "build",
           "clip_polygons", "polygon_bounds", "stored_planes"]


def _clip_uniform(v: np.ndarray, axis: np.ndarray, bound: np.ndarray, upper: bool):
    """Polygons ``v`` [K, c, 3] of exactly c vertices each clipped to a half-space (as
    :func:`clip_polygons`): the new vertices [K, 2c, 3] with a mask of those kept, in order.

    The next vertex of vertex i is i + 1 mod c, so a polygon of c vertices needs no mask
    of used slots; candidate 2i is vertex i (kept when inside), 2i + 1 the crossing of edge
    (i, i + 1) with the plane (when the edge crosses it strictly).
    """
    k, c = v.shape[0], v.shape[1]
    # The coordinates on each polygon's axis, by flat index (no index arrays per axis).
    at = (np.arange(k) * 3 * c)[:, None] + 3 * np.arange(c) + axis[:, None]
    coord = np.take(v, at)
    d = coord - bound[:, None] if upper else bound[:, None] - coord
    vn = np.concatenate((v[:, 1:], v[:, :1]), axis=1)
    dn = np.concatenate((d[:, 1:], d[:, :1]), axis=1)
    keep_p = d <= 0
    cross = ((d < 0) & (dn > 0)) | ((d > 0) & (dn < 0))
    t = d / np.where(cross, d - dn, 1.0)
    vn -= v
    vn *= t[:, :, None]
    x = np.add(v, vn, out=vn)
    # A crossing gets the plane's coordinate exactly (a polygon flat on an axis stays flat).
    x.reshape(-1)[at] = bound[:, None]
    keep = np.stack([keep_p, cross], axis=2).reshape(k, 2 * c)
    cand = np.stack([v, x], axis=2).reshape(k, 2 * c, 3)
    return cand, keep


def _clip_groups(fetch, count, axis, bound, upper, slots=POLYGON_SLOTS):
    """Polygons of ``count`` vertices each clipped as :func:`clip_polygons` says, in groups
    of equal vertex count c, on c slots (2c candidates) rather than all ``slots``: most are
    triangles and quadrilaterals. ``fetch(positions, c)``: the group's vertices [G, c, 3].

    ``count`` must not change while the groups are taken. Yields per group: its positions
    in ``count``, the clipped polygons [G, W, 3] (W = min(2c,
    slots), unused ones repeating the first vertex kept), their counts and bounding boxes
    (lo, hi).
    """
    for c in np.flatnonzero(np.bincount(count)):  # (the counts present, ascending)
        group = np.flatnonzero(count == c)
        cand, keep = _clip_uniform(fetch(group, c), axis[group], bound[group], upper)
        n = keep.sum(axis=1)
        fits = n <= slots
        if not fits.all():  # (rounding only) the unclipped polygon: every vertex kept
            keep[~fits] = np.arange(2 * c) % 2 == 0
            n = np.where(fits, n, c)
        width = min(2 * int(c), slots)
        g = group.size
        # The kept candidates, row after row, go to slots 0 .. n-1 of their row: by flat
        # index, the i-th kept one to slot i - (kept in the rows before) of its row.
        kept = np.flatnonzero(keep)
        before = np.cumsum(n) - n
        flat = cand.reshape(-1, 3)
        # The first vertex kept fills the rest (vertex 0 where none is kept).
        first = np.arange(g) * 2 * c
        some = n > 0
        first[some] = kept[before[some]]
        # One gather of candidate rows: each slot's index, the kept ones scattered over
        # the padding (indices are cheaper to move than vertices).
        take = np.repeat(first, width)
        take[np.arange(kept.size) + np.repeat(np.arange(g) * width - before, n)] = kept
        res = flat[take].reshape(g, width, 3)
        # Bounds, reduced pairwise over the slots (a reduction over a short middle axis is
        # slow); the unused slots repeat a kept vertex.
        lo, hi = res[:, 0].copy(), res[:, 0].copy()
        for i in range(1, width):
            np.minimum(lo, res[:, i], out=lo)
            np.maximum(hi, res[:, i], out=hi)
        yield group, res, n, lo, hi


def clip_polygons(poly: np.ndarray, count: np.ndarray, axis: np.ndarray, bound: np.ndarray,
                  upper: bool):
    """Convex polygons k clipped to the half-space ``x[axis[k]] <= bound[k]`` (``upper``) or
    ``>= bound[k]`` (Sutherland & Hodgman 1974), float64.

    ``poly`` [K, P, 3] holds ``count[k]`` vertices in order (the slots past them are not
    read). Returns the new (poly, count), the unused slots copies of vertex 0.
    A vertex on the plane is kept and no crossing is added next to it, so clipping never
    duplicates vertices; a crossing gets the plane's coordinate exactly, so a polygon flat
    on an axis stays flat. A polygon that would need more than P vertices (a triangle
    clipped to a box has at most 9; only rounding could add more) is returned unclipped,
    which is conservative.
    """
    out = np.empty_like(poly)
    count = np.asarray(count, np.int64)
    new_count = count.copy()  # (not the groups' counts: those are read group by group)
    for group, res, n, _, _ in _clip_groups(lambda group, c: poly[group, :c], count, axis,
                                            bound, upper, poly.shape[1]):
        out[group, :res.shape[1]] = res
        out[group, res.shape[1]:] = res[:, :1]
        new_count[group] = n
    return out, new_count


def polygon_bounds(poly: np.ndarray):
    """Bounding boxes (lo, hi) [K, 3] of polygons [K, P, 3] (unused slots repeat vertex 0)."""
    return poly.min(axis=1), poly.max(axis=1)


def _best_splits(box, seg, counts, cell_lo, cell_hi, bins, ct, ci, bonus):
    """Best SAH plane of every node: (cost, axis, plane), [K] each (cost inf: none).

    ``box`` [7, R]: the references' clipped boxes (lo x, y, z, hi x, y, z) and their
    triangles' extents, sorted by node ``seg`` (``counts`` per node, none 0).

    Candidates per axis: the interior boundaries of ``bins`` equal bins over the extent of
    the node's references (N_L: references whose box starts in a lower bin, N_R: ending in
    a higher one), and the two empty-space cuts just outside that extent. The three axes
    are binned at once, node arrays [3, K] and one ``bincount`` per side over keys
    ``bin * 3K + axis * K + node``; ties go to the lower axis, on an axis to the lowest
    interior boundary, then the low cut, then the high one.
    """
    k = counts.shape[0]
    offsets = np.cumsum(counts) - counts
    c_lo, c_hi = cell_lo.T, cell_hi.T  # [3, K]
    reduced = np.maximum.reduceat(box[3:7], offsets, axis=1)
    lo = np.maximum(np.minimum.reduceat(box[:3], offsets, axis=1), c_lo)
    hi = np.minimum(reduced[:3], c_hi)
    largest = reduced[3]  # the node's largest triangle
    ext = c_hi - c_lo
    # Per axis a: the cell's extents across it (perimeter and product of the other two),
    # so that a side of length s has half area s * perimeter + product.
    perimeter = ext[[1, 2, 0]] + ext[[2, 0, 1]]
    product = ext[[1, 2, 0]] * ext[[2, 0, 1]]
    area = half_area(cell_lo, cell_hi)
    costs, planes = [], []
    with np.errstate(divide="ignore", invalid="ignore"):
        width = (hi - lo) / bins
        scale = np.where(width > 0, 1.0 / np.where(width > 0, width, 1.0), 0.0)
        # (References are sorted by node: repeat is a gather without an index.)
        at, per = np.repeat(lo, counts, axis=1), np.repeat(scale, counts, axis=1)
        # Keys (bin, axis, node): the candidates' arrays are [bins - 1, 3K], a node's
        # values down a column, so that the per-node values broadcast along contiguous
        # rows and the prefix sums and the minimum are whole-row operations (measured
        # 2-5x faster than along a short last axis, which NumPy walks row by row).
        base = seg + (np.arange(3) * k)[:, None]
        wide = 3 * k

        def prefix(x):  # references of x's bin in bins < j, for j = 1 .. bins - 1
            f = x - at
            f *= per
            np.clip(f, 0, bins - 1, out=f)  # then truncation is floor
            key = f.astype(np.intp)
            key *= wide
            key += base
            h = np.bincount(key.ravel(), minlength=bins * wide).reshape(bins, wide)
            out = np.empty((bins - 1, wide), h.dtype)
            out[0] = h[0]
            for i in range(1, bins - 1):
                np.add(out[i - 1], h[i], out=out[i])
            return out

        # Boundary j (1 .. bins-1): N_L starts in bins < j, N_R = N - ends in bins < j.
        n_left = prefix(box[:3])
        n_right = np.subtract(np.tile(counts, 3), prefix(box[3:6]))
        # Side areas: (plane - c_lo) P + Q and (c_hi - plane) P + Q, plane = lo + j width.
        j = np.arange(1, bins)[:, None]
        plane = lo.reshape(-1) + j * width.reshape(-1)  # [bins-1, 3K]
        below = plane - c_lo.reshape(-1)
        below *= perimeter.reshape(-1)
        below += product.reshape(-1)
        above = np.subtract(c_hi.reshape(-1), plane, out=plane)
        above *= perimeter.reshape(-1)
        above += product.reshape(-1)
        below *= n_left
        above *= n_right
        below += above
        # The first minimum (as argmin: its value and index; a NaN, the first NaN).
        weighted = below.min(axis=0)
        pick = np.argmax(below == weighted, axis=0)
        nan = np.isnan(weighted)
        if nan.any():
            pick[nan] = np.argmax(np.isnan(below[:, nan]), axis=0)
        weighted, pick = weighted.reshape(3, k), pick.reshape(3, k)
        plane = (lo + (pick + 1) * width).astype(np.float32).astype(np.float64)
        cost = ct + ci * weighted / area
        cost[~((width > 0) & (plane > c_lo) & (plane < c_hi))] = np.inf
        costs.append(cost)
        planes.append(plane)
        # Empty-space cuts just outside the references (see EMPTY_CUT_GAP), where they cut
        # off more than their gap and MIN_EMPTY_CUT of the node.
        least = MIN_EMPTY_CUT * ext.max(axis=0)
        for low in (True, False):
            room = lo - c_lo if low else c_hi - hi
            gap = EMPTY_CUT_GAP * (largest + room)
            plane = (lo - gap if low else hi + gap).astype(np.float32).astype(np.float64)
            side = (c_hi - plane) if low else (plane - c_lo)
            cost = (1 - bonus) * (ct + ci * counts * (side * perimeter + product) / area)
            cost[~((room > np.maximum(2 * gap, least)) & (plane > c_lo)
                   & (plane < c_hi))] = np.inf
            costs.append(cost)
            planes.append(plane)
    # [axis, candidate kind, node]: the first of equal costs wins.
    cost = np.stack(costs, axis=1).reshape(9, k)
    cost[np.isnan(cost)] = np.inf
    best = np.argmin(cost, axis=0)
    cols = np.arange(k)
    plane = np.stack(planes, axis=1).reshape(9, k)[best, cols]
    return cost[best, cols], best // 3, plane


class _Pool:
    """The clipped polygons (float64 [N, POLYGON_SLOTS, 3], the slots past a polygon's
    count unused, and the counts) of the references whose triangle has been clipped (the
    others, ``-1``, are their triangles: most references, never copied here), appended to
    as straddlers are clipped; compacted to the live ones when those fall under a quarter
    (amortised O(1) per polygon)."""

    def __init__(self, n: int):
        self.poly = np.empty((max(n, 16), POLYGON_SLOTS, 3))
        self.count = np.empty(self.poly.shape[0], np.int64)
        self.size = 0

    def reserve(self, n: int) -> int:
        """Room for ``n`` more polygons: the first one's row."""
        if self.size + n > self.poly.shape[0]:
            cap = max(2 * self.poly.shape[0], self.size + n)
            grown = np.empty((cap, POLYGON_SLOTS, 3))
            grown[:self.size] = self.poly[:self.size]
            self.poly = grown
            self.count = np.concatenate([self.count[:self.size],
                                         np.empty(cap - self.size, np.int64)])
        self.size += n
        return self.size - n

    def compact(self, rpoly):
        """``rpoly`` (pool rows, -1: the triangle) once the pool holds only its rows."""
        clipped = np.flatnonzero(rpoly >= 0)
        if 4 * clipped.size >= self.size:
            return rpoly
        # A polygon referenced by several references is copied once per reference.
        n = clipped.size
        live = rpoly[clipped]
        self.poly[:n], self.count[:n] = self.poly[live], self.count[live]
        self.size = n
        rpoly = rpoly.copy()
        rpoly[clipped] = np.arange(n)
        return rpoly


def build(
    vertices: np.ndarray,
    faces: np.ndarray,
    *,
    bins: int = DEFAULT_BINS,
    max_leaf_size: int = DEFAULT_MAX_LEAF_SIZE,
    max_depth: int | None = None,
    traversal_cost: float = DEFAULT_TRAVERSAL_COST,
    intersection_cost: float = DEFAULT_INTERSECTION_COST,
    empty_bonus: float = DEFAULT_EMPTY_BONUS,
) -> Structure:
    """Build an SAH kd-tree over the non-degenerate faces.

    Args:
        bins: candidate planes per axis and node are the ``bins + 1`` bin boundaries.
        max_leaf_size: nodes with at most this many references become leaves.
        max_depth: deepest level split; ``None``: round(8 + 1.3 log2 N) (pbrt).
        traversal_cost, intersection_cost: the SAH constants K_T and K_I.
        empty_bonus: the cost of a split with an empty side is scaled by 1 - empty_bonus.
    """
    check_params("kdtree", bins, max_leaf_size, max_depth, traversal_cost, intersection_cost,
                 empty_bonus)
    start_time = time.perf_counter()
    ct, ci, bonus = float(traversal_cost), float(intersection_cost), float(empty_bonus)
    triangles = tree_triangles(vertices, faces)
    tri64, extent = triangles.local, triangles.extent
    t_count = triangles.ids.shape[0]
    depth_limit = default_max_depth(t_count) if max_depth is None else int(max_depth)
    # The nodes (cells), their splits (axis, plane) and leaves.
    levels = LevelBuild(triangles.bounds, t_count, max_leaf_size, depth_limit,
                        planes={"axis": (np.int64, ()), "plane": (np.float64, ())})
    planar_total = 0
    # The references of the active level, sorted by node: node, triangle row, the triangle
    # clipped to the node's widened cell (a polygon in ``pool``, which only straddlers add
    # to) and ``box`` [7, R]: its bounds (lo x, y, z, hi x, y, z) and the triangle's
    # extent, one array so that a level takes it with one gather.
    rseg = np.zeros(t_count, np.int64)
    rtri = np.arange(t_count, dtype=np.int64)
    pool = _Pool(8 * t_count)  # (rows never written cost no memory)
    rpoly = np.full(t_count, -1, np.int64)
    tri_lo, tri_hi = triangle_boxes(tri64)
    box = np.concatenate([tri_lo.T, tri_hi.T, extent[None]])
    while levels.active:
        k = levels.size
        counts = np.bincount(rseg, minlength=k)
        splitting = levels.wanting_split(counts)
        if not splitting.any():
            levels.close_leaves(splitting, counts, rseg, rtri)
            break
        # Every node's best plane (nodes not wanting a split hold at most max_leaf_size
        # references: cheaper to include than to leave out).
        cost, axis, plane = np.empty(k), np.empty(k, np.int64), np.empty(k)

        def search(run, box=box, rseg=rseg, counts=counts, lo=levels.lo, hi=levels.hi):
            first, end, r0, r1 = run
            return _best_splits(box[:, r0:r1], rseg[r0:r1] - first, counts[first:end],
                                lo[first:end], hi[first:end], bins, ct, ci, bonus)

        for first, end, best in search_level(counts, search):
            cost[first:end], axis[first:end], plane[first:end] = best
        splitting &= cost < ci * counts
        levels.close_leaves(splitting, counts, rseg, rtri)
        nodes = np.flatnonzero(splitting)
        m = nodes.size
        if m == 0:
            break
        # Children: cells below and above the plane, and their widened cells.
        rank = np.full(k, -1, np.int64)
        rank[nodes] = np.arange(m)
        ax, sp = axis[nodes], plane[nodes]
        lo, hi = levels.lo[nodes], levels.hi[nodes]
        rows = np.arange(m)
        lo0, hi0, lo1, hi1 = lo, hi.copy(), lo.copy(), hi
        hi0[rows, ax] = sp
        lo1[rows, ax] = sp
        size0 = (hi0 - lo0)[rows, ax]  # the children's sizes across the plane
        size1 = (hi1 - lo1)[rows, ax]
        levels.split(nodes, (lo0, hi0), (lo1, hi1), axis=ax, plane=sp)

        # Classify the references of the splitting nodes by their clipped bounds.
        sel = np.flatnonzero(splitting[rseg])
        r = rank[rseg[sel]]
        a = ax[r]
        # (By flat index: box is contiguous, and one index array is a faster gather.)
        flat = a * box.shape[1] + sel
        x_lo, x_hi = np.take(box, flat), np.take(box, flat + 3 * box.shape[1])
        s_r = sp[r]
        planar = (x_lo == s_r) & (x_hi == s_r)
        # Each child's cell widened, for this reference, by its margin: CELL_MARGIN of the
        # child's size and of the triangle's extent (accel.geometry.reference_margin).
        ext = box[6, sel]
        upper0 = s_r + reference_margin(size0[r], ext)  # child 0's widened cell ends here
        lower1 = s_r - reference_margin(size1[r], ext)  # child 1's starts here
        member = [(x_lo <= upper0) & ~planar, (x_hi >= lower1) & ~planar]
        if planar.any():
            # Planar references: the side of lower cost (Wald & Havran).
            n_planar = np.bincount(r[planar], minlength=m)
            n0 = np.bincount(r[member[0]], minlength=m)
            n1 = np.bincount(r[member[1]], minlength=m)
            area = half_area(lo, hi)
            a0, a1 = half_area(lo0, hi0), half_area(lo1, hi1)
            with np.errstate(divide="ignore", invalid="ignore"):
                planar_left = (split_cost(ct, ci, bonus, a0, a1, area, n0 + n_planar, n1)
                               < split_cost(ct, ci, bonus, a0, a1, area, n0, n1 + n_planar))
            member[0] |= planar & planar_left[r]
            member[1] |= planar & ~planar_left[r]
            planar_total += int(planar.sum())
        # Straddlers (both sides): the polygon clipped by each side's widened bound, where
        # it reaches past that bound (elsewhere clipping would return it unchanged).
        both = np.flatnonzero(member[0] & member[1])
        order = levels.descend(sel, r, member)
        # The next level's references: entries (side 0's members, then side 1's) whose
        # straddlers are replaced by their clipped polygons (rows R.. of the extended
        # arrays), in the order of ``order.entry``.
        src = np.concatenate([sel[order.rows[0]], sel[order.rows[1]]])
        at = [np.flatnonzero(member[1][order.rows[0]]),
              order.rows[0].size + np.flatnonzero(member[0][order.rows[1]])]
        # Each side's straddlers to clip, taken by vertex count (stable), so that each group
        # of _clip_groups is a run of rows here and in the pool: its results are written as
        # slices. Both sides' pool rows are reserved first (the pool grows only then), so
        # that the two sides are clipped on two threads, each writing its own rows.
        jobs = []
        for side, (upper, bound, beyond) in enumerate(
                ((True, upper0, x_hi > upper0), (False, lower1, x_lo < lower1))):
            clip = np.flatnonzero(beyond[both])
            if clip.size == 0:
                continue
            ids = rpoly[sel[both[clip]]]
            count = np.where(ids < 0, 3, pool.count[ids])
            by_count = np.argsort(count, kind="stable")
            jobs.append((side, upper, bound, clip[by_count], count[by_count], ids[by_count],
                         pool.reserve(clip.size)))

        def clip_side(job, box=box, rtri=rtri, sel=sel, both=both, a=a):
            """One side's straddlers clipped into its pool rows: their boxes [7, n]."""
            _, upper, bound, clip, count, ids, start = job
            refs = sel[both[clip]]
            p_box = np.empty((7, clip.size))
            p_box[6] = box[6, refs]

            def fetch(group, c, ids=ids, tris=rtri[refs]):  # the pool's, or the triangles
                run = slice(group[0], group[-1] + 1)
                mine = ids[run]
                whole = mine < 0
                if c != 3 or not whole.any():
                    return pool.poly[mine, :c]
                if whole.all():
                    return tri64[tris[run]]
                poly = np.empty((group.size, c, 3))
                poly[~whole] = pool.poly[mine[~whole], :c]
                poly[whole] = tri64[tris[run][whole]]
                return poly

            for group, res, n, p_lo, p_hi in _clip_groups(fetch, count, a[both[clip]],
                                                          bound[both[clip]], upper):
                run = slice(group[0], group[-1] + 1)
                pool.poly[start + run.start:start + run.stop, :res.shape[1]] = res
                pool.count[start + run.start:start + run.stop] = n
                p_box[:3, run], p_box[3:6, run] = p_lo.T, p_hi.T
            return p_box

        new_box, new_poly = [box], [rpoly]
        added = box.shape[1]
        clip_threads = threads_for(sum(job[3].size for job in jobs) // 2)
        for job, p_box in zip(jobs, thread_map(clip_side, jobs, clip_threads), strict=True):
            side, clip, start = job[0], job[3], job[6]
            new_poly.append(start + np.arange(clip.size))
            new_box.append(p_box)
            src[at[side][clip]] = added + np.arange(clip.size)
            added += clip.size
        src = src[order.entry]
        rseg, rtri = order.segment, order.gather(rtri)
        # (A take of the level's rows, then the clipped ones filled in: no copy of the
        # level's arrays with the clipped ones appended, at 1M triangles 100s of MiB.)
        clipped = np.flatnonzero(src >= box.shape[1])
        from_clip = src[clipped] - box.shape[1]
        src[clipped] = 0
        box, rpoly = np.take(box, src, axis=1), np.take(rpoly, src)
        if clipped.size:
            box[:, clipped] = np.concatenate(new_box[1:], axis=1)[:, from_clip]
            rpoly[clipped] = np.concatenate(new_poly[1:])[from_clip]
        rpoly = pool.compact(rpoly)

    tree = levels.rows("kdtree")
    return levels.structure(
        "kdtree", _node_rows(tree, triangles.bounds), tree, triangles,
        params={"bins": bins, "max_leaf_size": max_leaf_size, "max_depth": depth_limit,
                "traversal_cost": ct, "intersection_cost": ci, "empty_bonus": bonus},
        extra={"degenerate_skipped": triangles.degenerate, "planar_references": planar_total,
               "leaves_over_max_depth": levels.over_depth},
        start_time=start_time)


def _node_rows(tree: TreeRows, bounds: np.ndarray) -> np.ndarray:
    """The ``nodes`` array (the layout in the module docstring)."""
    if tree.interior_ids.size:
        nodes = np.zeros((tree.interior_ids.size, ROW_FLOATS), np.float32)
        nodes[:, 0] = tree.planes["plane"]
        nodes.view(np.int32)[:, 1] = tree.planes["axis"]
        nodes.view(np.int32)[:, 2:4] = tree.children
    else:  # a single leaf (or nothing): one root row, child 1 empty
        nodes = np.zeros((1, ROW_FLOATS), np.float32)
        nodes[0, 0] = bounds[1, 0]
        nodes.view(np.int32)[0, 2:4] = [tree.root, -1]
    return nodes


def stored_planes(structure: Structure) -> list[np.ndarray]:
    """Per axis, the inner nodes' split planes (world coordinates)."""
    nodes = np.asarray(structure["nodes"])
    axis = nodes.view(np.int32)[:, 1]
    return world_planes(structure, [nodes[axis == a, 0] for a in range(3)])


KIND = StructureKind(
    name="kdtree", build=build,
    arrays=frozenset({"nodes", "bounds", "references", "triangles", "triangle_ids", "frame"}),
    layout=frozenset({"leaf_bits"}), traversal="jrt.kdtree:traversal", planes=stored_planes,
    rows=frozenset({"nodes", "references", "triangles", "triangle_ids"}),
    summary="kd-tree: axis-aligned split planes chosen by the SAH")
