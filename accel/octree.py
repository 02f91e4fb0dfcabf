"""Octree: cubic cells split in eight at their centre, built level by level in NumPy.

Algorithm (Glassner, "Space subdivision for fast ray tracing", IEEE CG&A 4(10), 1984;
the subdivision rule of Samet's region octree): the root is the cube around the mesh's
bounding box; a cell referencing more than ``max_leaf_size`` triangles is split in eight
at its centre, until ``max_depth``. A triangle goes to every child it truly overlaps, by
the exact triangle-box test (separating axes, Akenine-Möller, "Fast 3D triangle-box
overlap testing", JGT 2001: ``accel.geometry.triangles_overlap_boxes``) against the child
cube widened by the pair's margin, ``CELL_MARGIN`` (2^-16) of the cell's size and of the
triangle's own extent (``accel.geometry.reference_margin``), so a hit whose computed point
strays a few ulps out of the triangle still finds the triangle in the cell the traversal
visits (the traversal widens its planes at run time for the rest of the rounding).
Triangles are never clipped or
split: one triangle is referenced by every leaf it overlaps.

The build is vectorised over all (cell, triangle) pairs of a tree level, with a loop
over the levels only: every pair of a cell to split is tested against the cell's eight
widened children at once. A child's widened box is, on each axis, one of two intervals
(the lower or the upper half, widened), so every test runs per axis and half on the pairs
and gives a byte of eight child bits, combined over the axes by bitwise AND (no [pairs, 8]
arrays): a child the triangle's box misses is rejected; one that contains the triangle's
box, one of its corners or one of its edges' midpoints certainly overlaps it; the
separating-axis test decides the rest (about a quarter of the candidates on the camel), in
``accel.geometry.overlap_rows`` (on component rows: an order of magnitude faster than on
[pairs, 3, 3] arrays). One sort of the keys (child, triangle)
groups the surviving pairs for the next level. A level goes through in blocks of about
2^15 pairs, cut between parents, whose temporaries stay in the cache. A level costs
O(P log P) for its P pairs, and P grows about as fast as N per level for a surface mesh,
so the build is O(N log N) overall (the camel: 0.3 s, 1.1M triangles: 4 s; 1.3 s and 20 s
with [pairs, 8, ...] arrays and ``triangles_overlap_boxes``).

Local frame. The tree is built and stored in a local frame whose origin ``frame`` is a
point of the triangles' bounding box (``accel.geometry.frame_origin``: the one nearest
the coordinate origin, so a scene around the origin keeps world coordinates): every
decision (the root cube, the centres, the triangle-box tests, the widening) is taken on
the exact float64 differences ``triangle - frame`` (``accel.geometry.local_corners``),
and the engine moves each ray's origin into the same frame (``o - frame``, rounded to
float32) before the cell tests, whose run-time margins (``jrt.engine.BOX_MARGIN`` of the
planes' and the origin's magnitudes) then follow the scene's extent and the ray's distance
from it, not the scene's position; the rounding of ``o - frame`` to float32, 2^-24 of
``|o - frame|``, is far inside them. The builder's own margins (above) depend only on the
cells' and the triangles' sizes. With margins of 2^-16 of the coordinates' magnitude in
world coordinates, the camel (1.4 units across) moved by (1000, -700, 1300) had every
cell widened by about 0.02, twice the length of its edges, and its build failed with 29M
references; now it builds as at the origin, wherever it sits, and two camels far apart
build as two camels. The triangle kernels still read the stored world-coordinate
triangles, so the hits stay brute force's, bit for bit.

Cell geometry is exact and shared with the traversal, in the local frame: the root cube
is ``centre +- half`` evaluated in float32 (the traversal evaluates the same expression),
with ``half`` grown until those float32 faces contain every local corner (compared in
float64: the local corners need not be float32 values), and is split at that centre; a
child's faces are its parent's faces and the parent's float32 centre, and its own centre
is the float32 midpoint of those faces. So the planes a ray crosses in the traversal are
exactly the planes the builder split at; the stored half size is nominal (root half /
2^depth).

Layout. ``frame`` float32 [3], 12 bytes: the local frame's origin. ``nodes`` holds local
coordinates (a world point ``p`` is at ``p - frame`` among them); the engine moves every
ray's origin into the frame.
``nodes`` float32 [M, 12], 48 bytes per *interior* cell (row 0 is the root,
which is always split, so a tree of up to ``max_leaf_size`` triangles has depth 1; rows
are in breadth-first order):

    bytes  0-11  floats 0-2    centre (x, y, z): the three split planes, local coordinates
    bytes 12-15  float  3      half the cell's edge (nominal; the root's gives its cube)
    bytes 16-47  floats 4-11   the eight children's references, int32 bit patterns;
                               child k = bx + 2 by + 4 bz, where b_axis = 1 for the upper
                               half (coordinate >= centre) on that axis

A reference ``r >= 0`` is the row of an interior cell. ``r < 0`` is a leaf,
``~r = (first << leaf_bits) | count`` (``accel.geometry.leaf_references``): slots
``first .. first + count - 1`` of ``references`` (int32 [R], each a row of
``triangles``; a tree without triangles keeps one unused slot, R = 1, for the engine's
gather). An empty leaf is always ``r = -1`` (first 0, count 0), which the
traversal skips without a step. ``triangles`` float32 [T, 3, 3] (world coordinates) and
``triangle_ids`` int32 [T] hold the non-degenerate faces in mesh order, as brute force
stores them.
``layout``: (("leaf_bits", b),).

Parameters:
    max_leaf_size (default 4): a cell referencing more triangles is split. Malley's
        octree study (A shading method for computer generated images, M.S. thesis,
        University of Utah, 1988, section 5.3) finds the break-even node capacity at
        about T/R, the cost of a traversal step over that of a triangle test (his best:
        15-20 with T about 10 R). On the shared engine a step and a triangle test each
        cost one loop iteration (T about R), which puts it at a few triangles; on the
        camel, capacities 2-6 came within 5 % of each other in loop iterations per ray
        and 4 was the fastest.
    max_depth (default: the larger of ``floor(log4 N)`` and ``ceil(log2 S)``, at least 1):
        cells at this depth stay leaves whatever their count (they are counted in
        ``leaves_over_max_depth``). A surface of N triangles inside the root cube meets
        about 4^d cells at depth d, so depth log4 N brings the cells to about the size of
        its triangles; deeper cells only repeat the triangles around a vertex (a vertex of
        valence v keeps every cell around it at v or more references). On the camel (69k
        triangles) this is 8, which is also the default depth of the 3ds Max raytracer's
        voxel tree in octree mode; depth 9 was 5 % faster on camera rays at twice the build
        time. That count assumes the triangles fill the root cube; a small detailed object
        in a large scene (the teapot in a stadium) needs more levels to reach its
        triangles' size, so the depth is also at least ``log2 S``, S the bounding box's
        largest side over the median triangle's largest side (the triangles' own extents,
        :func:`size_ratio`): the camel's S is 2^7.1 (depth 8 either way), the camel in
        the scene suite's stadium 2^17.6 (depth 18; at depth 8 a leaf held 20,010
        triangles, too many for a leaf reference beside 72,958 reference rows).
"""

