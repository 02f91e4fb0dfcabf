"""General-plane BSP tree (Ize, Wald & Parker, "Ray tracing with the BSP tree", IEEE RT
2008), SAH-like cost, binned, built level by level.

Like the kd-tree (``accel.kdtree``) a node's region is cut in two and a triangle is
referenced by every leaf whose region it reaches, but the planes ``n . x = c`` may have any
orientation. Candidates per node (as Ize et al.: triangle planes and a few fixed
orientations):

- the 3 axis normals, at every node;
- at nodes with at least ``general_min_references`` (64) references, the 4 body diagonals
  (±1, ±1, 1)/sqrt(3) and the planes of ``triangle_planes`` of the node's triangles (a
  deterministic sample: evenly spaced in the node's reference list), each orientation
  with its triangle's own offset as a candidate as well;
- offsets along every candidate normal binned as in ``accel.kdtree``: the interior
  boundaries of ``bins`` equal bins spanning the projections of the node's triangles, and
  empty-space cuts just outside them.

**Cost** (the SAH of MacDonald & Booth 1990 with Wald & Havran's empty-space bonus, as
``accel.kdtree``). Ize et al. measure the exact surface areas of the convex polytopes;
here a node's region is approximated by its axis-aligned bounding box B, and the area of
a side by that of the bounding box of ``B ∩ {n . x <= c}`` (in closed form: per axis, the
extreme coordinate of the box that the half-space allows). This is exact for axis-aligned
planes and overestimates both sides of an oblique cut. N_L, N_R count triangles with a
vertex on each side (whole triangles, projected on n), from bins as the kd-tree does; the
triangle-plane candidates are counted exactly.

**Which side a triangle goes to**: each side whose half-space, widened by the triangle's
margin ``delta = CELL_MARGIN * (sum_i |n_i| (hi_i - lo_i) + extent)`` (B's size along n
and the triangle's own extent, ``accel.geometry.reference_margin``, which says why that
suffices with the traversal's run-time margins), holds one of its vertices (in float64,
with the stored float32 plane, in the structure's local frame). A triangle meets a
half-space iff one of its vertices lies in it, so every triangle that reaches a leaf's
widened region is referenced there (straddlers on both sides). Neither term depends on
where the scene sits or how far apart its objects are.

On the camel the SAH picks an oblique plane at some 450 of 97,700 nodes (general planes at
every node of 16 or more references were picked at 50,000, and traced slower: see the
defaults below).

**Cost of the build**: per level, O(references x orientations) NumPy passes (the extents
along the fixed orientations are computed once per triangle; the binning works on float32
copies of them, the sides are decided in float64), at most ``max_depth`` levels.

Layout (``nodes`` float32 [M, 8], 32 bytes a row, one row per *interior* node, both child
references in the parent as ``accel.bvh`` and ``accel.kdtree``):

    bytes  0-11  floats 0-2   unit normal n (float32)
    bytes 12-15  float  3     offset c: the plane is n . x = c
    bytes 16-19  float  4     child 0's reference (int32 bit pattern): n . x <= c
    bytes 20-23  float  5     child 1's reference: n . x >= c
    bytes 24-31  floats 6-7   zero (padding to 32 bytes)

References, leaves, ``bounds``, ``references``, ``triangles`` and ``triangle_ids`` as in
``accel.kdtree`` (leaf code ``~((first << leaf_bits) | count)``, -1 an empty leaf, two leaf
children on adjacent slots, rows breadth first; a single-leaf tree is one row with the
plane x = the scene box's upper x, child 1 empty).
"""

from __future__ import annotations

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
from accel.kdtree import (
    EMPTY_CUT_GAP,
    MIN_EMPTY_CUT,
    check_params,
    default_max_depth,
    finish_plane_tree,
    half_area,
    ranks_in_segments,
    split_cost,
)
from accel.structure import Structure

