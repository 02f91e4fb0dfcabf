"""The general-plane BSP tree (``accel/bsp.py`` built, ``jrt/bsp.py`` on ``jrt/planes.py``).

Builder: the rows decoded against the documented layout (unit normals, a tree in
breadth-first rows, leaf codes, sibling leaves on adjacent slots), the statistics
recomputed, and the reference rule checked by point location, independently of how the
builder decides: points of every triangle (corners, edge midpoints, centroid, random
points) are sent down the tree with closed half-spaces (both ways on a plane), and every
leaf a point reaches must reference the point's triangle.

Traversal: the same hits as brute force, bit for bit, with every kernel: the camel (20k
camera and 20k incoherent rays, closest hit and ``occluded``), and random soups
(hypothesis) with flat axis-aligned triangles, rays with ±0.0 components, origins on the
tree's planes (exactly on its axis-aligned ones, rounded onto oblique ones) and rays lying
in or along them.
"""

from __future__ import annotations

import re
import warnings

import numpy as np
import pytest
import test_kdtree as kd
from hypothesis import given
from test_bvh_traversal import soup

import accel
from accel import bsp
from jrt.data import mesh_path
from jrt.mesh import load_mesh

KIND = "bsp"
STAT_KEYS = {
    "build_seconds", "bins", "triangle_planes", "general_min_references", "max_leaf_size",
    "max_depth", "traversal_cost", "intersection_cost", "empty_bonus", "triangles",
    "degenerate_skipped", "leaves_over_max_depth", "planes_axis", "planes_diagonal",
    "planes_triangle", "nodes", "interior_nodes", "leaves", "empty_leaves", "depth",
    "references", "references_per_triangle", "references_per_leaf_mean",
    "references_per_leaf_max", "sah_cost", "bytes",
}
DEFAULTS = {"bins": bsp.DEFAULT_BINS, "triangle_planes": bsp.DEFAULT_TRIANGLE_PLANES,
            "general_min_references": bsp.DEFAULT_GENERAL_MIN_REFERENCES,
            "max_leaf_size": bsp.DEFAULT_MAX_LEAF_SIZE,
            "traversal_cost": bsp.DEFAULT_TRAVERSAL_COST,
            "intersection_cost": bsp.DEFAULT_INTERSECTION_COST,
            "empty_bonus": bsp.DEFAULT_EMPTY_BONUS}

# Shared fixtures (see tests/test_kdtree.py: computed once for both modules).


def decode(structure) -> dict:
    nodes = np.asarray(structure["nodes"])
    assert nodes.dtype == np.float32 and nodes.ndim == 2 and nodes.shape[1] == 8
    np.testing.assert_array_equal(nodes[:, 6:8], 0)  # padding
    refs = np.ascontiguousarray(nodes).view(np.int32)[:, 4:6].astype(np.int64)
    normal = nodes[:, 0:3].astype(np.float64)
    offset = nodes[:, 3].astype(np.float64)
    assert np.all(np.isfinite(nodes[:, :4]))
    np.testing.assert_allclose(np.linalg.norm(normal, axis=1), 1, atol=1e-6)
    tree = kd.decode_tree(refs, structure.layout_value("leaf_bits"),
                          structure.stats["references"])
    bounds = np.asarray(structure["bounds"], np.float64)
    single = (nodes.shape[0] == 1 and refs[0, 1] == -1 and np.all(normal[0] == [1, 0, 0])
              and offset[0] == np.float32(bounds[1, 0]))
    return {**tree, "refs": refs, "normal": normal, "offset": offset, "single": single}


def check_bsp(structure, vertices, faces, **params):
    params = {**DEFAULTS, **params}
    kd.check_structure(structure, vertices, faces, kind=KIND)
    stats = structure.stats
    assert set(stats) == STAT_KEYS
    for key, value in params.items():
        if key != "max_depth":
            assert stats[key] == value
    tree = decode(structure)
    counts = tree["leaf_count"][:1] if tree["single"] else tree["leaf_count"]
    m = len(tree["depth"])
    interior = 0 if tree["single"] else m
    assert stats["interior_nodes"] == interior
    assert stats["leaves"] == interior + 1 == len(counts)
    assert stats["nodes"] == 2 * interior + 1
    assert stats["empty_leaves"] == int((counts == 0).sum())
    assert stats["depth"] == (0 if tree["single"] else int(tree["leaf_depth"].max()))
    assert stats["depth"] <= stats["max_depth"]
    if not tree["single"]:
        assert (stats["planes_axis"] + stats["planes_diagonal"] + stats["planes_triangle"]
                == interior)
    full = counts[counts > 0]
    assert stats["references_per_leaf_max"] == (int(full.max()) if full.size else 0)
    assert stats["references_per_leaf_mean"] == pytest.approx(
        full.mean() if full.size else 0.0, rel=1e-12)
    assert np.isfinite(stats["sah_cost"]) and stats["sah_cost"] >= 0
    return tree


