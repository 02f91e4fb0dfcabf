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

**The build** works level by level, every node of a level at once, with the kd-tree's
bookkeeping of nodes, leaves and rows, its cost model and its parameters' checks
(``accel.plane_tree``). A node whose bounding box has no area (a sliver cut off a corner,
whose box rounds to a segment, still holding references through their margins) has no SAH
(0 / 0) and stays a leaf. **Its cost**: per level, O(references x orientations) NumPy
passes (the extents along the fixed orientations are computed once per triangle; the
binning works on float32 copies of them, the sides are decided in float64), at most
``max_depth`` levels.

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
    search_level,
    split_cost,
    tree_triangles,
)
from accel.registry import StructureKind, world_planes
from accel.structure import Structure

#: Defaults: 16 bins (the orientations multiply the candidates: 16 offsets along up to 9
#: normals). The diagonals and 2 triangle planes at nodes of 64 references or more, the
#: axis planes alone below: measured on the camel (50k camera and 50k incoherent rays,
#: traversal steps + triangle tests per ray), general planes at every node of 16 or more
#: references cost 13.7 and 39.6, the axis planes alone 13.0 and 37.8, general planes at 64
#: or more 12.2 and 35.2 (and 256: 12.8, 37.0); the bounding-box estimate of an oblique
#: cut's areas is rougher on small nodes, and every orientation costs a projection of all
#: the node's triangles. The cost constants, the empty-space bonus and the leaf size are the
#: kd-tree's (``accel.plane_tree``).
DEFAULT_BINS = 16
DEFAULT_TRIANGLE_PLANES = 2
DEFAULT_GENERAL_MIN_REFERENCES = 64
ROW_FLOATS = 8
AXES = np.eye(3)
DIAGONALS = np.array([[1, 1, 1], [1, -1, 1], [-1, 1, 1], [-1, -1, 1]]) / np.sqrt(3)
KINDS = ("axis", "diagonal", "triangle")

__all__ = ["AXES", "DEFAULT_BINS", "DEFAULT_EMPTY_BONUS", "DEFAULT_GENERAL_MIN_REFERENCES",
           "DEFAULT_INTERSECTION_COST", "DEFAULT_MAX_LEAF_SIZE", "DEFAULT_TRAVERSAL_COST",
           "DEFAULT_TRIANGLE_PLANES", "DIAGONALS", "KIND", "KINDS", "ROW_FLOATS", "build",
           "halfspace_box", "size_along", "stored_planes"]


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
    # (Only axes with n_i != 0 use the bound; the others divide by 1, unused.)
    bound = (c[..., None] - rest) / np.where(n != 0, n, 1.0)
    new_lo = np.where(n < 0, np.maximum(lo, bound), lo)
    new_hi = np.where(n > 0, np.minimum(hi, bound), hi)
    empty = low_terms.sum(axis=-1) > c
    new_lo = np.where(empty[..., None], np.inf, new_lo)
    return new_lo, new_hi


def size_along(lo, hi, n):
    """The extent of boxes ``[lo, hi]`` [..., 3] along unit normals ``n``: sum |n_i| size_i."""
    return (np.abs(n) * (np.asarray(hi, np.float64) - lo)).sum(axis=-1)


