"""The kd-tree (``accel/kdtree.py`` built, ``jrt/kdtree.py`` on ``jrt/planes.py`` traced).

Builder: the arrays decoded against the documented layout by an independent decoder (a tree
in breadth-first rows, leaf codes, sibling leaves on adjacent slots, every split strictly
inside its cell); the statistics recomputed; and the reference rule checked with the shared
exact triangle-box test: a triangle that touches a leaf's widened cell is referenced by the
leaf, unless it lies in the plane of a split above the leaf (Wald & Havran's planar rule
sends those to one side), and a referenced triangle comes within the margin of the leaf.

Traversal: the same hits as brute force, bit for bit, with every kernel: on the camel (20k
camera and 20k incoherent rays, closest hit and ``occluded``), on a layered mesh where
triangles lie in the split planes, and on random soups (hypothesis) with axis-aligned flat
triangles on the planes of a coarse grid (where the bins' planes fall), rays with ±0.0
direction components and origins exactly on split planes, some of them lying in the plane.
The soups' trees are padded to fixed shapes so that every example runs the same compiled
kernels.
"""

from __future__ import annotations

import re
import warnings

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from test_bvh_traversal import (
    CAP,
    KERNELS,
    N_RAYS,
    assert_same_hits,
    check_closest_hit_matches_brute,
    check_occluded_matches_brute,
    fixed_shape_brute,
    rays,
    soup,
)

import accel
import jrt
from accel import kdtree
from accel.geometry import CELL_MARGIN, triangles_overlap_boxes
from accel.structure import Structure
from jrt.data import mesh_path
from jrt.mesh import load_mesh
from jrt.trace import as_numpy

KIND = "kdtree"
CHILD_COLUMNS = (2, 3)
STAT_KEYS = {
    "build_seconds", "bins", "max_leaf_size", "max_depth", "traversal_cost",
    "intersection_cost", "empty_bonus", "triangles", "degenerate_skipped",
    "planar_references", "leaves_over_max_depth", "nodes", "interior_nodes", "leaves",
    "empty_leaves", "depth", "references", "references_per_triangle",
    "references_per_leaf_mean", "references_per_leaf_max", "sah_cost", "bytes",
}
DEFAULTS = {"bins": kdtree.DEFAULT_BINS, "max_leaf_size": kdtree.DEFAULT_MAX_LEAF_SIZE,
            "traversal_cost": kdtree.DEFAULT_TRAVERSAL_COST,
            "intersection_cost": kdtree.DEFAULT_INTERSECTION_COST,
            "empty_bonus": kdtree.DEFAULT_EMPTY_BONUS}
PROPERTY = settings(max_examples=20, deadline=None, database=None)



# ---------------------------------------------------------------------------------------------
# An independent decoder of the layout
# ---------------------------------------------------------------------------------------------


def expected_ids(vertices, faces) -> np.ndarray:
    corners = np.asarray(vertices, np.float32)[np.asarray(faces)].astype(np.float64)
    if len(corners) == 0:
        return np.zeros(0, np.int64)
    normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    return np.flatnonzero(np.any(normal != 0, axis=1))


def half_area(lo, hi):
    e = np.maximum(np.asarray(hi, np.float64) - np.asarray(lo, np.float64), 0.0)
    return e[..., 0] * e[..., 1] + e[..., 1] * e[..., 2] + e[..., 2] * e[..., 0]


def decode_tree(refs: np.ndarray, leaf_bits: int, slots: int) -> dict:
    """The tree of child references [M, 2] (int64): asserts its shape; returns per row its
    parent (row, slot) and depth, and per leaf child its row, slot, first, count."""
    m = refs.shape[0]
    is_node = refs >= 0
    parent_row, parent_slot = np.nonzero(is_node)
    child = refs[is_node]
    assert np.all((parent_row < child) & (child < m)), "a reference to an earlier row"
    np.testing.assert_array_equal(np.bincount(child, minlength=m), [0] + [1] * (m - 1))
    parent = np.full((m, 2), -1, np.int64)
    parent[child] = np.stack([parent_row, parent_slot], axis=1)
    depth = np.zeros(m, np.int64)
    for row in range(1, m):  # rows are breadth first: parents come first
        depth[row] = depth[parent[row, 0]] + 1
    leaf_row, leaf_slot = np.nonzero(~is_node)
    code = ~refs[~is_node]
    first, count = code >> leaf_bits, code & ((1 << leaf_bits) - 1)
    empty = count == 0
    assert np.all(refs[~is_node][empty] == -1), "an empty leaf is coded -1"
    assert np.all((first >= 0) & (first + count <= slots))
    # Non-empty leaves tile the reference slots, each slot in exactly one leaf.
    cover = np.zeros(slots + 1, np.int64)
    np.add.at(cover, first[~empty], 1)
    np.add.at(cover, (first + count)[~empty], -1)
    np.testing.assert_array_equal(np.cumsum(cover)[:slots], 1)
    # Two leaf children of one row hold adjacent slots (the traversal takes them as one).
    both = np.all(~is_node & (refs != -1), axis=1)
    lo_code, hi_code = ~refs[both, 0], ~refs[both, 1]
    f0, c0 = lo_code >> leaf_bits, lo_code & ((1 << leaf_bits) - 1)
    f1, c1 = hi_code >> leaf_bits, hi_code & ((1 << leaf_bits) - 1)
    assert np.all((f0 + c0 == f1) | (f1 + c1 == f0)), "sibling leaves are not adjacent"
    return {"parent": parent, "depth": depth, "leaf_row": leaf_row, "leaf_slot": leaf_slot,
            "leaf_first": first, "leaf_count": count, "leaf_depth": depth[leaf_row] + 1}