def sample_points(triangles, rng, random_points=2):
    """Points of every triangle (float64) and their triangle: corners, edge midpoints,
    the centroid and ``random_points`` random points."""
    b = [np.eye(3), [[0.5, 0.5, 0], [0, 0.5, 0.5], [0.5, 0, 0.5]], [[1 / 3] * 3]]
    weights = np.concatenate([np.asarray(w, np.float64) for w in b])
    points = np.einsum("pk,tkj->tpj", weights, triangles)
    extra = rng.dirichlet(np.ones(3), (len(triangles), random_points))
    points = np.concatenate([points, np.einsum("tpk,tkj->tpj", extra, triangles)], axis=1)
    owner = np.repeat(np.arange(len(triangles)), points.shape[1])
    return points.reshape(-1, 3), owner


def check_point_location(structure, tree, rng, limit=None):
    """Every leaf that a point of a triangle reaches (closed half-spaces) references it."""
    # The cells are in the structure's frame: so are the triangles compared with them.
    triangles = (np.asarray(structure["triangles"], np.float64)
                 - np.asarray(structure["frame"], np.float64))
    if len(triangles) == 0:
        return
    if limit is not None and limit < len(triangles):
        pick = rng.choice(len(triangles), limit, replace=False)
    else:
        pick = np.arange(len(triangles))
    points, owner = sample_points(triangles[pick], rng)
    owner = pick[owner]
    scale = np.abs(triangles).max()
    # (A point within rounding of a plane goes both ways.)
    tolerance = 1e-12 * scale
    refs = tree["refs"]
    point = np.arange(len(points))
    row = np.zeros(len(points), np.int64)
    reached = []  # (point, leaf reference) pairs
    while point.size:
        d = (points[point] * tree["normal"][row]).sum(axis=1) - tree["offset"][row]
        nxt_p, nxt_r = [], []
        for side, go in ((0, d <= tolerance), (1, d >= -tolerance)):
            child = refs[row[go], side]
            nxt_p.append(point[go])
            nxt_r.append(child)
        point, row = np.concatenate(nxt_p), np.concatenate(nxt_r)
        leaf = row < 0
        reached.append((point[leaf], row[leaf]))
        point, row = point[~leaf], row[~leaf]
    p = np.concatenate([r[0] for r in reached])
    code = np.concatenate([r[1] for r in reached])
    if tree["single"]:  # only child 0 is the tree; child 1 is the documented empty leaf
        keep = code == refs[0, 0]
        p, code = p[keep], code[keep]
    leaf_bits = structure.layout_value("leaf_bits")
    first = ~code >> leaf_bits
    count = ~code & ((1 << leaf_bits) - 1)
    assert np.all(count > 0), "a triangle's point lies in an empty leaf"
    references = np.asarray(structure["references"])
    found = np.zeros(len(p), bool)
    for k in range(int(count.max())):  # is owner[p] among references[first : first+count]?
        ok = k < count
        found |= ok & (references[np.where(ok, first + k, 0)] == owner[p])
    assert found.all(), (f"{(~found).sum()} points reach a leaf without their triangle, "
                         f"e.g. triangle {owner[p][~found][:5]}")


def bsp_planes(structure) -> np.ndarray:
    """The tree's axis-aligned planes as (axis, value) rows."""
    nodes = np.asarray(structure["nodes"])
    axis_aligned = np.sum(nodes[:, 0:3] == 1, axis=1) == 1
    axis_aligned &= np.sum(nodes[:, 0:3] == 0, axis=1) == 2
    axis = np.argmax(nodes[:, 0:3], axis=1)
    return np.column_stack([axis, nodes[:, 3]])[axis_aligned]


