"""Bounding volume hierarchy: binned SAH (Wald 2007) or object median, built level by level.

The build is vectorised over every node of a tree level at once: per level, the
triangles of all the nodes still to split are binned together (``np.bincount`` and
``np.minimum.at`` keyed by node, axis and bin), the SAH sweep runs over all nodes as one
array, and the triangles are partitioned in place by a stable rank, so the work is
O(N) NumPy per level and O(N log N) in all, with no per-triangle (or per-node) Python loop.
A node of at most ``bins`` triangles (most of them, deep in the tree) is swept over its
triangles sorted by bin instead of over its bins: the same split for less work (see
:func:`_sorted_splits`). Each level's rows (triangle, centroid, box) are carried to the
next in the order the partition leaves them. On the camel this builds the same tree as
the plain binned sweep 1.5x faster (0.48 against 0.32 s).

Surface area heuristic (Goldsmith & Salmon 1987; MacDonald & Booth 1990), binned as in
Wald, "On fast construction of SAH-based bounding volume hierarchies" (IEEE RT 2007):
centroids of the triangles' boxes go into ``bins`` equal bins of the node's centroid
bounds along each axis; the split between bins i and i+1 costs

    C_T + C_I * (A(L) N(L) + A(R) N(R)) / A(node)

against ``C_I * N`` for a leaf (A the surface area, N the triangle count). A node with
more than ``max_leaf_size`` triangles is always split; one whose centroids all coincide
is split at its middle row (no plane can separate them).

Wide nodes. The binary tree is collapsed into nodes of up to ``width`` children (2, 4
or 8; default 4), as Embree's BVH4/BVH8 and Wald, Benthin & Boulos, "Getting rid of
packets" (RT 2008): from the root down, a node's child with the largest surface area that
is not a leaf is replaced by its two children until the node has ``width`` children or
only leaves. The leaves (and their triangles) are those of the binary tree. A wide node
costs a traversal step about as much as a binary one (the engine's per-step work is in
its passes over the lanes, not in the box tests), and the camel needs 40 % fewer steps
per ray with width 4 (``python -m benchmarks.bvh`` quotes both).

Layout (one row per *interior* node, child boxes stored in the parent as in Aila & Laine
2009 and tinybvh's ``BVH_GPU``, so one gather brings all the boxes a step tests). The
child boxes are quantised to 8 bits in the frame of their parent, as in Ylitie, Karras &
Laine, "Efficient incoherent ray traversal on GPUs through compressed wide BVHs" (HPG
2017): a row of a 4-wide node is 64 bytes, one cache line, where exact float32 boxes took
two. The node gather is memory-bound; on the camel's incoherent rays the quantised rows
traced 1.05-1.10x faster (width 4; 1.10x at width 8), for 1.5 % more steps. ``nodes`` is
int32 [M, R], R = :func:`row_words` (16 words for W = 2 or 4, 32 for W = 8); for W = 4:

    bytes   0-11  words  0-2   origin x, y, z: float32 bit patterns
    bytes  12-23  words  3-5   scale x, y, z: float32 bit patterns, powers of two
    bytes  24-47  words  6-11  quantised bounds, one byte each: byte ``f * W + c`` of
                               these 24 (little-endian words) is field f of child c,
                               fields f = lower x, y, z, upper x, y, z
    bytes  48-63  words 12-15  references of children 0-3

(W = 2: 12 bytes of bounds in words 6-8, references in words 9-10, words 11-15 zero;
W = 8: 48 bytes in words 6-17, references in words 18-25, words 26-31 zero.) Child c's
box on axis a is ``origin[a] + q * scale[a]`` for its byte q of the lower and of the upper
field, computed in float32: ``q * scale`` is exact (an 8-bit integer times a power of
two), so the decoded bound is one rounding of the exact sum whether or not the compiler
fuses the multiply-add, and the build checks each decoded bound with that same sum: a
child's decoded box contains its exact float32 box (within one ``scale`` of it on each
side). The origin is the lower corner of the union of the children's boxes and ``scale``
the smallest power of two at least 1/255 of its extent (at least 2^-100, a normal
float); see :func:`node_rows` and :func:`child_boxes`.

Every box is in the structure's local frame: ``frame`` float32 [3] (12 bytes) is its
origin, the point of the triangles' bounding box nearest the coordinate origin (0 for a
scene around the origin: ``accel.geometry.frame_origin``), and
each triangle's box is its exact box minus ``frame``, rounded outward to float32. The
engine moves every ray's origin into that frame before the box tests (``jrt.engine``),
whose margins (2^-16 of the box's and the origin's magnitudes) then follow the scene's
extent and the ray's distance from it, not the scene's position: far from the coordinate
origin the boxes stay as tight, and the steps per ray as few, as at the origin. The
triangles themselves stay in world coordinates (the kernels read them).

A reference ``r >= 0`` is the row of an interior node. ``r < 0`` is a leaf:
``~r = (first << leaf_bits) | count``, the leaf's triangles being rows
``first .. first+count-1`` of ``triangles`` (stored in leaf order). ``r = -1`` (``~0``:
no triangle) is an empty slot, whose bytes are lower 255 and upper 0 (an inverted box);
traversals skip it by its reference. Row 0 is the root and rows are in breadth-first
order; when the whole tree is one leaf (one triangle, or a few that the SAH keeps
together), row 0 is a root whose child 0 is that leaf.
"""