def decode(structure) -> dict:
    """The kd-tree's rows decoded: planes, cells of every child (row, slot) and the planes
    on each row's path (for the planar rule)."""
    nodes = np.asarray(structure["nodes"])
    assert nodes.dtype == np.float32 and nodes.ndim == 2 and nodes.shape[1] == 4
    fields = np.ascontiguousarray(nodes).view(np.int32)
    refs = fields[:, 2:4].astype(np.int64)
    axis = fields[:, 1].astype(np.int64)
    split = nodes[:, 0].astype(np.float64)
    assert np.all((axis >= 0) & (axis < 3))
    tree = decode_tree(refs, structure.layout_value("leaf_bits"),
                       structure.stats["references"])
    m = nodes.shape[0]
    bounds = np.asarray(structure["bounds"], np.float64)
    cell_lo = np.zeros((m, 2, 3))
    cell_hi = np.zeros((m, 2, 3))
    row_lo, row_hi = np.zeros((m, 3)), np.zeros((m, 3))
    row_lo[0], row_hi[0] = bounds
    path = [[] for _ in range(m)]  # (axis, plane) of the splits above each row's cell
    for row in range(m):
        if row:
            p, slot = tree["parent"][row]
            row_lo[row], row_hi[row] = cell_lo[p, slot], cell_hi[p, slot]
            path[row] = path[p] + [(axis[p], split[p])]
        cell_lo[row] = row_lo[row]
        cell_hi[row] = row_hi[row]
        cell_hi[row, 0, axis[row]] = split[row]
        cell_lo[row, 1, axis[row]] = split[row]
    # The documented single-leaf (or empty) tree: one row, its plane on the box's face.
    single = (m == 1 and refs[0, 1] == -1 and axis[0] == 0
              and split[0] == nodes.dtype.type(bounds[1, 0]))
    if not single:
        inside = (split > row_lo[np.arange(m), axis]) & (split < row_hi[np.arange(m), axis])
        assert inside.all(), "a split plane outside its cell"
        assert np.all(split == nodes[:, 0])  # float32 planes
    return {**tree, "refs": refs, "axis": axis, "split": split, "cell_lo": cell_lo,
            "plane": lambda row: (axis[row], split[row]),
            "cell_hi": cell_hi, "path": path, "single": single, "row_lo": row_lo,
            "row_hi": row_hi}


def check_structure(structure, vertices, faces, kind=KIND):
    """Arrays, triangles and bounds as documented (shared with the BSP tree's tests)."""
    vertices = np.asarray(vertices, np.float32)
    faces = np.asarray(faces)
    assert structure.kind == kind
    assert set(structure.arrays) == {"nodes", "bounds", "references", "triangles",
                                     "triangle_ids", "frame"}
    triangles, ids, references, bounds, frame = (np.asarray(structure[k]) for k in (
        "triangles", "triangle_ids", "references", "bounds", "frame"))
    assert triangles.dtype == np.float32 and ids.dtype == np.int32
    assert references.dtype == np.int32 and bounds.dtype == np.float32
    keep = expected_ids(vertices, faces)
    np.testing.assert_array_equal(ids, keep)
    np.testing.assert_array_equal(triangles, vertices[faces[keep]].reshape(-1, 3, 3))
    assert np.all((references >= 0) & (references < max(len(keep), 1)))
    if len(keep):
        # The frame: the point of the triangles' box nearest the origin; the root cell:
        # their exact box in that frame, rounded outward to float32.
        lo, hi = triangles.min(axis=(0, 1)), triangles.max(axis=(0, 1))
        np.testing.assert_array_equal(frame, np.minimum(np.maximum(0, lo), hi))
        exact = np.stack([lo, hi]).astype(np.float64) - frame.astype(np.float64)
        assert (bounds[0] <= exact[0]).all() and (bounds[1] >= exact[1]).all()
        np.testing.assert_array_equal(
            np.nextafter(bounds[0], np.float32(np.inf)) > exact[0], True)
        np.testing.assert_array_equal(
            np.nextafter(bounds[1], np.float32(-np.inf)) < exact[1], True)
        # Every triangle is referenced somewhere.
        assert np.all(np.bincount(references, minlength=len(keep)) >= 1)
    else:  # one unused slot (the engine gathers one)
        np.testing.assert_array_equal(bounds, 0)
        np.testing.assert_array_equal(references, [0])
    stats = structure.stats
    assert stats["triangles"] == len(keep) == structure.num_triangles
    assert stats["degenerate_skipped"] == len(faces) - len(keep)
    assert stats["bytes"] == structure.nbytes
    assert stats["references"] == (len(references) if len(keep) else 0)
    assert stats["build_seconds"] >= 0