def oblique_rays(rng, structure, origins, directions):
    """A sixth of the rays start on (rounded onto) an oblique plane of the tree; half of
    those run along it (direction projected on the plane)."""
    nodes = np.asarray(structure["nodes"], np.float64)
    oblique = np.flatnonzero(np.sum(nodes[:, 0:3] != 0, axis=1) > 1)
    if oblique.size == 0:
        return origins, directions
    origins, directions = origins.copy(), directions.copy()
    rows = np.flatnonzero(rng.random(len(origins)) < 1 / 6)
    pick = rng.choice(oblique, rows.size)
    n, c = nodes[pick, 0:3], nodes[pick, 3]
    o = origins[rows].astype(np.float64)
    origins[rows] = o - ((o * n).sum(axis=1) - c)[:, None] * n
    along = rng.random(rows.size) < 0.5
    d = directions[rows[along]].astype(np.float64)
    d -= (d * n[along]).sum(axis=1, keepdims=True) * n[along]
    length = np.linalg.norm(d, axis=1, keepdims=True)
    ok = length[:, 0] > 1e-3
    directions[rows[along][ok]] = d[ok] / length[ok]
    return origins, directions


# ---------------------------------------------------------------------------------------------
# Builder
# ---------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def camel_bsp(camel_structures):
    return camel_structures(KIND)  # built once per session (tests/conftest.py)


def test_camel_build_is_consistent(camel, camel_bsp):
    tree = check_bsp(camel_bsp, camel.vertices, camel.faces)
    stats = camel_bsp.stats
    assert stats["max_depth"] == round(8 + 1.3 * np.log2(stats["triangles"]))
    assert stats["planes_diagonal"] > 0 and stats["planes_triangle"] > 0
    print(f"\nBSP tree of the camel: {stats}")
    check_point_location(camel_bsp, tree, np.random.default_rng(0), limit=10_000)


@pytest.mark.parametrize(("param", "value", "message"), [
    ("bins", 1, "bins must be an integer in [2, 256], got 1"),
    ("max_leaf_size", 0, "max_leaf_size must be an integer in [1, 255], got 0"),
    ("max_depth", 65, "max_depth must be None or an integer in [0, 64], got 65"),
    ("traversal_cost", -1.0, "traversal_cost must be a positive finite number"),
    ("empty_bonus", 1.5, "empty_bonus must be a number in [0, 1), got 1.5"),
    ("triangle_planes", 17, "triangle_planes must be an integer in [0, 16], got 17"),
    ("triangle_planes", 1.0, "triangle_planes must be an integer in [0, 16], got 1.0"),
    ("general_min_references", 0, "general_min_references must be a positive integer, got 0"),
])
def test_bad_parameters_raise(param, value, message):
    with pytest.raises(ValueError, match=rf"^{KIND}: {re.escape(message)}"):
        accel.build(KIND, *kd.TINY, **{param: value})


@pytest.mark.parametrize("mesh", ["empty", "no vertices", "all degenerate", "one triangle"])
def test_tiny_meshes_build_and_trace(mesh):
    vertices, faces = {
        "empty": (np.zeros((3, 3), np.float32), np.zeros((0, 3), np.int32)),
        "no vertices": (np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32)),
        "all degenerate": kd.ALL_DEGENERATE,
        "one triangle": kd.TINY,
    }[mesh]
    structure = accel.build(KIND, vertices, faces)
    tree = check_bsp(structure, vertices, faces)
    assert tree["single"] and structure.stats["nodes"] == 1
    kd.check_tiny_traces(structure, vertices, faces, mesh)


@pytest.mark.parametrize("params", [{}, {"bins": 2}, {"general_min_references": 1},
                                    {"triangle_planes": 0, "max_leaf_size": 4},
                                    {"max_depth": 0}, {"traversal_cost": 0.1,
                                                       "general_min_references": 1}])