from __future__ import annotations

import time

import numpy as np

from accel.geometry import (
    degenerate_mask,
    float32_down,
    float32_up,
    frame_origin,
    leaf_bits_for,
    leaf_references,
    local_corners,
    triangle_vertices,
)
from accel.registry import StructureKind, world_planes
from accel.structure import Structure
from accel.threads import node_chunks, thread_map, threads_for

#: Defaults: 16 bins (Wald 2007 found 16-32 bins within a few percent of a full SAH
#: sweep); costs C_T = 1/2, C_I = 1 as pbrt-v4's BVH (Pharr, Jakob & Humphreys, 4th ed.,
#: section 7.3.2); leaves of at most 4 triangles (on the camel, leaves of at most 2, 3
#: and 4 traced within noise of each other).
DEFAULT_BINS = 16
DEFAULT_MAX_LEAF_SIZE = 4
DEFAULT_TRAVERSAL_COST = 0.5
DEFAULT_INTERSECTION_COST = 1.0
MAX_DEPTH = 64
METHODS = ("sah", "median")
WIDTHS = (2, 4, 8)
DEFAULT_WIDTH = 4
#: The reference of an empty child slot (a leaf of no triangle).
EMPTY_SLOT = -1


#: Words of a node row before the quantised bounds: the frame's origin and scale.
FRAME_WORDS = 6
#: Quantisation levels of a bound (one byte): a child's bound is origin + q * scale.
QUANT_MAX = 255
#: The smallest scale exponent: scales stay normal floats (no flush to zero).
MIN_SCALE_EXPONENT = -100