from __future__ import annotations

import time

import numpy as np

from accel.bvh import DEFAULT_INTERSECTION_COST, DEFAULT_TRAVERSAL_COST
from accel.geometry import (
    degenerate_mask,
    float32_up,
    frame_origin,
    leaf_bits_for,
    leaf_references,
    local_corners,
    overlap_rows,
    reference_margin,
    triangle_vertices,
)
from accel.registry import StructureKind, world_planes
from accel.structure import Structure

DEFAULT_MAX_LEAF_SIZE = 4
MAX_DEPTH_LIMIT = 32
ROW_FLOATS = 12
#: Pairs per block of a level's child tests (``_next_level``).
_PAIR_BLOCK = 1 << 15
#: child k's offset in the cell: bit a of k set means the upper half on axis a.
CHILD_BITS = ((np.arange(8)[:, None] >> np.arange(3)[None, :]) & 1).astype(bool)


def default_max_depth(triangles: int, size_ratio: float = 1.0) -> int:
    """The larger of floor(log4 N) and ceil(log2 ``size_ratio``), at least 1 and at most
    MAX_DEPTH_LIMIT (see the module docstring and :func:`size_ratio`)."""
    depth = 0
    while 4 ** (depth + 1) <= triangles:  # exact in integers
        depth += 1
    reach = 0
    while reach < MAX_DEPTH_LIMIT and 2.0 ** reach < size_ratio:  # exact powers of two
        reach += 1
    return int(min(MAX_DEPTH_LIMIT, max(1, depth, reach)))