def check_stats(structure, tree, cell_area):
    """Counts, depth, leaf sizes and SAH cost recomputed from the decoded tree."""
    stats = structure.stats
    counts = tree["leaf_count"]
    m = len(tree["depth"])
    if tree["single"]:
        leaves, interior, depth = 1, 0, 0
        counts = counts[:1]
    else:
        leaves, interior, depth = len(counts), m, int(tree["leaf_depth"].max())
    assert stats["interior_nodes"] == interior
    assert stats["leaves"] == leaves == interior + 1
    assert stats["nodes"] == interior + leaves
    assert stats["empty_leaves"] == int((counts == 0).sum())
    assert stats["depth"] == depth <= stats["max_depth"]
    full = counts[counts > 0]
    assert stats["references_per_leaf_max"] == (int(full.max()) if full.size else 0)
    assert stats["references_per_leaf_mean"] == pytest.approx(
        full.mean() if full.size else 0.0, rel=1e-12)
    ct, ci = stats["traversal_cost"], stats["intersection_cost"]
    if stats["triangles"]:
        root = cell_area(0, None)
        cost = 0.0 if tree["single"] else ct * (root + sum(cell_area(r, s) for r, s in zip(
            *np.nonzero(tree["refs"] >= 0), strict=True)))
        if tree["single"]:
            cost += ci * root * counts.sum()
        else:
            cost += ci * sum(cell_area(r, s) * c for r, s, c in zip(
                tree["leaf_row"], tree["leaf_slot"], tree["leaf_count"], strict=True))
        assert stats["sah_cost"] == pytest.approx(cost / root, rel=1e-9)


def planar_excused(triangle, path) -> bool:
    """Does the triangle lie in the plane of one of the splits of ``path``?"""
    return any(np.all(triangle[:, a] == s) for a, s in path)