def _best_planes(pmin, pmax, rext, counts, normals, exact, box_lo, box_hi, bins, ct,
                 ci, bonus):
    """Best plane of every node of a group: (cost, normal index, offset) [K] each.

    ``pmin``, ``pmax`` [R, C] (float32): the extent of each reference's triangle along each
    of its node's candidate normals ``normals`` [K, C, 3] (references sorted by node,
    ``counts`` [K] per node, none 0);
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
    # A box without area (a segment or a point: a sliver whose bounding box rounded to
    # nothing along two axes, still holding references through their margins) has no SAH,
    # 0 / 0: such a node stays a leaf (all its candidates cost inf), and divides by 1.
    box_area = half_area(box_lo, box_hi)
    flat = box_area == 0
    area = np.where(flat, 1.0, box_area)[:, None, None]

    axes_only = c_count == 3 and np.array_equal(normals[0], np.eye(3)) and np.all(
        normals == normals[:1])
    ext = box_hi - box_lo
    perimeter = np.stack([ext[:, 1] + ext[:, 2], ext[:, 0] + ext[:, 2], ext[:, 0] + ext[:, 1]],
                         axis=1)[:, :, None]
    product = np.stack([ext[:, 1] * ext[:, 2], ext[:, 0] * ext[:, 2], ext[:, 0] * ext[:, 1]],
                       axis=1)[:, :, None]

    def side_areas(c):  # c [K, C, O] -> areas of both sides over the node's
        if axes_only:  # the kd-tree's boxes (in place: these are the largest arrays)
            left = c - box_lo[:, :, None]
            right = box_hi[:, :, None] - c
            for e in (left, right):
                e *= perimeter
                e += product
                e /= area
            return left, right
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
    # Keys (node, normal, bin): a node's bins are contiguous, so the prefix sums run along
    # the last axis (far faster than along a middle one, or a transposed view).
    base = np.repeat((np.arange(k)[:, None] * c_count + np.arange(c_count)) * bins, counts,
                     axis=0)  # [R, C]
    # (References are sorted by node: repeat is a gather without an index.)
    at = np.repeat(elo.astype(pmin.dtype), counts, axis=0)
    to = np.repeat(scale.astype(pmin.dtype), counts, axis=0)

    def bin_counts(p):  # references per (node, normal, bin) of p's bin, as one bincount
        f = p - at
        f *= to
        np.clip(f, 0, bins - 1, out=f)  # then truncation is floor
        key = f.astype(np.intp)
        key += base
        return np.bincount(key.ravel(), minlength=total).reshape(k, c_count, bins)

    # Boundary j (1 .. bins-1): N_L starts in bins < j, N_R = N - ends in bins < j.
    n_left = np.cumsum(bin_counts(pmin)[:, :, :-1], axis=2)
    n_right = counts[:, None, None] - np.cumsum(bin_counts(pmax)[:, :, :-1], axis=2)
    cand_c = elo[:, :, None] + np.arange(1, bins) * width[:, :, None]  # [K, C, bins-1]
    cost, p_right = side_areas(cand_c)
    cost *= n_left  # ct + ci * (A_L N_L + A_R N_R) / A, in place
    p_right *= n_right
    cost += p_right
    cost *= ci
    cost += ct
    cost[(cand_c <= n_lo[:, :, None]) | (cand_c >= n_hi[:, :, None])] = np.inf
    cost[~(width > 0) | flat[:, None]] = np.inf
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
        # (References are sorted by node: repeat is a gather without an index.)
        plane = np.repeat(extra_c[:, cols, 2], counts, axis=0)
        delta = reference_margin(np.repeat((n_hi - n_lo)[:, cols], counts, axis=0),
                                 rext[:, None])
        below = (pmin[:, cols] <= plane + delta).astype(np.int64)
        above = (pmax[:, cols] >= plane - delta).astype(np.int64)
        nl_extra[:, cols, 2] = np.add.reduceat(below, offsets, axis=0)
        nr_extra[:, cols, 2] = np.add.reduceat(above, offsets, axis=0)
    e_left, e_right = side_areas(extra_c)
    extra_cost = split_cost(ct, ci, bonus, e_left, e_right, 1.0, nl_extra, nr_extra)
    extra_cost[~(extra_ok & ~flat[:, None, None])] = np.inf
    every_cost = np.concatenate([cost, extra_cost], axis=2).reshape(k, -1)
    every_c = np.concatenate([cand_c, extra_c], axis=2).reshape(k, -1)
    pick = np.argmin(every_cost, axis=1)
    rows = np.arange(k)
    per_normal = every_cost.shape[1] // c_count
    return every_cost[rows, pick], pick // per_normal, _as_float32(every_c[rows, pick])


def _project(tri, n):
    """Extent (min, max) of triangles along normals, [R, C] each: ``tri`` [3 vertices,
    3 axes, R] and ``n`` [3 axes, C, R] or [3, C, 1] (the same normals for all), both
    coordinate-major, so that every product runs over contiguous rows."""
    p = [tri[v, 0] * n[0] + tri[v, 1] * n[1] + tri[v, 2] * n[2] for v in range(3)]
    lo = np.minimum(np.minimum(p[0], p[1]), p[2]).T
    hi = np.maximum(np.maximum(p[0], p[1]), p[2]).T
    return lo, hi


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
    check_params("bsp", bins, max_leaf_size, max_depth, traversal_cost, intersection_cost,
                 empty_bonus)
    if not (isinstance(triangle_planes, int | np.integer) and 0 <= triangle_planes <= 16):
        raise ValueError(
            f"bsp: triangle_planes must be an integer in [0, 16], got {triangle_planes!r}")
    if not (isinstance(general_min_references, int | np.integer)
            and general_min_references >= 1):
        raise ValueError("bsp: general_min_references must be a positive integer, got "
                         f"{general_min_references!r}")
    start_time = time.perf_counter()
    ct, ci, bonus = float(traversal_cost), float(intersection_cost), float(empty_bonus)
    triangles = tree_triangles(vertices, faces)
    tri64, extent = triangles.local, triangles.extent
    t_count = triangles.ids.shape[0]
    depth_limit = default_max_depth(t_count) if max_depth is None else int(max_depth)
    if t_count:
        tri_normals = _as_float32(_unit(np.cross(tri64[:, 1] - tri64[:, 0],
                                                 tri64[:, 2] - tri64[:, 0])))
    else:
        tri_normals = np.zeros((0, 3))
    # The fixed orientations (axes, diagonals) and every triangle's extent along them.
    fixed = _as_float32(np.concatenate([AXES, DIAGONALS]))
    tri_t = np.ascontiguousarray(tri64.transpose(1, 2, 0))  # [vertex, axis, triangle]
    fixed_min, fixed_max = map(np.ascontiguousarray, _project(tri_t, fixed.T[:, :, None]))
    # The split search bins float32 copies (half the memory traffic); the sides are
    # decided in float64.
    fixed_min32, fixed_max32 = fixed_min.astype(np.float32), fixed_max.astype(np.float32)
    # The axes' columns apart, contiguous: most nodes search them alone, and a row gather
    # (np.take) of a contiguous [T, 3] is 2-3x faster than a fancy index with a slice.
    axis_min32, axis_max32 = (np.ascontiguousarray(a[:, :3]) for a in (fixed_min32,
                                                                        fixed_max32))

    # The nodes (their regions' bounding boxes), their splits (normal, offset) and leaves.
    levels = LevelBuild(triangles.bounds, t_count, max_leaf_size, depth_limit,
                        planes={"normal": (np.float64, (3,)), "offset": (np.float64, ())})
    kinds = np.zeros(len(KINDS), np.int64)
    # The references of the active level, sorted by node: node and triangle row.
    rseg = np.zeros(t_count, np.int64)
    rtri = np.arange(t_count, dtype=np.int64)
    while levels.active:
        k = levels.size
        counts = np.bincount(rseg, minlength=k)
        offsets = np.cumsum(counts) - counts
        splitting = levels.wanting_split(counts)
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
            mine = np.flatnonzero(group[rseg])
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
                kind_of = np.array([0, 0, 0, 1, 1, 1, 1] + [2] * triangle_planes)

                def extents(first, end, tris, g_counts=g_counts, sampled=sampled):
                    """The extents of a run's triangles ``tris`` (of nodes ``first`` to
                    ``end``) along the 7 fixed normals and their nodes' sampled triangles'
                    normals, [len(tris), C] float32 each (in the search's thread: the
                    projection is the level's largest pass)."""
                    normals = np.repeat(tri_normals[sampled[first:end]].transpose(2, 1, 0),
                                        g_counts[first:end], axis=2)
                    t_min, t_max = _project(tri_t[:, :, tris], normals)
                    return (np.concatenate([np.take(fixed_min32, tris, axis=0), t_min],
                                           axis=1, dtype=np.float32),
                            np.concatenate([np.take(fixed_max32, tris, axis=0), t_max],
                                           axis=1, dtype=np.float32))
            else:
                cand = np.broadcast_to(fixed[:3], (nodes.size, 3, 3))
                exact = np.full((nodes.size, 3), np.nan)
                kind_of = np.zeros(3, np.int64)

                def extents(first, end, tris):
                    """The extents of a run's triangles ``tris`` along the axes, [len(tris),
                    3] each."""
                    return np.take(axis_min32, tris, axis=0), np.take(axis_max32, tris, axis=0)
            g_counts = counts[nodes]
            g_lo, g_hi = levels.lo[nodes], levels.hi[nodes]
            g_cost, g_offset = np.empty(nodes.size), np.empty(nodes.size)
            g_pick = np.empty(nodes.size, np.int64)

            def search(run, extents=extents, g_tri=g_tri, g_counts=g_counts, cand=cand,
                       exact=exact, g_lo=g_lo, g_hi=g_hi):
                first, end, r0, r1 = run
                tris = g_tri[r0:r1]
                pmin, pmax = extents(first, end, tris)
                return _best_planes(pmin, pmax, extent[tris],
                                    g_counts[first:end],
                                    cand[first:end], exact[first:end], g_lo[first:end],
                                    g_hi[first:end], bins, ct, ci, bonus)

            for first, end, best in search_level(g_counts, search):
                g_cost[first:end], g_pick[first:end], g_offset[first:end] = best
            cost[nodes], offset[nodes] = g_cost, g_offset
            normal[nodes] = cand[np.arange(nodes.size), g_pick]
            kind[nodes] = kind_of[g_pick]
            fixed_index[nodes] = np.where(g_pick < 7, g_pick, -1)
        splitting &= cost < ci * counts
        levels.close_leaves(splitting, counts, rseg, rtri)
        nodes = np.flatnonzero(splitting)
        m = nodes.size
        if m == 0:
            break
        kinds += np.bincount(kind[nodes], minlength=len(KINDS))
        rank = np.full(k, -1, np.int64)
        rank[nodes] = np.arange(m)
        n, c, which = normal[nodes], offset[nodes], fixed_index[nodes]
        lo, hi = levels.lo[nodes], levels.hi[nodes]
        lo0, hi0 = halfspace_box(lo, hi, n, c)
        lo1, hi1 = halfspace_box(lo, hi, -n, -c)
        size_n = size_along(lo, hi, n)
        # (An empty side's box becomes a point: such a child gets no reference.)
        levels.split(nodes, (np.minimum(lo0, hi0), hi0), (np.minimum(lo1, hi1), hi1),
                     normal=n, offset=c)

        # Each side whose widened half-space holds a vertex of the triangle.
        sel = np.flatnonzero(splitting[rseg])
        r = rank[rseg[sel]]
        # (Along the fixed orientations the extents are precomputed, the others projected.)
        # (By flat index into the [T, 7] extents: one index array, one gather each.)
        flat = rtri[sel] * fixed.shape[0] + np.maximum(which[r], 0)
        p_min, p_max = np.take(fixed_min, flat), np.take(fixed_max, flat)
        own = np.flatnonzero(which[r] < 0)
        if own.size:
            t_min, t_max = _project(tri_t[:, :, rtri[sel[own]]], n[r[own]].T[:, None, :])
            p_min[own], p_max[own] = t_min[:, 0], t_max[:, 0]
        delta = reference_margin(size_n[r], extent[rtri[sel]])
        member = [p_min <= c[r] + delta, p_max >= c[r] - delta]
        # The next level: the children that hold references, references sorted by child.
        order = levels.descend(sel, r, member)
        rseg, rtri = order.segment, order.gather(rtri)

    tree = levels.rows("bsp")
    return levels.structure(
        "bsp", _node_rows(tree, triangles.bounds), tree, triangles,
        params={"bins": bins, "triangle_planes": triangle_planes,
                "general_min_references": general_min_references,
                "max_leaf_size": max_leaf_size, "max_depth": depth_limit,
                "traversal_cost": ct, "intersection_cost": ci, "empty_bonus": bonus},
        extra={"degenerate_skipped": triangles.degenerate,
               "leaves_over_max_depth": levels.over_depth,
               **{f"planes_{name}": int(count) for name, count in zip(KINDS, kinds,
                                                                      strict=True)}},
        start_time=start_time)


def _node_rows(tree: TreeRows, bounds: np.ndarray) -> np.ndarray:
    """The ``nodes`` array (the layout in the module docstring)."""
    if tree.interior_ids.size:
        nodes = np.zeros((tree.interior_ids.size, ROW_FLOATS), np.float32)
        nodes[:, 0:3] = tree.planes["normal"]
        nodes[:, 3] = tree.planes["offset"]
        nodes.view(np.int32)[:, 4:6] = tree.children
    else:  # a single leaf (or nothing): the plane x = upper x of the box, child 1 empty
        nodes = np.zeros((1, ROW_FLOATS), np.float32)
        nodes[0, 0] = 1.0
        nodes[0, 3] = bounds[1, 0]
        nodes.view(np.int32)[0, 4:6] = [tree.root, -1]
    return nodes


def stored_planes(structure: Structure) -> list[np.ndarray]:
    """Per axis, the tree's axis-aligned planes (normal ±e_a; general planes have no
    per-axis coordinate and are left out), in world coordinates."""
    nodes = np.asarray(structure["nodes"])
    n, c = nodes[:, :3], nodes[:, 3]
    found = []
    for a in range(3):
        axis_aligned = (np.abs(n[:, a]) == 1) & (np.count_nonzero(n, axis=1) == 1)
        found.append(c[axis_aligned] * n[axis_aligned, a])
    return world_planes(structure, found)


KIND = StructureKind(
    name="bsp", build=build,
    arrays=frozenset({"nodes", "bounds", "references", "triangles", "triangle_ids", "frame"}),
    layout=frozenset({"leaf_bits"}), traversal="jrt.bsp:traversal", planes=stored_planes,
    rows=frozenset({"nodes", "references", "triangles", "triangle_ids"}),
    summary="BSP tree: split planes along the axes and the triangles' own planes")