def size_ratio(extents: np.ndarray, lo, hi) -> float:
    """The largest side of the triangles' bounding box (``lo``, ``hi`` [3]) over the median
    of their own largest sides (``extents`` [T], float64; 1.0 for no triangle): how many
    halvings the root cube needs to reach a typical triangle."""
    if extents.shape[0] == 0:
        return 1.0
    return float((np.asarray(hi) - np.asarray(lo)).max() / np.median(extents))


def _check_params(max_leaf_size, max_depth):
    if not (isinstance(max_leaf_size, int | np.integer) and not isinstance(max_leaf_size, bool)
            and 1 <= max_leaf_size <= 255):
        raise ValueError(
            f"octree: max_leaf_size must be an integer in [1, 255], got {max_leaf_size!r}")
    if max_depth is not None and not (
            isinstance(max_depth, int | np.integer) and not isinstance(max_depth, bool)
            and 1 <= max_depth <= MAX_DEPTH_LIMIT):
        raise ValueError(f"octree: max_depth must be None or an integer in "
                         f"[1, {MAX_DEPTH_LIMIT}], got {max_depth!r}")


def root_cube(lo: np.ndarray | None,
              hi: np.ndarray | None) -> tuple[np.ndarray, np.float32, np.ndarray, np.ndarray]:
    """(centre float32 [3], half float32, lo, hi): the root cube ``centre +- half``.

    ``lo``, ``hi``: float64 [3], the bounds of the triangles' corners in the local frame
    (``accel.geometry.local_corners``; they need not be float32 values), None without
    triangles. The returned lo and hi are the float32 values ``centre - half`` and
    ``centre + half`` (float32 arithmetic, as the traversal evaluates them), which contain
    every local corner (compared in float64).
    """
    if lo is None:
        centre, half = np.zeros(3, np.float32), np.float32(1)
    else:
        centre = ((lo + hi) / 2).astype(np.float32)
        extent = max(float(np.max(hi - centre)), float(np.max(centre - lo)), 0.0)
        # Slack for the float32 rounding of half and of centre +- half.
        slack = 4 * float(np.spacing(np.float32(np.abs(centre).max() + extent)))
        half = np.float32(float32_up(extent * (1 + 2.0**-20) + slack))
    while True:
        lo32, hi32 = centre - half, centre + half
        if lo is None or (np.all(lo32.astype(np.float64) <= lo)
                          and np.all(hi32.astype(np.float64) >= hi)):
            return centre, half, lo32, hi32
        half = np.float32(half * np.float32(1 + 2.0**-10))


#: Children per axis side: bit k of ``SIDE_MASKS[a, s]`` is set when child k lies on side
#: s (0 lower, 1 upper) of axis a.
SIDE_MASKS = np.array([[sum(1 << k for k in range(8) if ((k >> a) & 1) == s)
                        for s in range(2)] for a in range(3)], np.uint8)