def check_references(structure, tree, leaves=None, rng=None):
    """The reference rule on every leaf (or a sample of ``leaves``)."""
    # The cells are in the structure's frame: so are the triangles compared with them.
    triangles = (np.asarray(structure["triangles"], np.float64)
                 - np.asarray(structure["frame"], np.float64))
    references = np.asarray(structure["references"])
    if len(triangles) == 0:
        return
    full = np.arange(1 if tree["single"] else len(tree["leaf_count"]))
    if leaves is not None and leaves < len(full):
        full = rng.choice(full, leaves, replace=False)
    root_lo, root_hi = tree["row_lo"][0], tree["row_hi"][0]
    tri_lo, tri_hi = triangles.min(axis=1), triangles.max(axis=1)
    # Each triangle's own margin: CELL_MARGIN of its extent (the least a face is widened).
    own = CELL_MARGIN * (tri_hi - tri_lo).max(axis=1)
    for chunk in np.array_split(full, max(1, len(full) // 64)):
        rows, slots = tree["leaf_row"][chunk], tree["leaf_slot"][chunk]
        lo, hi = tree["cell_lo"][rows, slots], tree["cell_hi"][rows, slots]
        # Candidates by bounds, then the exact test on the cell widened by the margin.
        near = np.all((tri_lo[None] <= hi[:, None] + own[None, :, None])
                      & (tri_hi[None] >= lo[:, None] - own[None, :, None]), axis=2)
        leaf_i, tri_i = np.nonzero(near)
        touch = np.zeros(near.shape, bool)
        touch[leaf_i, tri_i] = triangles_overlap_boxes(
            triangles[tri_i], lo[leaf_i] - own[tri_i, None], hi[leaf_i] + own[tri_i, None])
        held = np.zeros(near.shape, bool)
        for i, leaf in enumerate(chunk):
            first, count = tree["leaf_first"][leaf], tree["leaf_count"][leaf]
            held[i, references[first:first + count]] = True
            assert len(np.unique(references[first:first + count])) == count, "a duplicate"
        for i, t in zip(*np.nonzero(touch & ~held), strict=True):
            path = tree["path"][rows[i]] + [tree["plane"](rows[i])]
            assert planar_excused(triangles[t], path), (
                f"triangle {t} touches leaf ({rows[i]}, {slots[i]})'s widened cell, "
                "unreferenced")
        # A referenced triangle reaches the cell widened by the largest margin: CELL_MARGIN
        # of the root's extent and of the triangle's.
        li, ti = np.nonzero(held)
        reach = (CELL_MARGIN * (root_hi - root_lo))[None] + own[ti, None]
        assert triangles_overlap_boxes(triangles[ti], lo[li] - reach, hi[li] + reach).all(), \
            "a reference to a triangle away from the leaf"


def check_kdtree(structure, vertices, faces, **params):
    params = {**DEFAULTS, **params}
    check_structure(structure, vertices, faces)
    stats = structure.stats
    assert set(stats) == STAT_KEYS
    for key in ("bins", "max_leaf_size", "traversal_cost", "intersection_cost",
                "empty_bonus"):
        assert stats[key] == params[key]
    tree = decode(structure)

    def cell_area(row, slot):
        if slot is None:
            return half_area(tree["row_lo"][row], tree["row_hi"][row])
        return half_area(tree["cell_lo"][row, slot], tree["cell_hi"][row, slot])

    check_stats(structure, tree, cell_area)
    return tree


# ---------------------------------------------------------------------------------------------
# Builder
# ---------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def camel_kdtree(camel_structures):
    return camel_structures(KIND)  # built once per session (tests/conftest.py)


def test_camel_build_is_consistent(camel, camel_kdtree):
    tree = check_kdtree(camel_kdtree, camel.vertices, camel.faces)
    stats = camel_kdtree.stats
    assert stats["max_depth"] == round(8 + 1.3 * np.log2(stats["triangles"]))
    assert 1 < stats["references_per_triangle"] < 10
    print(f"\nkd-tree of the camel: {stats}")
    check_references(camel_kdtree, tree, leaves=200, rng=np.random.default_rng(0))


def test_real_mesh_builds_without_floating_point_warnings():
    """No division by zero nor invalid value on a real mesh with flat parts (RuntimeWarnings
    as errors), and a consistent tree."""
    mesh = load_mesh(mesh_path("fandisk"))
    with warnings.catch_warnings(), np.errstate(divide="warn", invalid="warn", over="warn"):
        warnings.simplefilter("error", RuntimeWarning)
        structure = accel.build(KIND, mesh.vertices, mesh.faces)
    tree = check_kdtree(structure, mesh.vertices, mesh.faces)
    check_references(structure, tree, leaves=200, rng=np.random.default_rng(2))


@pytest.mark.parametrize(("param", "value", "message"), [
    ("bins", 1, "bins must be an integer in [2, 256], got 1"),
    ("bins", 16.0, "bins must be an integer"),
    ("max_leaf_size", 0, "max_leaf_size must be an integer in [1, 255], got 0"),
    ("max_leaf_size", 256, "max_leaf_size must be an integer in [1, 255]"),
    ("max_depth", -1, "max_depth must be None or an integer in [0, 64], got -1"),
    ("max_depth", 65, "max_depth must be None or an integer"),
    ("traversal_cost", 0.0, "traversal_cost must be a positive finite number"),
    ("intersection_cost", float("inf"), "intersection_cost must be a positive finite"),
    ("empty_bonus", 1.0, "empty_bonus must be a number in [0, 1), got 1.0"),
    ("empty_bonus", -0.1, "empty_bonus must be a number in [0, 1)"),
])
def test_bad_parameters_raise(param, value, message):
    vertices, faces = TINY
    with pytest.raises(ValueError, match=rf"^{KIND}: {re.escape(message)}"):
        accel.build(KIND, vertices, faces, **{param: value})


def test_unknown_parameter_raises():
    with pytest.raises(TypeError):
        accel.build(KIND, *TINY, leaf_size=3)


TINY = (np.float32([[-1, -1, 1], [3, -1, 1], [-1, 3, 1]]), np.int32([[0, 1, 2]]))
ALL_DEGENERATE = (np.float32([[0, 0, 0], [1, 1, 1], [2, 2, 2]]),
                  np.int32([[0, 1, 2], [0, 0, 1], [2, 2, 2]]))


@pytest.mark.parametrize("mesh", ["empty", "no vertices", "all degenerate", "one triangle"])
def test_tiny_meshes_build_and_trace(mesh):
    vertices, faces = {
        "empty": (np.zeros((3, 3), np.float32), np.zeros((0, 3), np.int32)),
        "no vertices": (np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32)),
        "all degenerate": ALL_DEGENERATE,
        "one triangle": TINY,
    }[mesh]
    structure = accel.build(KIND, vertices, faces)
    tree = check_kdtree(structure, vertices, faces)
    assert tree["single"] and structure.stats["nodes"] == 1
    check_tiny_traces(structure, vertices, faces, mesh)


def check_tiny_traces(structure, vertices, faces, mesh):
    origins = np.float32([[0.5, 0.5, 0], [0.5, 0.5, 2], [5, 5, 0], [0, 0, 1], [0.5, 0.5, 1]])
    directions = np.float32([[0, 0, 1], [0, -0.0, -1], [0, 0, 1], [1, 0, 0], [0, 1, -0.0]])
    brute = accel.build("brute", vertices, faces)
    padded, brute_padded = fixed_shape(structure), fixed_shape_brute(brute)
    for kernel in KERNELS:
        got, want, occluded = traced(padded, brute_padded, origins, directions, kernel)
        assert_same_hits(got, want, origins, directions, f"{mesh}/{kernel}")
        np.testing.assert_array_equal(occluded, want["triangle"] >= 0)
    if mesh == "one triangle":
        np.testing.assert_array_equal(want["triangle"], [0, 0, -1, -1, -1])


def traced(structure, brute, origins, directions, kernel):
    """Closest hits of ``structure`` and ``brute`` and the structure's ``occluded``, traced
    in batches of N_RAYS rays, as the property tests do (they share compiled kernels)."""
    n = len(origins)
    pad = -n % N_RAYS
    o = np.concatenate([origins, np.zeros((pad, 3), np.float32)])
    d = np.concatenate([directions, np.tile(np.float32([0, 0, 1]), (pad, 1))])
    got, want, occluded = [], [], []
    for i in range(0, len(o), N_RAYS):
        ob, db = o[i:i + N_RAYS], d[i:i + N_RAYS]
        got.append(as_numpy(jrt.closest_hit(structure, ob, db, kernel=kernel, lanes=64)))
        want.append(as_numpy(jrt.closest_hit(brute, ob, db, kernel=kernel)))
        inf = np.full(N_RAYS, np.inf, np.float32)
        occluded.append(np.asarray(jrt.occluded(structure, ob, db, tmax=inf, kernel=kernel,
                                                lanes=32)))
    merge = lambda parts: {k: np.concatenate([p[k] for p in parts])[:n]  # noqa: E731
                           for k in parts[0]}
    return merge(got), merge(want), np.concatenate(occluded)[:n]


@pytest.mark.parametrize("params", [{}, {"bins": 2}, {"max_leaf_size": 8},
                                    {"max_depth": 0}, {"max_depth": 3, "bins": 4},
                                    {"traversal_cost": 0.1, "empty_bonus": 0.0}])
def test_random_soup_build_is_consistent(params):
    rng = np.random.default_rng(3)
    vertices, faces = layered(rng, *soup(rng, 150, grid=True, flat=0.3, duplicates=0.1,
                                         shared=0.5), share=0.3)
    structure = accel.build(KIND, vertices, faces, **params)
    tree = check_kdtree(structure, vertices, faces, **params)
    check_references(structure, tree)
    if params.get("max_depth") == 0:
        assert tree["single"]


# ---------------------------------------------------------------------------------------------
# Triangles in split planes
# ---------------------------------------------------------------------------------------------


def layer_cake():
    """Flat triangles tiling [-1, 1]^2 at z = -1, 0 and 1 (with bins=2 the only interior
    candidates are the cell's mid-planes, so the layer at z = 0 lies in a split plane)."""
    grid = np.linspace(-1, 1, 5)
    quads = []
    for z in (-1.0, 0.0, 1.0):
        for i in range(4):
            for j in range(4):
                x0, x1, y0, y1 = grid[i], grid[i + 1], grid[j], grid[j + 1]
                quads.append([[x0, y0, z], [x1, y0, z], [x1, y1, z]])
                quads.append([[x0, y0, z], [x1, y1, z], [x0, y1, z]])
    vertices = np.float32(quads).reshape(-1, 3)
    return vertices, np.arange(len(vertices), dtype=np.int32).reshape(-1, 3)


def cake_rays():
    """Vertical rays onto vertices, edges and interiors of the layers, from above, below
    and from exactly z = 0 (both ways, ±0.0 components); rays lying in z = 0; oblique
    rays crossing z = 0 on edges."""
    xy = np.stack(np.meshgrid(np.linspace(-1.25, 1.25, 11), np.linspace(-1.25, 1.25, 11)),
                  -1).reshape(-1, 2)
    o, d = [], []
    for z, dz in ((2.0, -1.0), (-2.0, 1.0), (0.0, 1.0), (0.0, -1.0), (0.5, -1.0)):
        for zero in (0.0, -0.0):
            o.append(np.column_stack([xy, np.full(len(xy), z)]))
            d.append(np.tile([zero, -zero, dz], (len(xy), 1)))
    o.append(np.column_stack([xy, np.zeros(len(xy))]))  # in the plane z = 0
    d.append(np.tile([1.0, 0.0, -0.0], (len(xy), 1)))
    o.append(np.column_stack([xy, np.full(len(xy), 1.0)]))
    d.append(np.tile([-0.6, 0.0, -0.8], (len(xy), 1)))
    return np.float32(np.concatenate(o)), np.float32(np.concatenate(d))


def test_triangles_in_split_planes_are_traced_exactly():
    vertices, faces = layer_cake()
    structure = accel.build(KIND, vertices, faces, bins=2, max_leaf_size=1)
    tree = check_kdtree(structure, vertices, faces, bins=2)
    check_references(structure, tree)
    assert structure.stats["planar_references"] > 0
    check_cake_traces(structure, vertices, faces)


def check_cake_traces(structure, vertices, faces):
    origins, directions = cake_rays()
    padded = fixed_shape(structure)
    brute = fixed_shape_brute(accel.build("brute", vertices, faces))
    for kernel in KERNELS:
        got, want, occluded = traced(padded, brute, origins, directions, kernel)
        assert (want["triangle"] >= 0).mean() > 0.5
        assert_same_hits(got, want, origins, directions, kernel)
        np.testing.assert_array_equal(occluded, want["triangle"] >= 0)


# ---------------------------------------------------------------------------------------------
# The camel
# ---------------------------------------------------------------------------------------------


def check_counters(structure, ray_sets, brute):
    origins, directions = ray_sets["incoherent"]
    hits, count = jrt.closest_hit(structure, origins, directions, counters=True)
    assert_same_hits(as_numpy(hits), brute("watertight", "incoherent"), origins,
                     directions, "counters")
    steps, tests, leaves = (np.asarray(a) for a in count)
    hit = np.asarray(hits.triangle) >= 0
    assert (steps >= 1).all() and (tests[hit] >= 1).all() and (leaves[hit] >= 1).all()
    assert (leaves <= tests).all()
    # A node is stepped through at most once per ray; a leaf's slots tested at most once.
    assert (steps <= structure.stats["nodes"]).all()
    assert (tests <= structure.stats["references"]).all()
    assert tests.mean() < 0.01 * structure.stats["triangles"]
    print(f"\n{structure.kind} per incoherent ray: steps {steps.mean():.1f}, tests "
          f"{tests.mean():.1f}, leaves {leaves.mean():.1f}")


def test_camel_counters(camel_kdtree, camel_rays, brute_hits):
    check_counters(camel_kdtree, camel_rays, brute_hits)


# ---------------------------------------------------------------------------------------------
# Random soups (hypothesis)
# ---------------------------------------------------------------------------------------------

N_NODES = 8192  # rows a soup's tree is padded to
N_REFERENCES = 16384
LEAF_BITS = 8


#: Where each plane tree's rows hold their child references.
CHILD_COLUMNS_OF = {"kdtree": CHILD_COLUMNS, "bsp": (4, 5)}


def fixed_shape(structure: Structure) -> Structure:
    """The same tree with N_NODES rows, N_REFERENCES slots, CAP triangles, LEAF_BITS."""
    columns = CHILD_COLUMNS_OF[structure.kind]
    nodes = np.asarray(structure["nodes"])
    m, width = nodes.shape
    references = np.asarray(structure["references"])
    leaf_bits = structure.layout_value("leaf_bits")
    assert m <= N_NODES and len(references) <= N_REFERENCES and leaf_bits <= LEAF_BITS
    refs = nodes.view(np.int32)[:, list(columns)]
    code = ~refs
    recoded = np.where(refs >= 0, refs,
                       ~(((code >> leaf_bits) << LEAF_BITS) | (code & ((1 << leaf_bits) - 1))))
    padded = np.zeros((N_NODES, width), np.float32)
    padded[:m] = nodes
    padded.view(np.int32)[:m, list(columns)] = recoded
    slots = np.zeros(N_REFERENCES, np.int32)
    slots[:len(references)] = references
    t = structure.num_triangles
    triangles = np.zeros((CAP, 3, 3), np.float32)
    triangles[:t] = structure["triangles"]
    ids = np.full(CAP, -1, np.int32)
    ids[:t] = structure["triangle_ids"]
    return Structure(kind=structure.kind, arrays={
        "nodes": padded, "bounds": np.asarray(structure["bounds"]), "references": slots,
        "triangles": triangles, "triangle_ids": ids, "frame": np.asarray(structure["frame"])},
        layout=(("leaf_bits", LEAF_BITS),),
        stats=structure.stats)


def layered(rng, vertices, faces, share):
    """A share of the triangles flattened onto axis planes at -1, -0.5, 0, 0.5 or 1: on a
    coarse grid spanning [-2, 2], the planes where binned candidates fall."""
    tri = vertices[faces].copy()
    rows = np.flatnonzero(rng.random(len(tri)) < share)
    axes = rng.integers(0, 3, rows.size)
    tri[rows, :, axes] = rng.choice([-1.0, -0.5, 0.0, 0.5, 1.0], rows.size)[:, None]
    return tri.reshape(-1, 3).astype(np.float32), np.arange(3 * len(tri),
                                                            dtype=np.int32).reshape(-1, 3)


def plane_rays(rng, planes, origins, directions):
    """A third of the rays moved to start exactly on a split plane ``(axis, value)``; half
    of those lie in it (that direction component ±0.0)."""
    origins, directions = origins.copy(), directions.astype(np.float64)
    if len(planes) == 0:
        return origins, directions.astype(np.float32)
    rows = np.flatnonzero(rng.random(len(origins)) < 1 / 3)
    pick = rng.integers(0, len(planes), rows.size)
    axes = planes[pick, 0].astype(np.int64)
    origins[rows, axes] = planes[pick, 1]
    lying = rng.random(rows.size) < 0.5
    rows, axes = rows[lying], axes[lying]
    directions[rows, axes] = 0
    length = np.linalg.norm(directions[rows], axis=1)
    stuck = length == 0
    directions[rows[stuck]] = 1.0
    directions[rows, axes] = 0
    directions[rows] /= np.linalg.norm(directions[rows], axis=1, keepdims=True)
    directions = directions.astype(np.float32)
    directions[rows, axes] = np.where(rng.random(rows.size) < 0.5, 0.0, -0.0)
    return origins, directions


def kd_planes(structure) -> np.ndarray:
    nodes = np.asarray(structure["nodes"])
    if nodes.shape[0] == 1 and nodes.view(np.int32)[0, 3] == -1:
        return np.zeros((0, 2))
    return np.column_stack([nodes.view(np.int32)[:, 1], nodes[:, 0]])


@st.composite
def soups(draw, kind=KIND):
    """(vertices, faces, build parameters, rng) of one example."""
    seed = draw(st.integers(0, 2**32 - 1))
    n = draw(st.integers(10, CAP))
    grid = draw(st.booleans())
    flat = draw(st.sampled_from([0.0, 0.3, 1.0]))
    duplicates = draw(st.sampled_from([0.0, 0.1, 0.5]))
    shared = draw(st.sampled_from([0.0, 0.5, 2.0]))
    share = draw(st.sampled_from([0.3, 0.8]))
    params = {"bins": draw(st.sampled_from([2, 4, 8, 16])),
              "max_leaf_size": draw(st.sampled_from([1, 2, 4]))}
    if kind == KIND:
        params["empty_bonus"] = draw(st.sampled_from([0.0, 0.2, 0.5]))
    else:  # the BSP tree: general planes at small nodes too
        params["triangle_planes"] = draw(st.sampled_from([0, 2, 4]))
        params["general_min_references"] = draw(st.sampled_from([1, 16]))
    rng = np.random.default_rng(seed)
    vertices, faces = soup(rng, n, grid=grid, flat=flat, duplicates=duplicates, shared=shared)
    vertices, faces = layered(rng, vertices, faces, share)
    return vertices, faces, params, rng


def soup_case(case, kind, planes, more_rays):
    vertices, faces, params, rng = case
    unpadded = accel.build(kind, vertices, faces, **params)
    origins, directions = rays(rng, vertices, faces)
    origins, directions = plane_rays(rng, planes(unpadded), origins, directions)
    if more_rays is not None:
        origins, directions = more_rays(rng, unpadded, origins, directions)
    brute_unpadded = accel.build("brute", vertices, faces)
    scale = float(np.abs(vertices).max()) * 4
    return (params, brute_unpadded, fixed_shape(unpadded),
            fixed_shape_brute(brute_unpadded), scale, origins, directions, rng)


def check_soup_closest_hit(case, kind=KIND, planes=kd_planes, more_rays=None):
    params, unpadded, structure, brute, scale, origins, directions, rng = soup_case(
        case, kind, planes, more_rays)
    check_closest_hit_matches_brute(structure, brute, unpadded, origins, directions, rng,
                                    scale, f"{kind} {params}")


def check_soup_occluded(case, kind=KIND, planes=kd_planes, more_rays=None):
    params, unpadded, structure, brute, scale, origins, directions, rng = soup_case(
        case, kind, planes, more_rays)
    check_occluded_matches_brute(structure, brute, unpadded, origins, directions, rng, scale,
                                 f"{kind} {params}")


@PROPERTY
@given(case=soups())
def test_soup_build_is_consistent(case):
    vertices, faces, params, _ = case
    structure = accel.build(KIND, vertices, faces, **params)
    check_references(structure, check_kdtree(structure, vertices, faces, **params))


@PROPERTY
@given(case=soups())
def test_soup_closest_hit_matches_brute(case):
    check_soup_closest_hit(case)


@PROPERTY
@given(case=soups())
def test_soup_occluded_matches_brute(case):
    check_soup_occluded(case)


def test_clip_polygons_clips_by_vertex_count_group():
    # A triangle and a square (4 slots: the square fills them; the triangle's 4th slot is
    # garbage, which clipping must not read), clipped to x <= 0.5 and to x >= 0.5.
    tri = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [9.0, 9.0, 9.0]]
    square = [[0.0, 0.0, 1.0], [1.0, 0.0, 1.0], [1.0, 1.0, 1.0], [0.0, 1.0, 1.0]]
    poly = np.array([tri, square])
    count = np.array([3, 4])
    axis = np.array([0, 0])
    bound = np.array([0.5, 0.5])
    below, below_count = kdtree.clip_polygons(poly, count, axis, bound, True)
    above, above_count = kdtree.clip_polygons(poly, count, axis, bound, False)
    assert below_count.tolist() == [4, 4] and above_count.tolist() == [3, 4]
    np.testing.assert_array_equal(below[0], [[0, 0, 0], [0.5, 0, 0], [0.5, 0.5, 0], [0, 1, 0]])
    np.testing.assert_array_equal(above[0], [[0.5, 0, 0], [1, 0, 0], [0.5, 0.5, 0], [0.5, 0, 0]])
    np.testing.assert_array_equal(below[1], [[0, 0, 1], [0.5, 0, 1], [0.5, 1, 1], [0, 1, 1]])
    np.testing.assert_array_equal(above[1], [[0.5, 0, 1], [1, 0, 1], [1, 1, 1], [0.5, 1, 1]])
    # Entirely inside: unchanged (unused slots repeat vertex 0).
    same, same_count = kdtree.clip_polygons(poly[:1], count[:1], axis[:1], np.array([2.0]),
                                            True)
    assert same_count.tolist() == [3]
    np.testing.assert_array_equal(same[0], tri[:3] + [tri[0]])


