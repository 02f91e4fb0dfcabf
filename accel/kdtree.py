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
clipped by the plane (Sutherland & Hodgman 1974) once for each child, which is the
triangle clipped to the child's cell, since a cell is the intersection of the half-spaces
above it. A long triangle is thus neither counted nor referenced where it does not reach.

**Binned** (as accel.bvh, and Wald's binned kd-tree variant, Shevtsov, Soupikov & Kapustin,
"Highly parallel fast kd-tree construction", Eurographics 2007): the candidates along an
axis are the ``bins + 1`` boundaries of ``bins`` equal bins spanning the node's references
(their clipped boxes). Boundary 0 and boundary ``bins`` are moved just outside the
geometry (by 2^-14 of the room cut off plus the node's largest triangle), where they cut
off empty space: a reference whose box
merely touched such a plane would otherwise go to the empty side as well (references are
decided against widened cells, below). N_L counts the references whose box starts in a
lower bin, N_R those ending in a higher one (``np.bincount`` over all nodes of a level, by
node, axis and bin), so a level costs O(references) NumPy work, with no per-node loop.

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

**Cost of the build**: a level's work is O(references of the level) NumPy passes (binning,
prefix sums, the straddlers' clipping), and there are at most ``max_depth`` levels:
O(N log N) overall.

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

import math
import time

import numpy as np

from accel.geometry import (
    degenerate_mask,
    leaf_bits_for,
    leaf_references,
    local_frame,
    reference_margin,
    triangle_extents,
    triangle_vertices,
)
from accel.structure import Structure

#: Defaults. 32 bins (Shevtsov et al. 2007 use 32; Wald 2007 found 16-32 within a few
#: percent of a full sweep). Cost constants: a traversal step and a triangle test each cost
#: one iteration of the engine's loop (``jrt.engine``), which puts K_T near K_I; measured on
#: the camel (50k camera and 50k incoherent rays, steps + tests per ray), K_T = 1 costs 11.5
#: and 32.8, K_T = 2 11.8 and 33.5 with half the nodes and a 1.5x faster build, K_T = 4 12.6
#: and 36.2 (K_I = 1); Wald & Havran's K_T = 15, K_I = 20 and pbrt's 1 and 80 split far
#: deeper (2-3x the references of K_T = 2 at the depth limit). The empty-space bonus is
#: Wald & Havran's lambda = 0.8, i.e. ``empty_bonus`` 0.2 (pbrt-v3 uses 0.5, which here
#: spends the depth limit on empty cuts: 2x the work per ray). Leaves of one reference
#: before the split search is skipped: pbrt's ``maxPrims = 1``; the SAH stops earlier
#: wherever splitting does not pay.
DEFAULT_BINS = 32
DEFAULT_TRAVERSAL_COST = 2.0
DEFAULT_INTERSECTION_COST = 1.0
DEFAULT_EMPTY_BONUS = 0.2
DEFAULT_MAX_LEAF_SIZE = 1
MAX_DEPTH_LIMIT = 64
ROW_FLOATS = 4
#: How far outside the geometry an empty-space cut is placed, relative to the room it cuts
#: off and the largest triangle of the node: 4 x CELL_MARGIN, so that a triangle touching
#: the geometry's bound is not referenced by the empty child (its margin is CELL_MARGIN of
#: that child's size and of its own extent, ``accel.geometry.reference_margin``).
EMPTY_CUT_GAP = 2.0**-14
#: An empty-space cut must cut off at least this fraction of the node's largest extent:
#: with the bonus any empty cut "pays", and thinner and thinner slivers next to geometry
#: lying in a plane would otherwise be cut off level after level.
MIN_EMPTY_CUT = 2.0**-10
#: Vertices a clipped polygon may have: a triangle clipped to a box has at most 9.
POLYGON_SLOTS = 10


def default_max_depth(triangles: int) -> int:
    """pbrt's rule: round(8 + 1.3 log2 N)."""
    return int(round(8 + 1.3 * math.log2(max(triangles, 1))))


def check_params(bins, max_leaf_size, max_depth, traversal_cost, intersection_cost,
                  empty_bonus, name="kdtree"):
    if not (isinstance(bins, int | np.integer) and 2 <= bins <= 256):
        raise ValueError(f"{name}: bins must be an integer in [2, 256], got {bins!r}")
    if not (isinstance(max_leaf_size, int | np.integer) and 1 <= max_leaf_size <= 255):
        raise ValueError(
            f"{name}: max_leaf_size must be an integer in [1, 255], got {max_leaf_size!r}")
    if max_depth is not None and not (
            isinstance(max_depth, int | np.integer) and 0 <= max_depth <= MAX_DEPTH_LIMIT):
        raise ValueError(f"{name}: max_depth must be None or an integer in "
                         f"[0, {MAX_DEPTH_LIMIT}], got {max_depth!r}")
    for key, value in (("traversal_cost", traversal_cost),
                       ("intersection_cost", intersection_cost)):
        if not (isinstance(value, int | float | np.number) and np.isfinite(value)
                and value > 0):
            raise ValueError(f"{name}: {key} must be a positive finite number, got {value!r}")
    if not (isinstance(empty_bonus, int | float | np.number) and 0 <= empty_bonus < 1):
        raise ValueError(f"{name}: empty_bonus must be a number in [0, 1), got {empty_bonus!r}")


def half_area(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Half the surface area of boxes [..., 3] (0 for inverted boxes)."""
    e = np.maximum(np.asarray(hi, np.float64) - np.asarray(lo, np.float64), 0.0)
    return e[..., 0] * e[..., 1] + e[..., 1] * e[..., 2] + e[..., 2] * e[..., 0]


def clip_polygons(poly: np.ndarray, count: np.ndarray, axis: np.ndarray, bound: np.ndarray,
                  upper: bool):
    """Convex polygons k clipped to the half-space ``x[axis[k]] <= bound[k]`` (``upper``) or
    ``>= bound[k]`` (Sutherland & Hodgman 1974), float64.

    ``poly`` [K, P, 3] holds ``count[k]`` vertices in order, the unused slots copies of
    vertex 0 (as the result). Returns the new (poly, count).
    A vertex on the plane is kept and no crossing is added next to it, so clipping never
    duplicates vertices; a crossing gets the plane's coordinate exactly, so a polygon flat
    on an axis stays flat. A polygon that would need more than P vertices (a triangle
    clipped to a box has at most 9; only rounding could add more) is returned unclipped,
    which is conservative.
    """
    k, slots = poly.shape[0], poly.shape[1]
    rows = np.arange(k)[:, None]
    index = np.arange(slots)[None, :]
    coord = poly[rows, index, axis[:, None]]
    d = coord - bound[:, None] if upper else bound[:, None] - coord
    valid = index < count[:, None]
    nxt = np.where(index + 1 < count[:, None], index + 1, 0)
    q = poly[rows, nxt]
    dq = d[rows, nxt]
    keep_p = valid & (d <= 0)
    cross = valid & (((d < 0) & (dq > 0)) | ((d > 0) & (dq < 0)))
    t = np.where(cross, d / np.where(cross, d - dq, 1.0), 0.0)
    x = poly + t[:, :, None] * (q - poly)
    x[rows, index, axis[:, None]] = bound[:, None]
    keep = np.stack([keep_p, cross], axis=2).reshape(k, 2 * slots)
    cand = np.stack([poly, x], axis=2).reshape(k, 2 * slots, 3)
    new_count = keep.sum(axis=1)
    fits = new_count <= slots
    keep &= fits[:, None]
    pos = np.cumsum(keep, axis=1) - 1
    r, j = np.nonzero(keep)
    new = poly.copy()
    new[r, pos[r, j]] = cand[r, j]
    count = np.where(fits, new_count, count)
    # Unused slots repeat vertex 0, so that min and max over all slots give the bounds.
    return np.where((index < count[:, None])[:, :, None], new, new[:, :1]), count


def polygon_bounds(poly: np.ndarray):
    """Bounding boxes (lo, hi) [K, 3] of polygons [K, P, 3] (unused slots repeat vertex 0)."""
    return poly.min(axis=1), poly.max(axis=1)


def _best_splits(rlo, rhi, rext, seg, counts, cell_lo, cell_hi, bins, ct, ci, bonus):
    """Best SAH plane of every node: (cost, axis, plane), [K] each (cost inf: none).

    Candidates per axis: the interior boundaries of ``bins`` equal bins over the extent of
    the node's references (N_L: references whose box starts in a lower bin, N_R: ending in
    a higher one), and the two empty-space cuts just outside that extent.
    """
    k = counts.shape[0]
    offsets = np.cumsum(counts) - counts
    elo = np.maximum(np.minimum.reduceat(rlo, offsets, axis=0), cell_lo)
    ehi = np.minimum(np.maximum.reduceat(rhi, offsets, axis=0), cell_hi)
    largest = np.maximum.reduceat(rext, offsets)  # the node's largest triangle
    ext = cell_hi - cell_lo
    area = half_area(cell_lo, cell_hi)
    j = np.arange(1, bins)[:, None]
    best_cost = np.full(k, np.inf)
    best_axis = np.zeros(k, np.int64)
    best_plane = np.zeros(k)
    cols = np.arange(k)

    def consider(cost, axis, plane):
        better = cost < best_cost
        best_cost[better] = cost[better]
        best_axis[better] = axis
        best_plane[better] = plane[better]

    with np.errstate(divide="ignore", invalid="ignore"):
        for axis in range(3):
            b, c = (axis + 1) % 3, (axis + 2) % 3
            perimeter = ext[:, b] + ext[:, c]
            product = ext[:, b] * ext[:, c]
            lo, hi = elo[:, axis], ehi[:, axis]
            c_lo, c_hi = cell_lo[:, axis], cell_hi[:, axis]
            width = (hi - lo) / bins
            # Interior boundaries (the bonus never applies: both sides hold a reference).
            scale = np.where(width > 0, 1.0 / np.where(width > 0, width, 1.0), 0.0)
            first = np.clip(np.floor((rlo[:, axis] - lo[seg]) * scale[seg]), 0, bins - 1)
            last = np.clip(np.floor((rhi[:, axis] - lo[seg]) * scale[seg]), 0, bins - 1)
            starts = np.bincount(first.astype(np.int64) * k + seg, minlength=bins * k)
            ends = np.bincount(last.astype(np.int64) * k + seg, minlength=bins * k)
            n_left = np.cumsum(starts.reshape(bins, k)[:-1], axis=0)
            n_right = np.cumsum(ends.reshape(bins, k)[::-1], axis=0)[::-1][1:]
            plane = lo + j * width
            weighted = ((plane - c_lo) * perimeter + product) * n_left
            weighted += ((c_hi - plane) * perimeter + product) * n_right
            pick = np.argmin(weighted, axis=0)
            cost = ct + ci * weighted[pick, cols] / area
            plane = plane[pick, cols].astype(np.float32).astype(np.float64)
            cost[~((width > 0) & (plane > c_lo) & (plane < c_hi))] = np.inf
            consider(cost, axis, plane)
            # Empty-space cuts just outside the references (see EMPTY_CUT_GAP), where they
            # cut off more than their gap and MIN_EMPTY_CUT of the node.
            least = MIN_EMPTY_CUT * ext.max(axis=1)
            for low in (True, False):
                gap = EMPTY_CUT_GAP * (largest + (lo - c_lo if low else c_hi - hi))
                room = lo - c_lo if low else c_hi - hi
                plane = (lo - gap if low else hi + gap).astype(np.float32).astype(np.float64)
                side = (c_hi - plane) if low else (plane - c_lo)
                cost = (1 - bonus) * (ct + ci * counts * (side * perimeter + product) / area)
                cost[~((room > np.maximum(2 * gap, least)) & (plane > c_lo)
                       & (plane < c_hi))] = np.inf
                consider(cost, axis, plane)
    best_cost[~np.isfinite(best_cost)] = np.inf
    return best_cost, best_axis, best_plane


def split_cost(ct, ci, bonus, a_left, a_right, area, n_left, n_right):
    cost = ct + ci * (a_left * n_left + a_right * n_right) / area
    return cost * np.where((n_left == 0) | (n_right == 0), 1.0 - bonus, 1.0)


class _Pool:
    """The references' clipped polygons, appended to as straddlers are clipped; compacted
    to the live ones when those fall under half (amortised O(1) per polygon)."""

    def __init__(self, triangles: np.ndarray):
        n = triangles.shape[0]
        self.poly = np.empty((max(4 * n, 16), POLYGON_SLOTS, 3))
        self.count = np.empty(self.poly.shape[0], np.int64)
        self.poly[:n, :3] = triangles
        self.poly[:n, 3:] = triangles[:, :1]
        self.count[:n] = 3
        self.size = n

    def get(self, index):
        return self.poly[index], self.count[index]

    def add(self, poly, count):
        n = poly.shape[0]
        if self.size + n > self.poly.shape[0]:
            cap = max(2 * self.poly.shape[0], self.size + n)
            self.poly = np.resize(self.poly, (cap, POLYGON_SLOTS, 3))
            self.count = np.resize(self.count, cap)
        self.poly[self.size:self.size + n] = poly
        self.count[self.size:self.size + n] = count
        self.size += n
        return np.arange(self.size - n, self.size)

    def compact(self, live):
        if 2 * live.shape[0] >= self.size:
            return live
        n = live.shape[0]
        poly, count = self.get(live)
        self.poly[:n], self.count[:n] = poly, count
        self.size = n
        return np.arange(n)


def ranks_in_segments(flags: np.ndarray, seg_first: np.ndarray, seg: np.ndarray) -> np.ndarray:
    """For each element, how many flagged elements precede it in its segment."""
    c = np.cumsum(flags) - flags
    return c - c[seg_first[seg]]


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
    check_params(bins, max_leaf_size, max_depth, traversal_cost, intersection_cost,
                  empty_bonus)
    start_time = time.perf_counter()
    ct, ci, bonus = float(traversal_cost), float(intersection_cost), float(empty_bonus)
    keep = ~degenerate_mask(vertices, faces)
    ids = np.flatnonzero(keep).astype(np.int32)
    tris = triangle_vertices(vertices, np.asarray(faces)[ids]).reshape(-1, 3, 3)
    t_count = ids.shape[0]
    depth_limit = default_max_depth(t_count) if max_depth is None else int(max_depth)
    frame, tri64, bounds = local_frame(tris)

    # Per node (creation order = breadth first): cell, depth, split (axis, plane, the
    # ids of both children) or leaf (slots in ``references``).
    node_lo, node_hi, node_depth = [], [], []
    split_ids, split_axis, split_plane, split_child = [], [], [], []
    leaf_ids, leaf_first, leaf_count, leaf_refs = [], [], [], []
    n_refs_out = 0
    planar_total = 0
    over_depth = 0
    # Active nodes of this level (cells) and their references, sorted by node: triangle
    # row, the triangle clipped to the node's widened cell (a polygon in ``pool``, which
    # only straddlers add to) and its bounds.
    act_ids = np.zeros(1 if t_count else 0, np.int64)
    act_lo = bounds[None, 0].astype(np.float64)[: len(act_ids)]
    act_hi = bounds[None, 1].astype(np.float64)[: len(act_ids)]
    node_lo.append(act_lo)
    node_hi.append(act_hi)
    node_depth.append(np.zeros(len(act_ids), np.int64))
    next_id = len(act_ids)
    rseg = np.zeros(t_count, np.int64)
    rtri = np.arange(t_count, dtype=np.int64)
    pool = _Pool(tri64)
    rpoly = np.arange(t_count, dtype=np.int64)
    rlo, rhi = tri64.min(axis=1), tri64.max(axis=1)
    extent = triangle_extents(tri64)
    depth = 0
    while act_ids.shape[0]:
        k = act_ids.shape[0]
        counts = np.bincount(rseg, minlength=k)
        want = counts > max_leaf_size
        splitting = want & (depth < depth_limit)
        over_depth += int((want & ~splitting).sum())
        axis = np.zeros(k, np.int64)
        plane = np.zeros(k)
        if splitting.any():
            cand = np.flatnonzero(splitting)
            remap = np.full(k, -1, np.int64)
            remap[cand] = np.arange(cand.size)
            mine = splitting[rseg]
            cost, axis[cand], plane[cand] = _best_splits(
                rlo[mine], rhi[mine], extent[rtri[mine]], remap[rseg[mine]], counts[cand],
                act_lo[cand],
                act_hi[cand], bins, ct, ci, bonus)
            splitting[cand] &= cost < ci * counts[cand]
        # Leaves: their references, in node order, go to ``references``.
        leaf_nodes = np.flatnonzero(~splitting)
        if leaf_nodes.size:
            leaf_refs.append(rtri[~splitting[rseg]])
            c = counts[leaf_nodes]
            leaf_ids.append(act_ids[leaf_nodes])
            leaf_first.append(n_refs_out + np.cumsum(c) - c)
            leaf_count.append(c)
            n_refs_out += int(c.sum())
        nodes = np.flatnonzero(splitting)
        m = nodes.size
        if m == 0:
            break
        # Children: cells below and above the plane, and their widened cells.
        rank = np.full(k, -1, np.int64)
        rank[nodes] = np.arange(m)
        ax, sp = axis[nodes], plane[nodes]
        lo, hi = act_lo[nodes], act_hi[nodes]
        rows = np.arange(m)
        lo0, hi0, lo1, hi1 = lo, hi.copy(), lo.copy(), hi
        hi0[rows, ax] = sp
        lo1[rows, ax] = sp
        size0 = (hi0 - lo0)[rows, ax]  # the children's sizes across the plane
        size1 = (hi1 - lo1)[rows, ax]
        child_ids = next_id + np.arange(2 * m)
        next_id += 2 * m
        split_ids.append(act_ids[nodes])
        split_axis.append(ax)
        split_plane.append(sp)
        split_child.append(child_ids.reshape(m, 2))
        child_lo = np.stack([lo0, lo1], axis=1).reshape(-1, 3)
        child_hi = np.stack([hi0, hi1], axis=1).reshape(-1, 3)
        node_lo.append(child_lo)
        node_hi.append(child_hi)
        node_depth.append(np.full(2 * m, depth + 1, np.int64))

        # Classify the references of the splitting nodes by their clipped bounds.
        sel = np.flatnonzero(splitting[rseg])
        r = rank[rseg[sel]]
        a = ax[r]
        x_lo, x_hi = rlo[sel, a], rhi[sel, a]
        planar = (x_lo == sp[r]) & (x_hi == sp[r])
        # Each child's cell widened, for this reference, by its margin: CELL_MARGIN of the
        # child's size and of the triangle's extent (accel.geometry.reference_margin).
        ext = extent[rtri[sel]]
        upper0 = sp[r] + reference_margin(size0[r], ext)  # child 0's widened cell ends here
        lower1 = sp[r] - reference_margin(size1[r], ext)  # child 1's starts here
        member = [(x_lo <= upper0) & ~planar, (x_hi >= lower1) & ~planar]
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
        # Straddlers (both sides): the polygon clipped by each side's widened bound.
        both = np.flatnonzero(member[0] & member[1])
        poly, count = pool.get(rpoly[sel[both]])
        clipped = []
        for upper, bound in ((True, upper0), (False, lower1)):
            p, c = clip_polygons(poly, count, a[both], bound[both], upper)
            clipped.append((pool.add(p, c),) + polygon_bounds(p))

        # The next level: the children that hold references, references sorted by child.
        seg_first = np.zeros(m, np.int64)
        seg_first[1:] = np.cumsum(np.bincount(r, minlength=m))[:-1]
        n_child = np.stack([np.bincount(r[member[0]], minlength=m),
                            np.bincount(r[member[1]], minlength=m)], axis=1).reshape(-1)
        child_first = np.cumsum(n_child) - n_child
        total = int(n_child.sum())
        new_poly = np.empty(total, np.int64)
        new_lo = np.empty((total, 3))
        new_hi = np.empty((total, 3))
        new_tri = np.empty(total, np.int64)
        new_seg = np.empty(total, np.int64)
        live = np.flatnonzero(n_child > 0)
        remap = np.full(2 * m, -1, np.int64)
        remap[live] = np.arange(live.size)
        for side in (0, 1):
            idx = np.flatnonzero(member[side])
            rank_in = ranks_in_segments(member[side], seg_first, r)
            pos = child_first[2 * r[idx] + side] + rank_in[idx]
            new_tri[pos] = rtri[sel[idx]]
            new_seg[pos] = remap[2 * r[idx] + side]
            new_poly[pos] = rpoly[sel[idx]]
            new_lo[pos] = rlo[sel[idx]]
            new_hi[pos] = rhi[sel[idx]]
            # The straddlers' clipped polygons replace their parents' ones.
            where = child_first[2 * r[both] + side] + rank_in[both]
            new_poly[where], new_lo[where], new_hi[where] = clipped[side]
        rseg, rtri, rpoly, rlo, rhi = new_seg, new_tri, new_poly, new_lo, new_hi
        rpoly = pool.compact(rpoly)
        act_ids = child_ids[live]
        act_lo = child_lo[live]
        act_hi = child_hi[live]
        depth += 1

    return _flatten(
        tris, ids, frame, bounds, next_id, node_lo, node_hi, node_depth,
        (split_ids, split_axis, split_plane, split_child),
        (leaf_ids, leaf_first, leaf_count, leaf_refs),
        params={"bins": bins, "max_leaf_size": max_leaf_size, "max_depth": depth_limit,
                "traversal_cost": ct, "intersection_cost": ci, "empty_bonus": bonus},
        extra={"degenerate_skipped": int((~keep).sum()), "planar_references": planar_total,
               "leaves_over_max_depth": over_depth},
        start_time=start_time)


def _cat(parts, dtype, shape=(0,)):
    return np.concatenate(parts).astype(dtype) if parts else np.zeros(shape, dtype)


def _flatten(tris, ids, frame, bounds, total, node_lo, node_hi, node_depth, splits, leaves, *,
             params, extra, start_time):
    split_ids, split_axis, split_plane, split_child = splits
    s_ids = _cat(split_ids, np.int64)
    s_axis = _cat(split_axis, np.int64)
    s_plane = _cat(split_plane, np.float64)
    s_child = _cat(split_child, np.int64, (0, 2))
    l_ids = _cat(leaves[0], np.int64)
    l_first = _cat(leaves[1], np.int64)
    l_count = _cat(leaves[2], np.int64)
    references = _cat(leaves[3], np.int32)
    max_count = int(l_count.max()) if l_count.size else 0
    try:
        leaf_bits = leaf_bits_for(max_count, references.shape[0])
    except ValueError as error:
        raise ValueError(f"kdtree: {error}") from None
    # The reference of every node: interior rows in creation (breadth-first) order,
    # leaves by their code, empty children (never active) -1.
    ref = np.full(max(total, 1), -1, np.int64)
    order = np.argsort(s_ids)
    s_ids, s_axis, s_plane, s_child = s_ids[order], s_axis[order], s_plane[order], \
        s_child[order]
    ref[s_ids] = np.arange(s_ids.size)
    ref[l_ids] = leaf_references(l_first, l_count, leaf_bits)
    ref[l_ids[l_count == 0]] = -1
    if s_ids.size:
        nodes = np.zeros((s_ids.size, ROW_FLOATS), np.float32)
        nodes[:, 0] = s_plane
        nodes.view(np.int32)[:, 1] = s_axis
        nodes.view(np.int32)[:, 2:4] = ref[s_child]
    else:  # a single leaf (or nothing): one root row, child 1 empty
        nodes = np.zeros((1, ROW_FLOATS), np.float32)
        nodes[0, 0] = bounds[1, 0]
        nodes.view(np.int32)[0, 2:4] = [ref[0] if total else -1, -1]
    return finish_plane_tree("kdtree", nodes, frame, bounds, references, tris, ids, leaf_bits,
                             node_lo, node_hi, node_depth, s_ids, l_ids, l_count, total,
                             params, extra, start_time)


def finish_plane_tree(kind, nodes, frame, bounds, references, tris, ids, leaf_bits, node_lo,
                      node_hi, node_depth, s_ids, l_ids, l_count, total, params, extra,
                      start_time):
    """The arrays and statistics of a plane tree (kd-tree or BSP tree) once its rows are
    laid out: shared by both builders. ``s_ids``/``l_ids``: the node ids of the interior
    nodes and of the leaves (empty children included), ``l_count`` the leaves' reference
    counts; ``node_lo``/``node_hi``/``node_depth`` per node by id. The SAH cost is
    Goldsmith & Salmon's: (C_T Σ interior areas + C_I Σ leaf area × references) / root area.
    """
    lo = _cat(node_lo, np.float64, (0, 3))
    hi = _cat(node_hi, np.float64, (0, 3))
    depth = _cat(node_depth, np.int64)
    interior = np.zeros(total, bool)
    interior[s_ids] = True
    is_leaf = ~interior
    # Per leaf (including empty children): its reference count.
    count = np.zeros(total, np.int64)
    count[l_ids] = l_count
    areas = half_area(lo, hi)
    root_area = areas[0] if total else 0.0
    ct, ci = params["traversal_cost"], params["intersection_cost"]
    if root_area > 0:
        sah = (ct * areas[interior].sum() + ci * (areas[is_leaf] * count[is_leaf]).sum()) \
            / root_area
    else:
        sah = 0.0
    full = l_count[l_count > 0]
    if references.size == 0:
        # The engine gathers a slot even when no leaf names one: one unused slot.
        references = np.zeros(1, np.int32)
    arrays = {"nodes": nodes, "bounds": bounds.astype(np.float32), "references": references,
              "triangles": np.ascontiguousarray(tris), "triangle_ids": ids,
              "frame": np.asarray(frame, np.float32)}
    stats = {
        "build_seconds": time.perf_counter() - start_time,
        **params,
        "triangles": int(tris.shape[0]),
        **extra,
        "nodes": int(total) if total else 1,
        "interior_nodes": int(s_ids.size),
        "leaves": int(is_leaf.sum()) if total else 1,
        "empty_leaves": int((is_leaf & (count == 0)).sum()) if total else 1,
        "depth": int(depth.max()) if total else 0,
        "references": int(full.sum()),
        "references_per_triangle": float(full.sum() / max(tris.shape[0], 1)),
        "references_per_leaf_mean": float(full.mean()) if full.size else 0.0,
        "references_per_leaf_max": int(full.max()) if full.size else 0,
        "sah_cost": float(sah),
        "bytes": int(sum(a.nbytes for a in arrays.values())),
    }
    return Structure(kind=kind, arrays=arrays, layout=(("leaf_bits", leaf_bits),), stats=stats)