def _children_pairs(points, tlo, thi, own, corners, wlo, whi, parent, tri):
    """(child cell, triangle) pairs of the next level, grouped by child (8 per parent),
    triangles ascending within a child.

    ``tlo``, ``thi`` [3, T]: the triangles' bounds per axis; ``wlo``, ``whi`` [8S, 3]: the
    children of the splitting cells widened by CELL_MARGIN of their size, to which each
    pair adds its triangle's ``own`` margin (CELL_MARGIN of its extent:
    ``accel.geometry.reference_margin``); ``parent``, ``tri``: the pairs of the splitting
    cells (``parent`` the pair's rank among them), grouped by parent, triangles ascending.
    ``points`` [3, T, 6]: per axis, each triangle's corners and edge midpoints (exact in
    float64); ``corners`` [9, T] the corners by component (``accel.geometry.overlap_rows``).

    A child's widened box is, on each axis, its parent's lower or upper widened
    interval, so every test runs per axis and side on the [P] pairs and becomes a byte
    of eight child bits (``SIDE_MASKS``): the children a set of per-axis sides selects
    are the AND over the axes of the OR of their sides' masks. A child the triangle's
    box misses is rejected; one that contains the triangle's box, or one of its corners
    or edge midpoints, certainly overlaps it; the separating-axis test decides the rest.
    """
    lower = 8 * parent  # child 0: the lower side on every axis
    m = own[tri]
    touch = np.full(tri.shape[0], 0xFF, np.uint8)
    sure = touch.copy()
    sides = []
    for a in range(3):
        lo_a, hi_a = tlo[a][tri], thi[a][tri]
        side = []
        t_a = np.zeros(tri.shape[0], np.uint8)
        c_a = np.zeros(tri.shape[0], np.uint8)
        for s in range(2):  # child 0 is on the lower side of every axis, child 7 upper
            s_lo, s_hi = wlo[7 * s::8, a][parent] - m, whi[7 * s::8, a][parent] + m
            t_a |= ((lo_a <= s_hi) & (hi_a >= s_lo)).view(np.uint8) * SIDE_MASKS[a, s]
            c_a |= ((lo_a >= s_lo) & (hi_a <= s_hi)).view(np.uint8) * SIDE_MASKS[a, s]
            side.append((s_lo, s_hi))
        touch &= t_a
        sure &= c_a
        sides.append(side)
    # Pairs with children to decide beyond their box: their corners and edge midpoints.
    open_ = np.flatnonzero(touch & ~sure)
    inside = np.full((open_.shape[0], 6), 0xFF, np.uint8)
    for a in range(3):
        x = points[a][tri[open_]]  # [Q, 6]
        p_a = np.zeros(x.shape, np.uint8)
        for s in range(2):
            s_lo, s_hi = (b[open_, None] for b in sides[a][s])
            p_a |= ((x >= s_lo) & (x <= s_hi)).view(np.uint8) * SIDE_MASKS[a, s]
        inside &= p_a
    sure[open_] |= (inside[:, 0] | inside[:, 1] | inside[:, 2] | inside[:, 3]
                    | inside[:, 4] | inside[:, 5])
    sure &= touch
    bits = np.unpackbits(touch, bitorder="little")  # [8P]: pair p's child k at 8 p + k
    slot = np.flatnonzero(bits)
    pair, k = slot >> 3, slot & 7
    child = lower[pair] + k
    overlap = ((sure[pair] >> k.astype(np.uint8)) & 1).astype(bool)
    undecided = np.flatnonzero(~overlap)
    if undecided.size:
        u_pair, u_child = pair[undecided], child[undecided]
        u_m = m[u_pair]
        overlap[undecided] = overlap_rows(
            corners[:, tri[u_pair]], [wlo[u_child, a] - u_m for a in range(3)],
            [whi[u_child, a] + u_m for a in range(3)])
    # Grouped by child, triangles ascending within a child (as the root lists them, and
    # so as every parent does): one sort of the unique keys child * T + triangle.
    t_count = corners.shape[1]
    key = np.sort(child[overlap] * t_count + tri[pair[overlap]])
    child = key // t_count
    return child, key - child * t_count


def _next_level(points, tlo, thi, own, corners, wlo, whi, parent, tri):
    """``_children_pairs`` over the level's pairs in blocks of about ``_PAIR_BLOCK``
    pairs, cut between parents: each block's children come out grouped by child, and the
    blocks' parents ascend, so the blocks' outputs in order are the level's. Blocks keep
    the per-pair temporaries in the cache (a level of the camel's octree holds up to
    300k pairs)."""
    cuts = np.searchsorted(parent, parent[::_PAIR_BLOCK], side="left")
    cuts = np.append(np.unique(cuts), parent.shape[0])
    out = [_children_pairs(points, tlo, thi, own, corners, wlo, whi, parent[a:b], tri[a:b])
           for a, b in zip(cuts[:-1], cuts[1:], strict=True)]
    if not out:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    return np.concatenate([c for c, _ in out]), np.concatenate([t for _, t in out])


