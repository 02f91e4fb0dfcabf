"""The build shared by the trees of split planes: the kd-tree (``accel.kdtree``) and the
general-plane BSP tree (``accel.bsp``).

Both cut space, not the triangle set, and both are built **level by level**: every node of
a level is handled at once by NumPy passes over the level's references (one per triangle
and node whose region the triangle reaches), sorted by node. What differs is the planes
each tree tries and how it decides which side a reference goes to; everything else lives
here:

- the triangles a tree is built over (:func:`tree_triangles`), the parameters' checks and
  defaults, and the cost model: the surface area heuristic of MacDonald & Booth (1990)
  with Wald & Havran's empty-space bonus (:func:`split_cost`, :func:`half_area`), and
  where empty-space cuts may go (:data:`EMPTY_CUT_GAP`, :data:`MIN_EMPTY_CUT`);
- :class:`LevelBuild`, the bookkeeping of the nodes: the active level (node ids, boxes,
  depth), the leaves closed and the splits made so far, the order in which a splitting
  node's references go to its two children (:class:`ChildOrder`), and the flattening into
  rows (:meth:`LevelBuild.rows`: interior rows breadth first, both children's references
  in the parent, leaf codes ``~((first << leaf_bits) | count)``, -1 an empty leaf) and the
  statistics (:meth:`LevelBuild.structure`).

A builder's loop, in outline (``rseg``: each reference's node in the level, ``rtri``: its
triangle row)::

    levels = LevelBuild(bounds, triangle_count, max_leaf_size, depth_limit, planes)
    while levels.active:
        counts = np.bincount(rseg, minlength=levels.size)
        splitting = levels.wanting_split(counts)
        ...                                   # choose planes; leave where none pays
        levels.close_leaves(splitting, counts, rseg, rtri)
        ...                                   # children's boxes, then:
        levels.split(nodes, below, above, axis=..., plane=...)
        ...                                   # which side(s) each reference goes to
        order = levels.descend(sel, node_of, member)
        rseg, rtri = order.segment, order.gather(rtri)
    rows = levels.rows(kind)                  # then the tree's own node rows
"""

from __future__ import annotations

import math
import time
from typing import NamedTuple

import numpy as np

from accel.geometry import (
    degenerate_mask,
    leaf_bits_for,
    leaf_references,
    local_frame,
    triangle_extents,
    triangle_vertices,
)
from accel.structure import Structure
from accel.threads import node_chunks, thread_map, threads_for

#: Cost constants. A traversal step and a triangle test each cost one iteration of the
#: engine's loop (``jrt.engine``), which puts K_T near K_I; measured with the kd-tree on the
#: camel (50k camera and 50k incoherent rays, steps + tests per ray), K_T = 1 costs 11.5
#: and 32.8, K_T = 2 11.8 and 33.5 with half the nodes and a 1.5x faster build, K_T = 4 12.6
#: and 36.2 (K_I = 1); Wald & Havran's K_T = 15, K_I = 20 and pbrt's 1 and 80 split far
#: deeper (2-3x the references of K_T = 2 at the depth limit). The empty-space bonus is
#: Wald & Havran's lambda = 0.8, i.e. ``empty_bonus`` 0.2 (pbrt-v3 uses 0.5, which here
#: spends the depth limit on empty cuts: 2x the work per ray). Leaves of one reference
#: before the split search is skipped: pbrt's ``maxPrims = 1``; the SAH stops earlier
#: wherever splitting does not pay.
DEFAULT_TRAVERSAL_COST = 2.0
DEFAULT_INTERSECTION_COST = 1.0
DEFAULT_EMPTY_BONUS = 0.2
DEFAULT_MAX_LEAF_SIZE = 1
MAX_DEPTH_LIMIT = 64
#: How far outside the geometry an empty-space cut is placed, relative to the room it cuts
#: off and the largest triangle of the node: 4 x CELL_MARGIN, so that a triangle touching
#: the geometry's bound is not referenced by the empty child (its margin is CELL_MARGIN of
#: that child's size and of its own extent, ``accel.geometry.reference_margin``).
EMPTY_CUT_GAP = 2.0**-14
#: An empty-space cut must cut off at least this fraction of the node's largest extent:
#: with the bonus any empty cut "pays", and thinner and thinner slivers next to geometry
#: lying in a plane would otherwise be cut off level after level.
MIN_EMPTY_CUT = 2.0**-10
#: Nodes per pass of a split search (:func:`accel.threads.node_chunks`): its per-candidate arrays
#: ([nodes, orientations, bins] float64) then stay a few MiB, in cache and reused by the
#: allocator, where a whole level's (up to GiBs on 1M triangles) would be mapped afresh,
#: page by page, for every temporary. The search is per node, so the result is the same.
SEARCH_CHUNK = 4096