def _clip_one(v, axis, bound, upper):
    """Sutherland & Hodgman for one polygon, vertex by vertex (the reference for the
    vectorised clip): kept vertices and strict crossings, in order."""
    d = [(p[axis] - bound) if upper else (bound - p[axis]) for p in v]
    out = []
    for i, p in enumerate(v):
        j = (i + 1) % len(v)
        if d[i] <= 0:
            out.append(p)
        if (d[i] < 0 < d[j]) or (d[i] > 0 > d[j]):
            x = p + d[i] / (d[i] - d[j]) * (v[j] - p)
            x[axis] = bound
            out.append(x)
    return out


def test_clip_polygons_matches_polygon_by_polygon_clipping():
    # Mixed vertex counts (groups), vertices on the plane (coordinates rounded), polygons
    # wholly outside (count 0, the slots repeat vertex 0): bit for bit as one at a time.
    rng = np.random.default_rng(7)
    k, slots = 300, 10
    count = rng.integers(3, 8, k)
    poly = rng.normal(size=(k, slots, 3)).round(1)
    axis = rng.integers(0, 3, k)
    bound = rng.normal(size=k).round(1)
    for upper in (True, False):
        out, out_count = kdtree.clip_polygons(poly, count, axis, bound, upper)
        for i in range(k):
            want = _clip_one(list(poly[i, :count[i]]), axis[i], bound[i], upper)
            if len(want) > slots:  # (rounding only) left unclipped
                want = list(poly[i, :count[i]])
            assert out_count[i] == len(want)
            pad = want[0] if want else poly[i, 0]
            expect = np.array(want + [pad] * (slots - len(want)))
            assert out[i].tobytes() == expect.tobytes()