def build(vertices: np.ndarray, faces: np.ndarray, *,
          max_leaf_size: int = DEFAULT_MAX_LEAF_SIZE, max_depth: int | None = None) -> Structure:
    """Build an octree over the non-degenerate faces (see the module docstring)."""
    _check_params(max_leaf_size, max_depth)
    start_time = time.perf_counter()
    keep = ~degenerate_mask(vertices, faces)
    ids = np.flatnonzero(keep).astype(np.int32)
    tris = triangle_vertices(vertices, np.asarray(faces)[ids])
    t_count = ids.shape[0]
    # Every geometric decision is taken in the local frame (exact float64 corners).
    frame = frame_origin(tris)
    t64 = local_corners(tris, frame)
    # Per-axis rows [T] for the level loop's gathers (a [T, 3, 3] reduction over its
    # small middle axis is several times slower than these element-wise minima): the
    # corners, their bounds, and per axis the corners and edge midpoints [3, T, 6].
    corners = np.ascontiguousarray(t64.reshape(-1, 9).T)
    c = [corners[3 * i:3 * i + 3] for i in range(3)]
    tlo = np.minimum(np.minimum(c[0], c[1]), c[2])
    thi = np.maximum(np.maximum(c[0], c[1]), c[2])
    # Each triangle's largest side (accel.geometry.triangle_extents), and the bounds of all.
    extent = np.maximum(np.maximum(thi[0] - tlo[0], thi[1] - tlo[1]), thi[2] - tlo[2])
    bounds = (tlo.min(axis=1), thi.max(axis=1)) if t_count else (None, None)
    own = reference_margin(0.0, extent)  # CELL_MARGIN of the triangle's extent
    depth_limit = (default_max_depth(t_count, size_ratio(extent, *bounds))
                   if max_depth is None else int(max_depth))
    points = np.stack([c[0], c[1], c[2], (c[0] + c[1]) / 2, (c[1] + c[2]) / 2,
                       (c[2] + c[0]) / 2], axis=2)

    centre, half, lo32, hi32 = root_cube(*bounds)
    cell_lo = lo32.astype(np.float64)[None]
    cell_hi = hi32.astype(np.float64)[None]
    pair_cell = np.zeros(t_count, np.int64)
    pair_tri = np.arange(t_count, dtype=np.int64)

    # Per level: interior rows (centre, half), each cell's fate, and the leaf lists.
    row_centres, row_halves = [], []
    level_split, level_first, level_count = [], [], []
    leaf_lists = []
    leaf_areas, leaf_sizes, interior_areas = [], [], []
    ref_offset = 0
    level_half = np.float64(half)
    forced = 0
    depth = 0
    while True:
        cells = cell_lo.shape[0]
        count = np.bincount(pair_cell, minlength=cells)
        if depth == 0:
            split = np.ones(cells, bool)  # the root is always interior
        elif depth >= depth_limit:
            split = np.zeros(cells, bool)
            forced += int((count > max_leaf_size).sum())
        else:
            split = count > max_leaf_size
        areas = _half_area(cell_lo, cell_hi)
        # Leaves: their pairs (already grouped by cell) are their reference lists.
        leaf = ~split
        in_leaf = leaf[pair_cell]
        leaf_lists.append(pair_tri[in_leaf])
        counts = count * leaf
        first = np.where(counts > 0, ref_offset + np.cumsum(counts) - counts, 0)
        ref_offset += int(counts.sum())
        level_split.append(split)
        level_first.append(first)
        level_count.append(counts)
        leaf_areas.append(areas[leaf])
        leaf_sizes.append(count[leaf])
        interior_areas.append(areas[split])
        if not split.any():
            break
        # Children of the splitting cells: faces from the parent's faces and centre.
        plo, phi = cell_lo[split], cell_hi[split]
        # (The root splits at its stored centre, of which its faces are centre +- half.)
        c32 = centre[None] if depth == 0 else ((plo + phi) / 2).astype(np.float32)
        c = c32.astype(np.float64)
        row_centres.append(c32)
        row_halves.append(np.full(c32.shape[0], level_half, np.float32))
        bits = CHILD_BITS[None]  # [1, 8, 3]
        child_lo = np.where(bits, c[:, None], plo[:, None]).reshape(-1, 3)
        child_hi = np.where(bits, phi[:, None], c[:, None]).reshape(-1, 3)
        grow = reference_margin(child_hi - child_lo, 0.0)
        wlo, whi = child_lo - grow, child_hi + grow
        splitting = split[pair_cell]
        pair_cell, pair_tri = _next_level(
            points, tlo, thi, own, corners, wlo, whi,
            (np.cumsum(split) - 1)[pair_cell[splitting]], pair_tri[splitting])
        cell_lo, cell_hi = child_lo, child_hi
        level_half = level_half / 2
        depth += 1

    return _flatten(tris, frame, ids, row_centres, row_halves, level_split, level_first,
                    level_count, leaf_lists, leaf_areas, leaf_sizes, interior_areas,
                    max_leaf_size=max_leaf_size, max_depth=depth_limit, depth=depth,
                    forced=forced, degenerate=int((~keep).sum()), start_time=start_time)