def bound_words(width: int) -> int:
    """Words holding the quantised bounds of a row: 6 bytes a child."""
    return -(-6 * width // 4)


def reference_column(width: int) -> int:
    """The word of child 0's reference in a row (children's references follow)."""
    return FRAME_WORDS + bound_words(width)


def row_words(width: int) -> int:
    """Words of a node row: frame, bounds and references, rounded up to 64-byte lines."""
    return -(-(reference_column(width) + width) // 16) * 16


def _half_area(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Half the surface area of boxes [..., 3]; 0 for empty (inverted) boxes."""
    e = np.maximum(hi - lo, 0.0)
    return e[..., 0] * e[..., 1] + e[..., 1] * e[..., 2] + e[..., 2] * e[..., 0]


def _check_params(method, bins, max_leaf_size, traversal_cost, intersection_cost, width):
    if method not in METHODS:
        raise ValueError(f"bvh: unknown method {method!r}; allowed: {', '.join(METHODS)}")
    if not (isinstance(width, int | np.integer) and not isinstance(width, bool)
            and width in WIDTHS):
        raise ValueError(f"bvh: width must be one of {', '.join(map(str, WIDTHS))}, "
                         f"got {width!r}")
    if not (isinstance(bins, int | np.integer) and 2 <= bins <= 256):
        raise ValueError(f"bvh: bins must be an integer in [2, 256], got {bins!r}")
    if not (isinstance(max_leaf_size, int | np.integer) and 1 <= max_leaf_size <= 255):
        raise ValueError(
            f"bvh: max_leaf_size must be an integer in [1, 255], got {max_leaf_size!r}")
    for name, value in (("traversal_cost", traversal_cost),
                        ("intersection_cost", intersection_cost)):
        if not (np.isfinite(value) and value > 0):
            raise ValueError(f"bvh: {name} must be a positive finite number, got {value!r}")


def _segment_ids(counts: np.ndarray) -> np.ndarray:
    return np.repeat(np.arange(counts.shape[0]), counts)


def _ranks_in_segments(flags: np.ndarray, offsets: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """For each element, how many flagged elements precede it in its segment (segments
    of ``counts`` elements from ``offsets``, in order)."""
    c = np.cumsum(flags) - flags
    return c - np.repeat(c[offsets], counts)


def _sah_splits(lo, hi, cent, seg, counts, cmin, cmax, node_area, bins, ct, ci):
    """Best binned-SAH split of every segment: (cost, axis, bin) each [K], and the bins
    ``b`` [n, 3] of the level's rows.

    A segment of at most ``bins`` triangles is swept over its sorted triangles
    (:func:`_sorted_splits`, the segments grouped by size: up to 2, 4, 8, ...), a larger
    one over its bins (:func:`_binned_splits`): both find the same split (the same cost,
    axis and bin). Deep in the tree most segments hold a few triangles, where a sweep over
    ``bins`` bins per segment did 4x the triangles' work (65 % of the camel's build).
    """
    k = counts.shape[0]
    extent = cmax - cmin
    scale = np.where(extent > 0, bins * (1 - 1e-9) / np.where(extent > 0, extent, 1), 0.0)
    # (np.repeat over the segments: 2.5x faster than gathering through ``seg``.)
    b = cent - np.repeat(cmin, counts, axis=0)
    b *= np.repeat(scale, counts, axis=0)
    b = np.clip(b, 0, bins - 1, out=b).astype(np.int64)
    cost = np.full(k, np.inf)
    axis = np.zeros(k, np.int64)
    split_bin = np.zeros(k, np.int64)
    # Segments by size: up to 2, 4, 8, ... triangles (padded to that many slots), and the
    # ones above ``bins``. Each group is searched in runs of its segments, spread over
    # threads (accel.threads): a segment's split depends on its own rows only, so the
    # result does not depend on the runs.
    widths = [w for w in (2, 4, 8, 16, 32, 64, 128, 256) if w < bins] + [bins]
    group = np.searchsorted(np.asarray(widths), counts)
    runs = []
    for g in np.unique(group):
        members = np.flatnonzero(group == g)
        # A group is cut only from 64k rows a thread: cut from 4k (accel.threads' least),
        # the camel's small groups built no faster (0.43 against 0.41 s).
        parts = threads_for(int(counts[members].sum()) // 16)
        runs += [(g, members[first:end])
                 for first, end, _, _ in node_chunks(counts[members], parts=parts)]

    def search(run):
        g, members = run
        if members.size == k:
            args = (lo, hi, b, seg, counts, node_area)
        else:
            part = np.zeros(k, bool)
            part[members] = True
            rows = part[seg]
            sub_seg = (np.cumsum(part) - 1)[seg[rows]]
            args = (lo[rows], hi[rows], b[rows], sub_seg, counts[part], node_area[part])
        if g < len(widths):
            return _sorted_splits(*args, widths[g], bins, ct, ci)
        return _binned_splits(*args, bins, ct, ci)

    threads = threads_for(seg.shape[0])
    for (_, members), found in zip(runs, thread_map(search, runs, threads), strict=True):
        cost[members], axis[members], split_bin[members] = found
    return cost, axis, split_bin, b


def _split_costs(al, ar, nl, nr, node_area, ct, ci):
    """The SAH cost of splits, inf where a side is empty or the cost is not finite.

    ``al``, ``ar`` float32 half areas, ``nl``, ``nr`` int64 counts, ``node_area`` float64:
    the same operations in the same types for both sweeps, so that they agree bit for bit.
    """
    with np.errstate(invalid="ignore", divide="ignore"):
        cost = ct + ci * (al * nl + ar * nr) / node_area
    cost[(nl == 0) | (nr == 0) | ~np.isfinite(cost)] = np.inf
    return cost


def _binned_splits(lo, hi, b, seg, counts, node_area, bins, ct, ci):
    """Binned SAH (Wald 2007) of segments: per (axis, bin, segment) the triangle count
    and box, swept from both ends; (cost, axis, bin) each [K].

    Arrays are laid out [axis, bin, segment, ...] so that the sweeps along the bins run
    over contiguous rows.
    """
    k = counts.shape[0]
    # One key per (triangle, axis): (axis, bin, segment).
    key = ((np.arange(3)[None, :] * bins + b) * k + seg[:, None]).T.reshape(-1)
    n = np.bincount(key, minlength=3 * bins * k).reshape(3, bins, k)
    # Bin boxes in float32: min and max of float32 corners are exact, and half the bytes
    # make the sweeps (memory bound) twice as fast.
    blo = np.full((3, 3 * bins * k), np.inf, np.float32)
    bhi = np.full((3, 3 * bins * k), -np.inf, np.float32)
    for j in range(3):
        np.minimum.at(blo[j], key, np.tile(lo[:, j], 3))
        np.maximum.at(bhi[j], key, np.tile(hi[:, j], 3))
    blo = blo.reshape(3, 3, bins, k)  # [coordinate, axis, bin, segment]
    bhi = bhi.reshape(3, 3, bins, k)
    # Sweep: left = bins 0..i, right = bins i+1..; empty sides have inverted boxes.
    nl = np.cumsum(n, axis=1)[:, :-1]
    nr = counts[None, None, :] - nl
    al = _half_area_t(_sweep(np.minimum, blo)[:, :, :-1], _sweep(np.maximum, bhi)[:, :, :-1])
    ar = _half_area_t(_sweep(np.minimum, blo, reverse=True)[:, :, 1:],
                      _sweep(np.maximum, bhi, reverse=True)[:, :, 1:])
    cost = _split_costs(al, ar, nl, nr, node_area[None, None, :], ct, ci)
    flat = cost.reshape(3 * (bins - 1), k)
    best = np.argmin(flat, axis=0)
    return flat[best, np.arange(k)], best // (bins - 1), best % (bins - 1)


def _sorted_splits(lo, hi, b, seg, counts, node_area, width, bins, ct, ci):
    """The binned SAH of segments of at most ``width`` (<= ``bins``) triangles, swept over
    each segment's triangles sorted by bin instead of over the bins: (cost, axis, bin)
    each [K].

    A split between bins i and i+1 puts the triangles of bins <= i on the left, so the
    distinct candidates are the prefixes of the sorted triangles that end where the bin
    changes; the empty bins between two occupied ones repeat the cost of the first of
    them, which the binned sweep's first minimum picks. So the candidate after sorted
    triangle j, on axis a, is reported as bin ``b[j, a]``, and the first minimum over
    (axis, j) is the binned sweep's (axis, bin). Boxes, areas and costs are computed in
    the same types and order (:func:`_split_costs`): the same floats.
    """
    k = counts.shape[0]
    offsets = np.cumsum(counts) - counts
    slot = np.arange(seg.shape[0]) - offsets[seg]
    # [K, width] slots, padded with bin ``bins`` (sorted last) and inverted boxes.
    key = np.full((3, k, width), bins, np.int64)
    key[:, seg, slot] = b.T
    order = np.argsort(key, axis=2, kind="stable")
    sorted_bins = np.take_along_axis(key, order, axis=2).transpose(0, 2, 1)  # [3, width, K]
    row = np.full((k, width), -1, np.int64)
    row[seg, slot] = np.arange(seg.shape[0])
    lo_pad = np.concatenate([lo, np.full((1, 3), np.inf, np.float32)])  # row -1: the pad
    hi_pad = np.concatenate([hi, np.full((1, 3), -np.inf, np.float32)])
    nl = np.arange(1, width, dtype=np.int64)[:, None]
    nr = counts[None, :] - nl
    cost = np.empty((3, width - 1, k))
    for a in range(3):
        rows = np.take_along_axis(row, order[a], axis=1).T  # [width, K], pads last
        slo, shi = lo_pad[rows], hi_pad[rows]  # [width, K, 3], in sorted order
        left_lo, left_hi = _sweep(np.minimum, slo, axis=0), _sweep(np.maximum, shi, axis=0)
        right_lo = _sweep(np.minimum, slo, reverse=True, axis=0)
        right_hi = _sweep(np.maximum, shi, reverse=True, axis=0)
        c = _split_costs(_half_area(left_lo[:-1], left_hi[:-1]),
                         _half_area(right_lo[1:], right_hi[1:]), nl, nr, node_area[None, :],
                         ct, ci)
        # Within one bin no plane separates the triangles (past the last one, nr <= 0).
        c[sorted_bins[a, :-1] == sorted_bins[a, 1:]] = np.inf
        cost[a] = c
    flat = cost.reshape(3 * (width - 1), k)
    best = np.argmin(flat, axis=0)
    axis, j = best // (width - 1), best % (width - 1)
    best_cost = flat[best, np.arange(k)]
    # A segment with no finite split: the binned sweep's first candidate, axis 0, bin 0.
    none = ~np.isfinite(best_cost)
    return best_cost, np.where(none, 0, axis), np.where(none, 0, sorted_bins[axis, j, np.arange(k)])


def _sweep(op: np.ufunc, a: np.ndarray, reverse: bool = False, axis: int = 2) -> np.ndarray:
    """Running ``op`` (minimum or maximum) of ``a`` along ``axis`` (the bins of
    [c, axis, bin, segment] by default), from its first index (or from its last,
    ``reverse``).

    Same values as ``op.accumulate(a, axis=axis)``, computed one index at a time over
    contiguous slices: NumPy's accumulate along a middle axis ran 14x slower (19 against
    1.3 ms on [3, 3, 16, 20000] float32), a third of the camel's build.
    """
    out = a.copy()
    rows = np.moveaxis(out, axis, 0)  # a view: writing its rows writes ``out``
    order = range(a.shape[axis] - 1, -1, -1) if reverse else range(a.shape[axis])
    for previous, i in zip(order, order[1:], strict=False):
        op(rows[previous], rows[i], out=rows[i])
    return out


def _half_area_t(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Half the surface area of boxes with the coordinate on the first axis."""
    e = np.maximum(hi - lo, 0.0)
    return e[0] * e[1] + e[1] * e[2] + e[2] * e[0]


def build(
    vertices: np.ndarray,
    faces: np.ndarray,
    *,
    method: str = "sah",
    bins: int = DEFAULT_BINS,
    max_leaf_size: int = DEFAULT_MAX_LEAF_SIZE,
    traversal_cost: float = DEFAULT_TRAVERSAL_COST,
    intersection_cost: float = DEFAULT_INTERSECTION_COST,
    width: int = DEFAULT_WIDTH,
) -> Structure:
    """Build a BVH over the non-degenerate faces.

    Args:
        method: ``"sah"`` (binned SAH, Wald 2007) or ``"median"`` (object median: split
            the node's triangles in two halves along the longest axis of their centroids).
        bins: SAH bins per axis.
        max_leaf_size: nodes with more triangles are always split.
        traversal_cost, intersection_cost: the SAH constants C_T and C_I.
        width: children per node of the flattened tree (2, 4 or 8), see the module's
            docstring.
    """
    _check_params(method, bins, max_leaf_size, traversal_cost, intersection_cost, width)
    start_time = time.perf_counter()
    keep = ~degenerate_mask(vertices, faces)
    ids = np.flatnonzero(keep).astype(np.int32)
    tris = triangle_vertices(vertices, np.asarray(faces)[ids])
    t_count = ids.shape[0]
    # Boxes in the local frame (accel.geometry.frame_origin), each float32 triangle's
    # exact box rounded outward.
    frame = frame_origin(tris)
    local = local_corners(tris, frame)
    # (Elementwise over the three corners: a reduction along the middle axis ran 5x slower.)
    lo32 = float32_down(np.minimum(np.minimum(local[:, 0], local[:, 1]), local[:, 2]))
    hi32 = float32_up(np.maximum(np.maximum(local[:, 0], local[:, 1]), local[:, 2]))
    cent = 0.5 * (lo32.astype(np.float64) + hi32.astype(np.float64))

    order = np.arange(t_count)
    # Nodes in creation (breadth-first) order. Per node: box, range of rows, children.
    node_lo, node_hi, node_first, node_count, node_depth = [], [], [], [], []
    # Active segments of this level: (node id, first row, count, box), and their rows'
    # triangles, centroids and boxes, in segment order. The rows are carried from level to
    # level in the order the partition leaves them (one gather per level), not gathered
    # again from the whole mesh through ``order``.
    seg_node = np.zeros(1 if t_count else 0, np.int64)
    seg_first = np.zeros_like(seg_node)
    seg_count = np.full_like(seg_node, t_count)
    seg_lo = lo32.min(axis=0, initial=np.inf)[None]  # (no triangle: no segment)
    seg_hi = hi32.max(axis=0, initial=-np.inf)[None]
    tri, c, tlo, thi = order.copy(), cent, lo32, hi32
    next_node = 1 if t_count else 0
    if t_count:
        node_lo.append(seg_lo)
        node_hi.append(seg_hi)
        node_first.append(np.zeros(1, np.int64))
        node_count.append(np.full(1, t_count, np.int64))
        node_depth.append(np.zeros(1, np.int64))
    # Parent id -> first child's id, level by level (children get consecutive ids).
    parent_ids, first_child_ids = [], []
    depth = 0
    forced_leaves = 0
    while seg_node.shape[0]:
        split = seg_count > max_leaf_size if method == "median" else seg_count > 1
        if depth >= MAX_DEPTH:
            forced_leaves += int(split.sum())
            break
        if not split.all():
            kept = np.repeat(split, seg_count)
            tri, c, tlo, thi = tri[kept], c[kept], tlo[kept], thi[kept]
            seg_node, seg_first, seg_count = seg_node[split], seg_first[split], seg_count[split]
            seg_lo, seg_hi = seg_lo[split], seg_hi[split]
        k = seg_node.shape[0]
        if k == 0:
            break
        seg = _segment_ids(seg_count)
        offsets = np.cumsum(seg_count) - seg_count

        def per_row(values, counts=seg_count):  # a segment's value on each of its rows
            return np.repeat(values, counts, axis=0)

        if method == "sah":
            cmin = np.minimum.reduceat(c, offsets, axis=0)
            cmax = np.maximum.reduceat(c, offsets, axis=0)
            node_area = _half_area(seg_lo.astype(np.float64), seg_hi.astype(np.float64))
            cost, axis, split_bin, b = _sah_splits(
                tlo, thi, c, seg, seg_count, cmin, cmax, node_area, bins, traversal_cost,
                intersection_cost)
            leaf_cost = intersection_cost * seg_count
            no_plane = ~np.isfinite(cost)
            make_leaf = (seg_count <= max_leaf_size) & (no_plane | (cost >= leaf_cost))
            go_left = (np.take_along_axis(b, per_row(axis)[:, None], axis=1)[:, 0]
                       <= per_row(split_bin))
            # No plane separates coincident centroids: split at the middle row.
            if no_plane.any():
                mid = (np.arange(seg.shape[0]) - per_row(offsets)) < per_row(seg_count // 2)
                go_left = np.where(per_row(no_plane), mid, go_left)
        else:
            make_leaf = np.zeros(k, bool)
            axis = np.argmax(np.maximum.reduceat(c, offsets, axis=0)
                             - np.minimum.reduceat(c, offsets, axis=0), axis=1)
            # Sort each segment by its centroid along its own axis; left = lower half.
            perm = np.lexsort((c[np.arange(seg.shape[0]), axis[seg]], seg))
            tri, c, tlo, thi = tri[perm], c[perm], tlo[perm], thi[perm]
            go_left = np.arange(seg.shape[0]) - offsets[seg] < seg_count[seg] // 2
        # Leaves stay as they are; the others are partitioned (stable) into two children.
        splitting = ~make_leaf
        moving = per_row(splitting)
        go_left &= moving
        n_left = np.bincount(seg, weights=go_left, minlength=k).astype(np.int64)
        rank_left = _ranks_in_segments(go_left, offsets, seg_count)
        slot = np.arange(seg.shape[0]) - per_row(offsets)
        # Left rows first, then right ones, each in their order: a stable partition.
        in_segment = np.where(go_left, rank_left, per_row(n_left) + slot - rank_left)
        order[(in_segment + per_row(seg_first))[moving]] = tri[moving]

        parents = seg_node[splitting]
        first = seg_first[splitting]
        count = seg_count[splitting]
        nl = n_left[splitting]
        m = parents.shape[0]
        if m == 0:
            break
        # The splitting segments' rows, partitioned, become the next level's rows.
        kept_before = np.cumsum(np.where(splitting, seg_count, 0)) - np.where(
            splitting, seg_count, 0)
        source = np.empty(int(count.sum()), np.int64)
        source[(in_segment + per_row(kept_before))[moving]] = np.flatnonzero(moving)
        tri, c, tlo, thi = tri[source], c[source], tlo[source], thi[source]
        child_first = np.stack([first, first + nl], axis=1).reshape(-1)
        child_count = np.stack([nl, count - nl], axis=1).reshape(-1)
        child_ids = next_node + np.arange(2 * m)
        parent_ids.append(parents)
        first_child_ids.append(child_ids[::2])
        next_node += 2 * m
        # Child boxes: exact float32 bounds of their rows.
        coff = np.cumsum(child_count) - child_count
        seg_lo = np.minimum.reduceat(tlo, coff, axis=0)
        seg_hi = np.maximum.reduceat(thi, coff, axis=0)
        node_lo.append(seg_lo)
        node_hi.append(seg_hi)
        node_first.append(child_first)
        node_count.append(child_count)
        depth += 1
        node_depth.append(np.full(2 * m, depth, np.int64))
        seg_node, seg_first, seg_count = child_ids, child_first, child_count

    return _flatten(
        tris, ids, frame, order, node_lo, node_hi, node_first, node_count, node_depth,
        (parent_ids, first_child_ids), method=method, bins=bins, max_leaf_size=max_leaf_size,
        width=int(width), ct=traversal_cost,
        ci=intersection_cost, degenerate=int((~keep).sum()), forced_leaves=forced_leaves,
        start_time=start_time,
    )


def _segment_rows(first: np.ndarray, count: np.ndarray) -> np.ndarray:
    seg = _segment_ids(count)
    offsets = np.cumsum(count) - count
    return np.arange(seg.shape[0]) - offsets[seg] + first[seg]


def _collapse(child_lo, child_hi, child_ref, width):
    """Binary interior rows (children [m, 2, ...], breadth first) into wide nodes.

    Returns the wide nodes' children ``lo``, ``hi`` [K, W, 3], ``ref`` [K, W] (interior
    references renumbered to wide rows, breadth first; empty slots ``EMPTY_SLOT`` with
    zero boxes) and the number of wide levels. Vectorised over each level's nodes.
    """
    m = child_ref.shape[0]
    levels_lo, levels_hi, levels_ref = [], [], []
    level = np.zeros(1 if m else 0, np.int64)  # the binary rows that become this level
    next_row = 1
    while level.size:
        k = level.size
        ref = np.full((k, width), EMPTY_SLOT, np.int64)
        lo = np.zeros((k, width, 3), np.float32)
        hi = np.zeros((k, width, 3), np.float32)
        ref[:, :2], lo[:, :2], hi[:, :2] = child_ref[level], child_lo[level], child_hi[level]
        count = np.full(k, 2)
        for _ in range(width - 2):
            # Open the interior child of largest surface area, where there is one.
            area = np.where(ref >= 0, _half_area(lo, hi), -1.0)
            slot = np.argmax(area, axis=1)
            nodes = np.flatnonzero(area[np.arange(k), slot] >= 0)
            if not nodes.size:
                break
            slot, opened, last = slot[nodes], ref[nodes, slot[nodes]], count[nodes]
            for target, side in ((slot, 0), (last, 1)):
                ref[nodes, target] = child_ref[opened, side]
                lo[nodes, target] = child_lo[opened, side]
                hi[nodes, target] = child_hi[opened, side]
            count[nodes] += 1
        interior = ref >= 0
        rows = next_row + np.cumsum(interior.reshape(-1)).reshape(k, width) - 1
        levels_lo.append(lo)
        levels_hi.append(hi)
        levels_ref.append(np.where(interior, rows, ref))
        next_row += int(interior.sum())
        level = ref[interior]
    if not levels_ref:
        return (np.zeros((0, width, 3), np.float32), np.zeros((0, width, 3), np.float32),
                np.zeros((0, width), np.int64), 0)
    return (np.concatenate(levels_lo), np.concatenate(levels_hi),
            np.concatenate(levels_ref), len(levels_ref))


def _decode(origin, scale, q):
    """``origin + q * scale`` in float32, as the traversal computes it (q * scale exact)."""
    return (origin + q.astype(np.float32) * scale).astype(np.float32)


def node_rows(lo: np.ndarray, hi: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """The documented int32 node rows from children ``lo``, ``hi`` [K, W, 3] (float32,
    exact boxes) and ``ref`` [K, W]: each child's box quantised, conservatively, in the
    frame of the union of the node's filled children (see the module's layout)."""
    k, width = ref.shape
    lo, hi = np.asarray(lo, np.float32), np.asarray(hi, np.float32)
    filled = (ref != EMPTY_SLOT)[..., None]
    origin = np.where(filled, lo, np.inf).min(axis=1)  # [K, 3]
    top = np.where(filled, hi, -np.inf).max(axis=1)
    origin = np.where(np.isfinite(origin), origin, 0).astype(np.float32)
    top = np.where(np.isfinite(top), top, 0).astype(np.float32)
    step = (top.astype(np.float64) - origin) / QUANT_MAX
    exponent = np.ceil(np.log2(np.maximum(step, np.ldexp(1.0, MIN_SCALE_EXPONENT))))
    # origin + 255 scale >= top exactly, so its float32 rounding is >= top as well.
    scale = np.ldexp(np.float32(1), exponent.astype(np.int32)).astype(np.float32)
    origin, scale = origin[:, None], scale[:, None]  # [K, 1, 3] against children [K, W, 3]
    offset_lo = (lo.astype(np.float64) - origin) / scale
    offset_hi = (hi.astype(np.float64) - origin) / scale
    q_lo = np.clip(np.floor(offset_lo), 0, QUANT_MAX).astype(np.int32)
    q_hi = np.clip(np.ceil(offset_hi), 0, QUANT_MAX).astype(np.int32)
    # The float32 sum may round past the exact bound: step out until it contains it
    # (q = 0 gives the origin, q = 255 at least the top: one or two steps at most).
    for _ in range(QUANT_MAX + 1):
        low = (_decode(origin, scale, q_lo) > lo) & filled
        high = (_decode(origin, scale, q_hi) < hi) & filled
        if not (low.any() or high.any()):
            break
        q_lo, q_hi = q_lo - low, q_hi + high
    else:
        raise ValueError("bvh: child boxes could not be quantised (non-finite bounds?)")
    q_lo = np.where(filled, q_lo, QUANT_MAX)
    q_hi = np.where(filled, q_hi, 0)
    # Bytes field-major: byte f * W + c is field f (lower x, y, z, upper x, y, z) of child c.
    fields = np.concatenate([q_lo, q_hi], axis=2).transpose(0, 2, 1).reshape(k, 6 * width)
    bound_bytes = np.zeros((k, 4 * bound_words(width)), "<u1")
    bound_bytes[:, :6 * width] = fields
    column = reference_column(width)
    nodes = np.zeros((k, row_words(width)), np.int32)
    nodes[:, 0:3] = origin[:, 0].view(np.int32)
    nodes[:, 3:FRAME_WORDS] = scale[:, 0].view(np.int32)
    nodes[:, FRAME_WORDS:column] = bound_bytes.view("<i4")
    nodes[:, column:column + width] = ref.astype(np.int32)
    return nodes


def child_references(nodes: np.ndarray, width: int) -> np.ndarray:
    """The children's references, int32 [K, W], of documented node rows."""
    column = reference_column(width)
    return np.asarray(nodes)[:, column:column + width]


def child_boxes(nodes: np.ndarray, width: int) -> tuple[np.ndarray, np.ndarray]:
    """The children's boxes as the traversal decodes them: ``lo``, ``hi`` float32 [K, W, 3].

    An empty slot decodes to an inverted box (lower at the frame's top, upper at its
    origin)."""
    nodes = np.ascontiguousarray(nodes, np.int32)
    origin = nodes[:, None, 0:3].view(np.float32)
    scale = nodes[:, None, 3:6].view(np.float32)
    bound_bytes = nodes[:, FRAME_WORDS:reference_column(width)].view("<u1")
    q = bound_bytes[:, :6 * width].reshape(-1, 6, width).transpose(0, 2, 1)  # [K, W, 6]
    return _decode(origin, scale, q[..., :3]), _decode(origin, scale, q[..., 3:])


def _flatten(tris, ids, frame, order, node_lo, node_hi, node_first, node_count, node_depth, links,
             *, method, bins, max_leaf_size, width, ct, ci, degenerate, forced_leaves,
             start_time):
    if node_lo:
        lo = np.concatenate(node_lo)
        hi = np.concatenate(node_hi)
        first = np.concatenate(node_first)
        count = np.concatenate(node_count)
        depth = np.concatenate(node_depth)
    else:  # no triangle at all: one empty leaf
        lo = hi = np.zeros((1, 3), np.float32)
        first = count = depth = np.zeros(1, np.int64)
    total = lo.shape[0]
    left = np.full(total, -1, np.int64)
    if links[0]:
        left[np.concatenate(links[0])] = np.concatenate(links[1])
    interior = left >= 0
    try:
        leaf_bits = leaf_bits_for(first[~interior], count[~interior], tris.shape[0])
    except ValueError as error:
        raise ValueError(f"bvh: {error}") from None
    # Binary interior rows: breadth-first order of the interior nodes; the root is row 0.
    row_of = np.cumsum(interior) - 1
    ref = np.where(interior, row_of, leaf_references(first, count, leaf_bits))
    if interior[0]:
        parents = np.flatnonzero(interior)
        kids = np.stack([left[parents], left[parents] + 1], axis=1)
        child_lo, child_hi, child_ref = lo[kids], hi[kids], ref[kids]
    else:  # a root leaf: child 0 is the leaf, child 1 an empty slot
        child_lo = np.stack([lo[0], np.zeros(3, np.float32)])[None]
        child_hi = np.stack([hi[0], np.zeros(3, np.float32)])[None]
        child_ref = np.asarray([[ref[0], EMPTY_SLOT]])
    wide_lo, wide_hi, wide_ref, levels = _collapse(child_lo, child_hi, child_ref, width)
    nodes = node_rows(wide_lo, wide_hi, wide_ref)

    triangles = np.ascontiguousarray(tris[order])
    triangle_ids = ids[order]
    leaves = ~interior
    leaf_counts = count[leaves]
    # SAH cost of the tree as stored: every child's box as the traversal decodes it (an
    # interior child's or a leaf's; an empty slot's inverted box has no area), and the
    # root's, the union of its children's.
    child_lo, child_hi = (b.astype(np.float64) for b in child_boxes(nodes, width))
    filled = wide_ref != EMPTY_SLOT
    areas = _half_area(child_lo, child_hi)
    root_area = _half_area(np.where(filled[0, :, None], child_lo[0], np.inf).min(axis=0),
                           np.where(filled[0, :, None], child_hi[0], -np.inf).max(axis=0))
    leaf_slot = filled & (wide_ref < 0)
    slot_counts = (~wide_ref[leaf_slot]) & ((1 << leaf_bits) - 1)
    leaf_area = (areas[leaf_slot] * slot_counts).sum()
    interior_area = areas[wide_ref >= 0].sum() + root_area if interior[0] else 0.0
    if root_area > 0:
        sah = (ct * interior_area + ci * leaf_area) / root_area
    else:
        sah = float(ci * leaf_counts.sum())
    wide_interior = int(wide_ref.shape[0]) if interior[0] else 0
    arrays = {"nodes": nodes, "triangles": triangles, "triangle_ids": triangle_ids,
              "frame": np.asarray(frame, np.float32)}
    stats = {
        "build_seconds": time.perf_counter() - start_time,
        "method": method,
        "bins": bins,
        "max_leaf_size": max_leaf_size,
        "width": width,
        "triangles": int(tris.shape[0]),
        "degenerate_skipped": degenerate,
        "nodes": wide_interior + int(leaves.sum()),
        "interior_nodes": wide_interior,
        "leaves": int(leaves.sum()),
        "depth": levels if interior[0] else 0,
        "binary_depth": int(depth.max()) if total else 0,
        "triangles_per_leaf_mean": float(leaf_counts.mean()) if leaf_counts.size else 0.0,
        "triangles_per_leaf_max": int(leaf_counts.max()) if leaf_counts.size else 0,
        "leaves_over_max_depth": forced_leaves,
        "sah_cost": float(sah),
        "bytes": int(sum(a.nbytes for a in arrays.values())),
    }
    return Structure(kind="bvh", arrays=arrays,
                     layout=(("leaf_bits", leaf_bits), ("width", width)), stats=stats)


def stored_planes(structure: Structure) -> list[np.ndarray]:
    """Per axis, the faces of every decoded child box (the empty slots' inverted boxes
    too), in world coordinates: the planes the traversal's slab tests compare against."""
    lo, hi = child_boxes(np.asarray(structure["nodes"]), structure.layout_value("width"))
    return world_planes(structure, [np.concatenate([lo[..., a].ravel(), hi[..., a].ravel()])
                                    for a in range(3)])


KIND = StructureKind(
    name="bvh", build=build,
    arrays=frozenset({"nodes", "triangles", "triangle_ids", "frame"}),
    layout=frozenset({"leaf_bits", "width"}), traversal="jrt.bvh:traversal", planes=stored_planes,
    rows=frozenset({"nodes", "triangles", "triangle_ids"}), refit="jrt.refitting:refit_bvh",
    summary="bounding volume hierarchy: SAH-binned, 2-, 4- or 8-wide nodes")