#: Defaults: 16 bins (the orientations multiply the candidates: 16 offsets along up to 9
#: normals). The diagonals and 2 triangle planes at nodes of 64 references or more, the
#: axis planes alone below: measured on the camel (50k camera and 50k incoherent rays,
#: traversal steps + triangle tests per ray), general planes at every node of 16 or more
#: references cost 13.7 and 39.6, the axis planes alone 13.0 and 37.8, general planes at 64
#: or more 12.2 and 35.2 (and 256: 12.8, 37.0); the bounding-box estimate of an oblique
#: cut's areas is rougher on small nodes, and every orientation costs a projection of all
#: the node's triangles. Cost constants as the kd-tree's.
DEFAULT_BINS = 16
DEFAULT_TRIANGLE_PLANES = 2
DEFAULT_GENERAL_MIN_REFERENCES = 64
DEFAULT_TRAVERSAL_COST = 2.0
DEFAULT_INTERSECTION_COST = 1.0
DEFAULT_EMPTY_BONUS = 0.2
DEFAULT_MAX_LEAF_SIZE = 1
ROW_FLOATS = 8
AXES = np.eye(3)
DIAGONALS = np.array([[1, 1, 1], [1, -1, 1], [-1, 1, 1], [-1, -1, 1]]) / np.sqrt(3)
KINDS = ("axis", "diagonal", "triangle")


def _as_float32(a: np.ndarray) -> np.ndarray:
    return np.asarray(a, np.float64).astype(np.float32).astype(np.float64)


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def halfspace_box(lo, hi, n, c):
    """Bounding boxes of ``box ∩ {n . x <= c}``: lo, hi [..., 3] (inverted when empty).

    ``lo``, ``hi``, ``n`` broadcast against ``c[..., None]``. Along axis i the half-space
    allows ``n_i x_i <= c - (the least the other axes can contribute)``.
    """
    low_terms = np.minimum(n * lo, n * hi)
    rest = low_terms.sum(axis=-1, keepdims=True) - low_terms
    with np.errstate(divide="ignore", invalid="ignore"):
        bound = (c[..., None] - rest) / n
    new_lo = np.where(n < 0, np.maximum(lo, bound), lo)
    new_hi = np.where(n > 0, np.minimum(hi, bound), hi)
    empty = low_terms.sum(axis=-1) > c
    new_lo = np.where(empty[..., None], np.inf, new_lo)
    return new_lo, new_hi


def size_along(lo, hi, n):
    """The extent of boxes ``[lo, hi]`` [..., 3] along unit normals ``n``: sum |n_i| size_i."""
    return (np.abs(n) * (np.asarray(hi, np.float64) - lo)).sum(axis=-1)