def _half_area(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    e = np.maximum(hi - lo, 0.0)
    return e[..., 0] * e[..., 1] + e[..., 1] * e[..., 2] + e[..., 2] * e[..., 0]


def _flatten(tris, frame, ids, row_centres, row_halves, level_split, level_first, level_count,
             leaf_lists, leaf_areas, leaf_sizes, interior_areas, *, max_leaf_size, max_depth,
             depth, forced, degenerate, start_time):
    references = np.concatenate(leaf_lists).astype(np.int32)
    reference_count = references.shape[0]
    if reference_count == 0:  # no triangle: one unused slot keeps the engine's gather legal
        references = np.zeros(1, np.int32)
    try:  # (interior cells have count 0 in the level arrays)
        leaf_bits = leaf_bits_for(np.concatenate(level_first), np.concatenate(level_count),
                                  references.shape[0])
    except ValueError as error:
        raise ValueError(f"octree: {error}") from None
    # Each level's cells as references: interior rows numbered breadth first.
    refs = []
    row_base = 0
    for split, first, count in zip(level_split, level_first, level_count, strict=True):
        rows = row_base + np.cumsum(split) - 1
        refs.append(np.where(split, rows, leaf_references(first, count, leaf_bits)))
        row_base += int(split.sum())
    m = row_base
    nodes = np.zeros((m, ROW_FLOATS), np.float32)
    nodes[:, 0:3] = np.concatenate(row_centres)
    nodes[:, 3] = np.concatenate(row_halves)
    # The interior cells of level d are, in order, the parents of level d + 1's cells.
    nodes.view(np.int32)[:, 4:12] = np.concatenate(refs[1:]).reshape(m, 8)

    leaf_sizes = np.concatenate(leaf_sizes)
    leaf_areas = np.concatenate(leaf_areas)
    interior_areas = np.concatenate(interior_areas)
    root_area = float(interior_areas[0])
    ct, ci = DEFAULT_TRAVERSAL_COST, DEFAULT_INTERSECTION_COST
    sah = (ct * interior_areas.sum() + ci * (leaf_areas * leaf_sizes).sum()) / root_area
    nonempty = leaf_sizes[leaf_sizes > 0]
    arrays = {"nodes": nodes, "references": references, "triangles": tris,
              "triangle_ids": ids, "frame": np.asarray(frame, np.float32)}
    stats = {
        "build_seconds": time.perf_counter() - start_time,
        "max_leaf_size": int(max_leaf_size),
        "max_depth": int(max_depth),
        "triangles": int(tris.shape[0]),
        "degenerate_skipped": degenerate,
        "cells": int(m + leaf_sizes.shape[0]),
        "nodes": int(m + leaf_sizes.shape[0]),
        "interior_cells": int(m),
        "leaves": int(leaf_sizes.shape[0]),
        "empty_leaves": int((leaf_sizes == 0).sum()),
        "depth": int(depth),
        "references": reference_count,
        "references_per_triangle": (float(reference_count / tris.shape[0])
                                    if tris.shape[0] else 0.0),
        "references_per_leaf_mean": float(nonempty.mean()) if nonempty.size else 0.0,
        "references_per_leaf_max": int(leaf_sizes.max()),
        "leaves_over_max_depth": forced,
        "sah_cost": float(sah),
        "bytes": int(sum(a.nbytes for a in arrays.values())),
    }
    return Structure(kind="octree", arrays=arrays, layout=(("leaf_bits", leaf_bits),),
                     stats=stats)


def stored_planes(structure: Structure) -> list[np.ndarray]:
    """Per axis, every cell's centre plane and the root cell's faces (world coordinates):
    the planes a cell's children split at."""
    nodes = np.asarray(structure["nodes"])
    c, h = nodes[0, :3], nodes[0, 3]
    return world_planes(structure, [np.concatenate([nodes[:, a], [c[a] - h, c[a] + h]])
                                    for a in range(3)])


KIND = StructureKind(
    name="octree", build=build,
    arrays=frozenset({"nodes", "references", "triangles", "triangle_ids", "frame"}),
    layout=frozenset({"leaf_bits"}), traversal="jrt.octree:traversal", planes=stored_planes,
    rows=frozenset({"nodes", "references", "triangles", "triangle_ids"}),
    summary="octree: cubic cells split at their centres, SAH-terminated")