def default_max_depth(triangles: int) -> int:
    """pbrt's rule: round(8 + 1.3 log2 N) (Pharr, Jakob & Humphreys, *Physically Based
    Rendering*, 3rd ed., section 4.4)."""
    return int(round(8 + 1.3 * math.log2(max(triangles, 1))))


def check_params(name, bins, max_leaf_size, max_depth, traversal_cost, intersection_cost,
                 empty_bonus) -> None:
    """A ValueError naming the tree (``name``), the parameter, its value and what is
    allowed, for the parameters both trees take."""
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


def search_level(counts: np.ndarray, search):
    """``search(run)`` of every run of :func:`node_chunks` (a run: first node, end node,
    first reference, end reference), the runs spread over threads (``accel.threads``, as
    many as the level's references warrant): (first node, end node, result) per run, in
    order. The search is per node, so the results do not depend on the runs."""
    threads = threads_for(int(counts.sum()))
    runs = list(node_chunks(counts, SEARCH_CHUNK, parts=threads))
    return [(run[0], run[1], best)
            for run, best in zip(runs, thread_map(search, runs, threads), strict=True)]


def split_cost(ct, ci, bonus, a_left, a_right, area, n_left, n_right):
    """The SAH cost of a split (Wald & Havran 2006, eq. 4): ``lambda * (K_T + K_I *
    (A_L N_L + A_R N_R) / A)``, lambda = 1 - ``bonus`` when a side is empty, else 1."""
    cost = ct + ci * (a_left * n_left + a_right * n_right) / area
    return cost * np.where((n_left == 0) | (n_right == 0), 1.0 - bonus, 1.0)


class TreeTriangles(NamedTuple):
    """The triangles a plane tree is built over: the mesh's non-degenerate faces, in mesh
    order.

    Attributes:
        ids: int32 [T], their face rows (``triangle_ids``).
        stored: float32 [T, 3, 3], their corners as stored (``triangles``).
        frame: the structure's local frame (``accel.geometry.local_frame``).
        local: float64 [T, 3, 3], the corners in that frame (the build works on these).
        bounds: float32 [2, 3], their exact bounding box in the frame (the root's box).
        extent: float64 [T], each triangle's own extent (``triangle_extents``).
        degenerate: how many faces were left out (zero area).
    """

    ids: np.ndarray
    stored: np.ndarray
    frame: np.ndarray
    local: np.ndarray
    bounds: np.ndarray
    extent: np.ndarray
    degenerate: int


def tree_triangles(vertices: np.ndarray, faces: np.ndarray) -> TreeTriangles:
    """The non-degenerate faces of a mesh, as a plane tree is built over them."""
    keep = ~degenerate_mask(vertices, faces)
    ids = np.flatnonzero(keep).astype(np.int32)
    stored = triangle_vertices(vertices, np.asarray(faces)[ids]).reshape(-1, 3, 3)
    frame, local, bounds = local_frame(stored)
    return TreeTriangles(ids, stored, frame, local, bounds, triangle_extents(local),
                         int((~keep).sum()))


def concatenated(parts, dtype, shape=(0,)) -> np.ndarray:
    """The arrays ``parts`` end to end as ``dtype``; an empty array of ``shape`` if none."""
    return np.concatenate(parts).astype(dtype) if parts else np.zeros(shape, dtype)


class ChildOrder:
    """Where the references of a level's splitting nodes go in the next level's arrays.

    The next level's references are sorted by child (child 0 of the first splitting node,
    its child 1, then the next node's), each child's in their order in the level; a
    reference on both sides (a straddler) is in both children. Children that receive no
    reference are not in the next level.

    The order is one stable sort of the *entries* (side 0's members, then side 1's, each
    in level order) by the key ``2 * node + side``: the keys are two ascending runs, which
    the stable sort (timsort) merges in O(S); the next level then takes every array with
    one gather (``source``) instead of a scatter per side.

    Args:
        sel: int [S], the rows (in the level's reference arrays) of the splitting nodes'
            references, in level order.
        node_of: int [S], each one's node among the ``m`` splitting nodes (0 .. m-1),
            ascending.
        member: two bool [S] arrays: whether each goes to child 0 (below the plane) and to
            child 1 (above).
        m: the number of splitting nodes.

    Attributes:
        size: the next level's reference count.
        live: the children (index ``2 * node + side``) that receive references.
        segment: int64 [size], each next-level reference's node in the next level.
        rows: (rows 0, rows 1), the members of each side (indices into ``sel``); the
            entries are their concatenation.
        entry: int64 [size], each next-level reference's entry.
        source: int64 [size], each next-level reference's row in the level.
    """

    def __init__(self, sel, node_of, member, m):
        self.rows = (np.flatnonzero(member[0]), np.flatnonzero(member[1]))
        key = np.concatenate([2 * node_of[self.rows[0]], 2 * node_of[self.rows[1]] + 1])
        self.entry = np.argsort(key, kind="stable")
        n_child = np.bincount(key, minlength=2 * m)
        self.size = int(key.size)
        self.live = np.flatnonzero(n_child)
        self.segment = np.repeat(np.arange(self.live.size), n_child[self.live])
        self.source = np.concatenate([sel[self.rows[0]], sel[self.rows[1]]])[self.entry]

    def gather(self, values: np.ndarray) -> np.ndarray:
        """A per-reference array of the level (indexed by reference row) for the next
        level: each reference's value in each child that receives it."""
        return values[self.source]