def _best_planes(pmin, pmax, rext, seg, counts, normals, exact, box_lo, box_hi, bins, ct,
                 ci, bonus):
    """Best plane of every node of a group: (cost, normal index, offset) [K] each.

    ``pmin``, ``pmax`` [R, C] (float32): the extent of each reference's triangle along each
    of its node's candidate normals ``normals`` [K, C, 3] (references sorted by node ``seg``);
    ``exact`` [K, C]: one more candidate offset per orientation (NaN: none).

    The area of a side, the bounding box of ``B ∩ {n . x <= c}``, has along axis i the
    extent ``clip(a_i c + b_i, 0, D_i)`` (D the box's extent; the half-space allows
    ``n_i x_i <= c`` minus the least the other axes contribute), linear in c between
    clamps, so every candidate costs a few multiply-adds per axis.
    """
    k, c_count = normals.shape[:2]
    offsets = np.cumsum(counts) - counts
    lo, hi = box_lo[:, None, :], box_hi[:, None, :]  # [K, 1, 3]
    low = np.minimum(normals * lo, normals * hi)
    high = np.maximum(normals * lo, normals * hi)
    n_lo, n_hi = low.sum(axis=2), high.sum(axis=2)  # the box's extent along n [K, C]
    rest_lo, rest_hi = n_lo[:, :, None] - low, n_hi[:, :, None] - high
    size = np.broadcast_to(hi - lo, normals.shape)
    absn = np.abs(normals)
    inv = np.where(absn > 0, 1.0 / np.where(absn > 0, absn, 1.0), 0.0)
    pos, neg = normals > 0, normals < 0
    b_below = np.where(pos, -rest_lo * inv - lo, np.where(neg, hi - rest_lo * inv, size))
    b_above = np.where(pos, hi + rest_hi * inv, np.where(neg, rest_hi * inv - lo, size))
    area = half_area(box_lo, box_hi)[:, None, None]

    axes_only = c_count == 3 and np.array_equal(normals[0], np.eye(3)) and np.all(
        normals == normals[:1])
    ext = box_hi - box_lo
    perimeter = np.stack([ext[:, 1] + ext[:, 2], ext[:, 0] + ext[:, 2], ext[:, 0] + ext[:, 1]],
                         axis=1)[:, :, None]
    product = np.stack([ext[:, 1] * ext[:, 2], ext[:, 0] * ext[:, 2], ext[:, 0] * ext[:, 1]],
                       axis=1)[:, :, None]

    def side_areas(c):  # c [K, C, O] -> areas of both sides over the node's
        if axes_only:  # the kd-tree's boxes
            return (((c - box_lo[:, :, None]) * perimeter + product) / area,
                    ((box_hi[:, :, None] - c) * perimeter + product) / area)
        left, right = [], []
        for i in range(3):
            a, d = inv[:, :, i, None], size[:, :, i, None]
            left.append(np.clip(a * c + b_below[:, :, i, None], 0.0, d))
            right.append(np.clip(b_above[:, :, i, None] - a * c, 0.0, d))
        return tuple((e[0] * e[1] + e[1] * e[2] + e[2] * e[0]) / area for e in (left, right))

    largest = np.maximum.reduceat(rext, offsets)[:, None]  # the node's largest triangle
    elo = np.maximum(np.minimum.reduceat(pmin, offsets, axis=0), n_lo)  # [K, C] float64
    ehi = np.minimum(np.maximum.reduceat(pmax, offsets, axis=0), n_hi)
    width = (ehi - elo) / bins
    scale = np.where(width > 0, 1.0 / np.where(width > 0, width, 1.0), 0.0)
    total = c_count * bins * k
    base = np.arange(c_count)[None, :] * (bins * k) + seg[:, None]  # [R, C]
    at, to = elo.astype(pmin.dtype)[seg], (scale * k).astype(pmin.dtype)[seg]

    def bin_counts(p):  # references per (normal, bin, node) of p's bin, as one bincount
        key = p - at
        key *= to
        key = np.clip(key, 0, (bins - 1) * k, out=key).astype(np.int64)
        key -= key % k  # whole bins of k keys
        key += base
        return np.bincount(key.ravel(), minlength=total)

    starts, ends = bin_counts(pmin), bin_counts(pmax)
    starts = starts.reshape(c_count, bins, k).transpose(2, 0, 1)  # [K, C, bins]
    ends = ends.reshape(c_count, bins, k).transpose(2, 0, 1)
    n_left = np.cumsum(starts[:, :, :-1], axis=2)  # boundaries 1 .. bins-1
    n_right = np.cumsum(ends[:, :, ::-1], axis=2)[:, :, ::-1][:, :, 1:]
    cand_c = elo[:, :, None] + np.arange(1, bins) * width[:, :, None]  # [K, C, bins-1]
    p_left, p_right = side_areas(cand_c)
    with np.errstate(invalid="ignore"):
        cost = ct + ci * (p_left * n_left + p_right * n_right)
    cost[~((width > 0)[:, :, None] & (cand_c > n_lo[:, :, None])
           & (cand_c < n_hi[:, :, None]) & np.isfinite(cost))] = np.inf
    # Empty-space cuts, and the triangles' own planes, as extra candidates [K, C, 3].
    gap_lo = EMPTY_CUT_GAP * (largest + (elo - n_lo))
    gap_hi = EMPTY_CUT_GAP * (largest + (n_hi - ehi))
    extra_c = _as_float32(np.stack([elo - gap_lo, ehi + gap_hi, np.nan_to_num(exact)],
                                   axis=2))
    least = MIN_EMPTY_CUT * (box_hi - box_lo).max(axis=1)[:, None]
    extra_ok = np.stack([elo - n_lo > np.maximum(2 * gap_lo, least),
                         n_hi - ehi > np.maximum(2 * gap_hi, least), ~np.isnan(exact)], axis=2)
    extra_ok &= (extra_c > n_lo[:, :, None]) & (extra_c < n_hi[:, :, None])
    full = np.broadcast_to(counts[:, None, None], extra_c.shape)
    nl_extra = np.where(np.arange(3) == 0, 0, full).astype(np.int64)
    nr_extra = np.where(np.arange(3) == 1, 0, full).astype(np.int64)
    cols = np.flatnonzero(np.any(extra_ok[:, :, 2], axis=0))
    if cols.size:  # exact counts at the triangles' own planes
        plane = extra_c[:, cols, 2]
        delta = reference_margin((n_hi - n_lo)[:, cols][seg], rext[:, None])
        below = (pmin[:, cols] <= plane[seg] + delta).astype(np.int64)
        above = (pmax[:, cols] >= plane[seg] - delta).astype(np.int64)
        nl_extra[:, cols, 2] = np.add.reduceat(below, offsets, axis=0)
        nr_extra[:, cols, 2] = np.add.reduceat(above, offsets, axis=0)
    e_left, e_right = side_areas(extra_c)
    with np.errstate(invalid="ignore"):
        extra_cost = split_cost(ct, ci, bonus, e_left, e_right, 1.0, nl_extra, nr_extra)
    extra_cost[~(extra_ok & np.isfinite(extra_cost))] = np.inf
    every_cost = np.concatenate([cost, extra_cost], axis=2).reshape(k, -1)
    every_c = np.concatenate([cand_c, extra_c], axis=2).reshape(k, -1)
    pick = np.argmin(every_cost, axis=1)
    rows = np.arange(k)
    per_normal = every_cost.shape[1] // c_count
    return every_cost[rows, pick], pick // per_normal, _as_float32(every_c[rows, pick])


