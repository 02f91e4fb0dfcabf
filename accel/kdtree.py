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

from accel.geometry import reference_margin
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
    split_cost,
    tree_triangles,
)
from accel.registry import StructureKind, world_planes
from accel.structure import Structure

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
    # to) and its bounds.
    rseg = np.zeros(t_count, np.int64)
    rtri = np.arange(t_count, dtype=np.int64)
    pool = _Pool(tri64)
    rpoly = np.arange(t_count, dtype=np.int64)
    rlo, rhi = tri64.min(axis=1), tri64.max(axis=1)
    while levels.active:
        k = levels.size
        counts = np.bincount(rseg, minlength=k)
        splitting = levels.wanting_split(counts)
        axis = np.zeros(k, np.int64)
        plane = np.zeros(k)
        if splitting.any():
            cand = np.flatnonzero(splitting)
            remap = np.full(k, -1, np.int64)
            remap[cand] = np.arange(cand.size)
            mine = splitting[rseg]
            cost, axis[cand], plane[cand] = _best_splits(
                rlo[mine], rhi[mine], extent[rtri[mine]], remap[rseg[mine]], counts[cand],
                levels.lo[cand], levels.hi[cand], bins, ct, ci, bonus)
            splitting[cand] &= cost < ci * counts[cand]
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

        # The next level: the children that hold references, references sorted by child;
        # the straddlers' clipped polygons replace their parents' ones.
        order = levels.descend(sel, r, member)
        rseg, rtri = order.segment, order.gather(rtri)
        rpoly, rlo, rhi = order.gather(rpoly), order.gather(rlo), order.gather(rhi)
        for side in (0, 1):
            where = order.slots(side, both)
            rpoly[where], rlo[where], rhi[where] = clipped[side]
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