class TreeRows(NamedTuple):
    """A plane tree flattened, before its node rows are written (:meth:`LevelBuild.rows`).

    Attributes:
        planes: each per-split field given to :meth:`LevelBuild.split`, one entry per
            interior row (breadth first).
        children: int64 [S, 2], each interior row's references to its two children: a row
            ``>= 0``, a leaf code ``< -1``, -1 an empty leaf.
        root: the root's reference when the tree is a single leaf (-1: no triangles).
        leaf_bits: the leaf code's split between first slot and count.
        references: int32 [R], the leaves' triangle rows, leaf after leaf.
        interior_ids, leaf_ids, leaf_count: node ids of the interior rows and of the
            leaves, and the leaves' reference counts (for the statistics).
    """

    planes: dict
    children: np.ndarray
    root: int
    leaf_bits: int
    references: np.ndarray
    interior_ids: np.ndarray
    leaf_ids: np.ndarray
    leaf_count: np.ndarray


class LevelBuild:
    """The nodes of a plane tree built level by level.

    Nodes get ids in creation order (the root 0, then both children of each split, level
    after level: breadth first). Per node: its box (float64, the local frame; for the BSP
    tree the bounding box of its region) and depth; per split: the children's ids and the
    fields the tree stores for its plane; per leaf: its slots in ``references``.

    Args:
        bounds: float32 [2, 3], the root's box.
        triangle_count: the triangles (none: no active node, the tree is one empty leaf).
        max_leaf_size: nodes with at most this many references are not split.
        depth_limit: the deepest level split.
        planes: per-split fields: name -> (dtype, shape of one entry).
    """

    def __init__(self, bounds, triangle_count, max_leaf_size, depth_limit, planes):
        self.max_leaf_size, self.depth_limit = max_leaf_size, depth_limit
        self._fields = dict(planes)
        self.ids = np.zeros(1 if triangle_count else 0, np.int64)
        self.lo = bounds[None, 0].astype(np.float64)[: len(self.ids)]
        self.hi = bounds[None, 1].astype(np.float64)[: len(self.ids)]
        self.depth = 0
        self.next_id = len(self.ids)
        self.node_lo, self.node_hi = [self.lo], [self.hi]
        self.node_depth = [np.zeros(len(self.ids), np.int64)]
        self.split_ids, self.split_child = [], []
        self.split_planes = {name: [] for name in self._fields}
        self.leaf_ids, self.leaf_first, self.leaf_count, self.leaf_refs = [], [], [], []
        self.references_out = 0
        self.over_depth = 0
        self._children = None

    @property
    def active(self) -> bool:
        """Whether the current level has nodes."""
        return self.ids.shape[0] > 0

    @property
    def size(self) -> int:
        """The current level's node count."""
        return self.ids.shape[0]

    def wanting_split(self, counts: np.ndarray) -> np.ndarray:
        """The level's nodes that may be split: more than ``max_leaf_size`` references and
        above the depth limit (those stopped by the limit are counted)."""
        want = counts > self.max_leaf_size
        splitting = want & (self.depth < self.depth_limit)
        self.over_depth += int((want & ~splitting).sum())
        return splitting

    def close_leaves(self, splitting, counts, rseg, rtri) -> None:
        """The level's nodes not ``splitting`` become leaves; their references (``rtri``,
        sorted by node ``rseg``) take the next slots of ``references``, in node order."""
        leaf_nodes = np.flatnonzero(~splitting)
        if leaf_nodes.size:
            self.leaf_refs.append(rtri[~splitting[rseg]])
            c = counts[leaf_nodes]
            self.leaf_ids.append(self.ids[leaf_nodes])
            self.leaf_first.append(self.references_out + np.cumsum(c) - c)
            self.leaf_count.append(c)
            self.references_out += int(c.sum())

    def split(self, nodes, below, above, **planes) -> None:
        """Split the level's ``nodes`` (indices, increasing): ``below`` and ``above`` are
        the children's boxes (lo, hi), [m, 3] each; ``planes`` the fields of each plane."""
        m = nodes.size
        child_ids = self.next_id + np.arange(2 * m)
        self.next_id += 2 * m
        self.split_ids.append(self.ids[nodes])
        for name, value in planes.items():
            self.split_planes[name].append(value)
        self.split_child.append(child_ids.reshape(m, 2))
        child_lo = np.stack([below[0], above[0]], axis=1).reshape(-1, 3)
        child_hi = np.stack([below[1], above[1]], axis=1).reshape(-1, 3)
        self.node_lo.append(child_lo)
        self.node_hi.append(child_hi)
        self.node_depth.append(np.full(2 * m, self.depth + 1, np.int64))
        self._children = (child_ids, child_lo, child_hi)

    def descend(self, sel, node_of, member) -> ChildOrder:
        """Go to the next level: the children of the last :meth:`split` that receive
        references, placed as :class:`ChildOrder` says (its arguments)."""
        child_ids, child_lo, child_hi = self._children
        order = ChildOrder(sel, node_of, member, child_ids.size // 2)
        self.ids = child_ids[order.live]
        self.lo = child_lo[order.live]
        self.hi = child_hi[order.live]
        self.depth += 1
        self._children = None
        return order

    def rows(self, kind: str) -> TreeRows:
        """The tree flattened: interior rows breadth first, children's references, leaf
        codes (a ValueError, naming ``kind``, when the leaves do not fit one)."""
        s_ids = concatenated(self.split_ids, np.int64)
        planes = {name: concatenated(self.split_planes[name], dtype, (0,) + tuple(shape))
                  for name, (dtype, shape) in self._fields.items()}
        s_child = concatenated(self.split_child, np.int64, (0, 2))
        l_ids = concatenated(self.leaf_ids, np.int64)
        l_first = concatenated(self.leaf_first, np.int64)
        l_count = concatenated(self.leaf_count, np.int64)
        references = concatenated(self.leaf_refs, np.int32)
        try:
            leaf_bits = leaf_bits_for(l_first, l_count, references.shape[0])
        except ValueError as error:
            raise ValueError(f"{kind}: {error}") from None
        # The reference of every node: interior rows in creation (breadth-first) order,
        # leaves by their code, empty children (never active) -1.
        total = self.next_id
        ref = np.full(max(total, 1), -1, np.int64)
        order = np.argsort(s_ids)
        s_ids, s_child = s_ids[order], s_child[order]
        planes = {name: value[order] for name, value in planes.items()}
        ref[s_ids] = np.arange(s_ids.size)
        ref[l_ids] = leaf_references(l_first, l_count, leaf_bits)
        ref[l_ids[l_count == 0]] = -1
        return TreeRows(planes, ref[s_child], int(ref[0]) if total else -1, leaf_bits,
                        references, s_ids, l_ids, l_count)

    def structure(self, kind: str, nodes: np.ndarray, rows: TreeRows,
                  triangles: TreeTriangles, params: dict, extra: dict,
                  start_time: float) -> Structure:
        """The record of a plane tree once its node rows are written: its arrays and
        statistics. The SAH cost is Goldsmith & Salmon's: (C_T Σ interior areas + C_I Σ
        leaf area × references) / root area (boxes' areas)."""
        total = self.next_id
        lo = concatenated(self.node_lo, np.float64, (0, 3))
        hi = concatenated(self.node_hi, np.float64, (0, 3))
        depth = concatenated(self.node_depth, np.int64)
        interior = np.zeros(total, bool)
        interior[rows.interior_ids] = True
        is_leaf = ~interior
        # Per leaf (including empty children): its reference count.
        count = np.zeros(total, np.int64)
        count[rows.leaf_ids] = rows.leaf_count
        areas = half_area(lo, hi)
        root_area = areas[0] if total else 0.0
        ct, ci = params["traversal_cost"], params["intersection_cost"]
        if root_area > 0:
            sah = (ct * areas[interior].sum()
                   + ci * (areas[is_leaf] * count[is_leaf]).sum()) / root_area
        else:
            sah = 0.0
        l_count = rows.leaf_count
        full = l_count[l_count > 0]
        references = rows.references
        if references.size == 0:
            # The engine gathers a slot even when no leaf names one: one unused slot.
            references = np.zeros(1, np.int32)
        tris = triangles.stored
        arrays = {"nodes": nodes, "bounds": triangles.bounds.astype(np.float32),
                  "references": references, "triangles": np.ascontiguousarray(tris),
                  "triangle_ids": triangles.ids,
                  "frame": np.asarray(triangles.frame, np.float32)}
        stats = {
            "build_seconds": time.perf_counter() - start_time,
            **params,
            "triangles": int(tris.shape[0]),
            **extra,
            "nodes": int(total) if total else 1,
            "interior_nodes": int(rows.interior_ids.size),
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
        return Structure(kind=kind, arrays=arrays, layout=(("leaf_bits", rows.leaf_bits),),
                         stats=stats)