def _project(tri, n):
    """Extent (min, max) of triangles [R, 3, 3] along normals [R, C, 3]: [R, C] each."""
    p = [tri[:, v, None, 0] * n[:, :, 0] + tri[:, v, None, 1] * n[:, :, 1]
         + tri[:, v, None, 2] * n[:, :, 2] for v in range(3)]
    return np.minimum(np.minimum(p[0], p[1]), p[2]), np.maximum(np.maximum(p[0], p[1]), p[2])


def build(
    vertices: np.ndarray,
    faces: np.ndarray,
    *,
    bins: int = DEFAULT_BINS,
    triangle_planes: int = DEFAULT_TRIANGLE_PLANES,
    general_min_references: int = DEFAULT_GENERAL_MIN_REFERENCES,
    max_leaf_size: int = DEFAULT_MAX_LEAF_SIZE,
    max_depth: int | None = None,
    traversal_cost: float = DEFAULT_TRAVERSAL_COST,
    intersection_cost: float = DEFAULT_INTERSECTION_COST,
    empty_bonus: float = DEFAULT_EMPTY_BONUS,
) -> Structure:
    """Build a BSP tree with general planes over the non-degenerate faces.

    Args:
        bins: offsets per orientation are the boundaries of ``bins`` bins.
        triangle_planes: planes of the node's triangles among the candidates (0: none).
        general_min_references: nodes with fewer references try the axis planes only.
        max_leaf_size, max_depth, traversal_cost, intersection_cost, empty_bonus: as
            ``accel.kdtree`` (max_depth None: round(8 + 1.3 log2 N)).
    """
    check_params(bins, max_leaf_size, max_depth, traversal_cost, intersection_cost,
                 empty_bonus, name="bsp")
    if not (isinstance(triangle_planes, int | np.integer) and 0 <= triangle_planes <= 16):
        raise ValueError(
            f"bsp: triangle_planes must be an integer in [0, 16], got {triangle_planes!r}")
    if not (isinstance(general_min_references, int | np.integer)
            and general_min_references >= 1):
        raise ValueError("bsp: general_min_references must be a positive integer, got "
                         f"{general_min_references!r}")
    start_time = time.perf_counter()
    ct, ci, bonus = float(traversal_cost), float(intersection_cost), float(empty_bonus)
    keep = ~degenerate_mask(vertices, faces)
    ids = np.flatnonzero(keep).astype(np.int32)
    tris = triangle_vertices(vertices, np.asarray(faces)[ids]).reshape(-1, 3, 3)
    t_count = ids.shape[0]
    depth_limit = default_max_depth(t_count) if max_depth is None else int(max_depth)
    frame, tri64, bounds = local_frame(tris)
    extent = triangle_extents(tri64)
    if t_count:
        tri_normals = _as_float32(_unit(np.cross(tri64[:, 1] - tri64[:, 0],
                                                 tri64[:, 2] - tri64[:, 0])))
    else:
        tri_normals = np.zeros((0, 3))
    # The fixed orientations (axes, diagonals) and every triangle's extent along them.
    fixed = _as_float32(np.concatenate([AXES, DIAGONALS]))
    fixed_min, fixed_max = _project(tri64, np.broadcast_to(fixed, (t_count, 7, 3)))
    # The split search bins float32 copies (half the memory traffic); the sides are
    # decided in float64.
    fixed_min32, fixed_max32 = fixed_min.astype(np.float32), fixed_max.astype(np.float32)

    node_lo, node_hi, node_depth = [], [], []
    split_ids, split_normal, split_offset, split_child = [], [], [], []
    leaf_ids, leaf_first, leaf_count, leaf_refs = [], [], [], []
    kinds = np.zeros(len(KINDS), np.int64)
    n_refs_out = 0
    over_depth = 0
    act_ids = np.zeros(1 if t_count else 0, np.int64)
    act_lo = bounds[None, 0].astype(np.float64)[: len(act_ids)]
    act_hi = bounds[None, 1].astype(np.float64)[: len(act_ids)]
    node_lo.append(act_lo)
    node_hi.append(act_hi)
    node_depth.append(np.zeros(len(act_ids), np.int64))
    next_id = len(act_ids)
    rseg = np.zeros(t_count, np.int64)
    rtri = np.arange(t_count, dtype=np.int64)
    depth = 0
    while act_ids.shape[0]:
        k = act_ids.shape[0]
        counts = np.bincount(rseg, minlength=k)
        offsets = np.cumsum(counts) - counts
        want = counts > max_leaf_size
        splitting = want & (depth < depth_limit)
        over_depth += int((want & ~splitting).sum())
        normal = np.zeros((k, 3))
        offset = np.zeros(k)
        kind = np.zeros(k, np.int64)
        fixed_index = np.zeros(k, np.int64)  # 0-6: a fixed orientation, -1: a triangle's
        cost = np.full(k, np.inf)
        general = counts >= general_min_references
        for use_general in (False, True):
            group = splitting & (general if use_general else ~general)
            nodes = np.flatnonzero(group)
            if nodes.size == 0:
                continue
            remap = np.full(k, -1, np.int64)
            remap[nodes] = np.arange(nodes.size)
            mine = np.flatnonzero(group[rseg])
            g_seg = remap[rseg[mine]]
            g_tri = rtri[mine]
            if use_general:
                # Sampled triangles: evenly spaced in each node's references.
                g_counts = counts[nodes]
                sample = (offsets[nodes][:, None]
                          + (np.arange(1, triangle_planes + 1)[None, :] * g_counts[:, None])
                          // (triangle_planes + 1))
                sampled = rtri[sample]
                cand = np.concatenate([np.broadcast_to(fixed, (nodes.size, 7, 3)),
                                       tri_normals[sampled]], axis=1)
                exact = np.full(cand.shape[:2], np.nan)
                exact[:, 7:] = (tri_normals[sampled] * tri64[sampled, 0]).sum(axis=2)
                t_min, t_max = _project(tri64[g_tri], tri_normals[sampled][g_seg])
                pmin = np.concatenate([fixed_min32[g_tri], t_min], axis=1, dtype=np.float32)
                pmax = np.concatenate([fixed_max32[g_tri], t_max], axis=1, dtype=np.float32)
                kind_of = np.array([0, 0, 0, 1, 1, 1, 1] + [2] * triangle_planes)
            else:
                cand = np.broadcast_to(fixed[:3], (nodes.size, 3, 3))
                exact = np.full((nodes.size, 3), np.nan)
                pmin, pmax = fixed_min32[g_tri, :3], fixed_max32[g_tri, :3]
                kind_of = np.zeros(3, np.int64)
            g_cost, g_pick, g_offset = _best_planes(
                pmin, pmax, extent[g_tri], g_seg, counts[nodes], cand, exact, act_lo[nodes],
                act_hi[nodes],
                bins, ct, ci, bonus)
            cost[nodes], offset[nodes] = g_cost, g_offset
            normal[nodes] = cand[np.arange(nodes.size), g_pick]
            kind[nodes] = kind_of[g_pick]
            fixed_index[nodes] = np.where(g_pick < 7, g_pick, -1)
        splitting &= cost < ci * counts
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
        kinds += np.bincount(kind[nodes], minlength=len(KINDS))
        rank = np.full(k, -1, np.int64)
        rank[nodes] = np.arange(m)
        n, c, which = normal[nodes], offset[nodes], fixed_index[nodes]
        lo, hi = act_lo[nodes], act_hi[nodes]
        lo0, hi0 = halfspace_box(lo, hi, n, c)
        lo1, hi1 = halfspace_box(lo, hi, -n, -c)
        size_n = size_along(lo, hi, n)
        child_ids = next_id + np.arange(2 * m)
        next_id += 2 * m
        split_ids.append(act_ids[nodes])
        split_normal.append(n)
        split_offset.append(c)
        split_child.append(child_ids.reshape(m, 2))
        child_lo = np.stack([lo0, lo1], axis=1).reshape(-1, 3)
        child_hi = np.stack([hi0, hi1], axis=1).reshape(-1, 3)
        child_lo = np.minimum(child_lo, child_hi)  # an empty side: a point, never used
        node_lo.append(child_lo)
        node_hi.append(child_hi)
        node_depth.append(np.full(2 * m, depth + 1, np.int64))

        # Each side whose widened half-space holds a vertex of the triangle.
        sel = np.flatnonzero(splitting[rseg])
        r = rank[rseg[sel]]
        # (Along the fixed orientations the extents are precomputed, the others projected.)
        p_min, p_max = fixed_min[rtri[sel], which[r]], fixed_max[rtri[sel], which[r]]
        own = np.flatnonzero(which[r] < 0)
        if own.size:
            t_min, t_max = _project(tri64[rtri[sel[own]]], n[r[own]][:, None, :])
            p_min[own], p_max[own] = t_min[:, 0], t_max[:, 0]
        delta = reference_margin(size_n[r], extent[rtri[sel]])
        member = [p_min <= c[r] + delta, p_max >= c[r] - delta]
        seg_first = np.zeros(m, np.int64)
        seg_first[1:] = np.cumsum(np.bincount(r, minlength=m))[:-1]
        n_child = np.stack([np.bincount(r[member[0]], minlength=m),
                            np.bincount(r[member[1]], minlength=m)], axis=1).reshape(-1)
        child_first = np.cumsum(n_child) - n_child
        total = int(n_child.sum())
        new_tri = np.empty(total, np.int64)
        new_seg = np.empty(total, np.int64)
        live = np.flatnonzero(n_child > 0)
        remap = np.full(2 * m, -1, np.int64)
        remap[live] = np.arange(live.size)
        for side in (0, 1):
            idx = np.flatnonzero(member[side])
            pos = (child_first[2 * r[idx] + side]
                   + ranks_in_segments(member[side], seg_first, r)[idx])
            new_tri[pos] = rtri[sel[idx]]
            new_seg[pos] = remap[2 * r[idx] + side]
        rseg, rtri = new_seg, new_tri
        act_ids = child_ids[live]
        act_lo = child_lo[live]
        act_hi = child_hi[live]
        depth += 1

    return _flatten(
        tris, ids, frame, bounds, next_id, node_lo, node_hi, node_depth,
        (split_ids, split_normal, split_offset, split_child),
        (leaf_ids, leaf_first, leaf_count, leaf_refs),
        params={"bins": bins, "triangle_planes": triangle_planes,
                "general_min_references": general_min_references,
                "max_leaf_size": max_leaf_size, "max_depth": depth_limit,
                "traversal_cost": ct, "intersection_cost": ci, "empty_bonus": bonus},
        extra={"degenerate_skipped": int((~keep).sum()), "leaves_over_max_depth": over_depth,
               **{f"planes_{name}": int(count) for name, count in zip(KINDS, kinds,
                                                                      strict=True)}},
        start_time=start_time)


def _cat(parts, dtype, shape=(0,)):
    return np.concatenate(parts).astype(dtype) if parts else np.zeros(shape, dtype)


def _flatten(tris, ids, frame, bounds, total, node_lo, node_hi, node_depth, splits, leaves, *,
             params, extra, start_time):
    s_ids = _cat(splits[0], np.int64)
    s_normal = _cat(splits[1], np.float64, (0, 3))
    s_offset = _cat(splits[2], np.float64)
    s_child = _cat(splits[3], np.int64, (0, 2))
    l_ids = _cat(leaves[0], np.int64)
    l_first = _cat(leaves[1], np.int64)
    l_count = _cat(leaves[2], np.int64)
    references = _cat(leaves[3], np.int32)
    max_count = int(l_count.max()) if l_count.size else 0
    try:
        leaf_bits = leaf_bits_for(max_count, references.shape[0])
    except ValueError as error:
        raise ValueError(f"bsp: {error}") from None
    ref = np.full(max(total, 1), -1, np.int64)
    order = np.argsort(s_ids)
    s_ids, s_normal, s_offset, s_child = (s_ids[order], s_normal[order], s_offset[order],
                                          s_child[order])
    ref[s_ids] = np.arange(s_ids.size)
    ref[l_ids] = leaf_references(l_first, l_count, leaf_bits)
    ref[l_ids[l_count == 0]] = -1
    if s_ids.size:
        nodes = np.zeros((s_ids.size, ROW_FLOATS), np.float32)
        nodes[:, 0:3] = s_normal
        nodes[:, 3] = s_offset
        nodes.view(np.int32)[:, 4:6] = ref[s_child]
    else:  # a single leaf (or nothing): the plane x = upper x of the box, child 1 empty
        nodes = np.zeros((1, ROW_FLOATS), np.float32)
        nodes[0, 0] = 1.0
        nodes[0, 3] = bounds[1, 0]
        nodes.view(np.int32)[0, 4:6] = [ref[0] if total else -1, -1]
    return finish_plane_tree("bsp", nodes, frame, bounds, references, tris, ids, leaf_bits,
                             node_lo, node_hi, node_depth, s_ids, l_ids, l_count, total,
                             params, extra, start_time)