def test_random_soup_build_is_consistent(params):
    rng = np.random.default_rng(5)
    vertices, faces = kd.layered(rng, *soup(rng, 150, grid=True, flat=0.3, duplicates=0.1,
                                            shared=0.5), share=0.3)
    structure = accel.build(KIND, vertices, faces, **params)
    tree = check_bsp(structure, vertices, faces, **params)
    check_point_location(structure, tree, rng)
    if params.get("max_depth") == 0:
        assert tree["single"]
    elif params.get("general_min_references") == 1:
        assert structure.stats["planes_diagonal"] + structure.stats["planes_triangle"] > 0


#: On the fandisk these reach nodes whose bounding box has no area (a segment: a sliver
#: whose box rounded to nothing along two axes, with references through their margins),
#: where the SAH is 0 / 0: in the axis-plane search (64 bins) and in the general one.
FLAT_BOX_PARAMS = [{"bins": 64, "triangle_planes": 0},
                   {"general_min_references": 1, "bins": 64, "triangle_planes": 0}]


@pytest.mark.parametrize("params", [{}, *FLAT_BOX_PARAMS])
def test_real_mesh_builds_without_floating_point_warnings(params):
    """No division by zero nor invalid value on a real mesh (RuntimeWarnings as errors),
    and the tree still references every triangle wherever its points lie."""
    mesh = load_mesh(mesh_path("fandisk"))
    with warnings.catch_warnings(), np.errstate(divide="warn", invalid="warn", over="warn"):
        warnings.simplefilter("error", RuntimeWarning)
        structure = accel.build(KIND, mesh.vertices, mesh.faces, **params)
    tree = check_bsp(structure, mesh.vertices, mesh.faces, **params)
    check_point_location(structure, tree, np.random.default_rng(2))


def test_layer_cake_is_traced_exactly():
    """Triangles in the planes of axis-aligned splits (both sides for the BSP tree)."""
    vertices, faces = kd.layer_cake()
    structure = accel.build(KIND, vertices, faces, bins=2)
    check_point_location(structure, check_bsp(structure, vertices, faces, bins=2),
                         np.random.default_rng(1))
    kd.check_cake_traces(structure, vertices, faces)


# ---------------------------------------------------------------------------------------------
# The camel
# ---------------------------------------------------------------------------------------------


def test_camel_counters(camel_bsp, camel_rays, brute_hits):
    kd.check_counters(camel_bsp, camel_rays, brute_hits)


# ---------------------------------------------------------------------------------------------
# Random soups (hypothesis)
# ---------------------------------------------------------------------------------------------


@kd.PROPERTY
@given(case=kd.soups(kind=KIND))
def test_soup_build_is_consistent(case):
    vertices, faces, params, rng = case
    structure = accel.build(KIND, vertices, faces, **params)
    check_point_location(structure, check_bsp(structure, vertices, faces, **params), rng)


@kd.PROPERTY
@given(case=kd.soups(kind=KIND))
def test_soup_closest_hit_matches_brute(case):
    kd.check_soup_closest_hit(case, KIND, bsp_planes, oblique_rays)


@kd.PROPERTY
@given(case=kd.soups(kind=KIND))
def test_soup_occluded_matches_brute(case):
    kd.check_soup_occluded(case, KIND, bsp_planes, oblique_rays)


def test_one_leaf_of_every_needle_fits_its_leaf_reference():
    """The scene suite's slivers at full size: 50,000 needles through one region, which no
    plane separates, end in one leaf of all 50,000 references (first row 0) below empty-space
    cuts. Its code fits an int32 (only the leaves' largest first row and count matter); the
    bound from the total rows refused it. The BSP tree answers as brute force."""
    import jrt
    from jrt.raysets import incoherent_set
    from jrt.scenes import scene_mesh
    from jrt.trace import as_numpy

    mesh = scene_mesh("slivers")
    structure = accel.build("bsp", mesh.vertices, mesh.faces)
    assert structure.stats["references_per_leaf_max"] == len(mesh.faces)
    origins, directions = incoherent_set(mesh.vertices, 1024, seed=2)
    want = as_numpy(jrt.closest_hit(accel.build("brute", mesh.vertices, mesh.faces), origins,
                                    directions))
    got = as_numpy(jrt.closest_hit(structure, origins, directions))
    assert (want["triangle"] >= 0).mean() > 0.05
    for name in ("triangle", "t", "u", "v"):
        np.testing.assert_array_equal(got[name], want[name], err_msg=name)
    for name in ("triangle", "t"):
        assert got[name].dtype == want[name].dtype
