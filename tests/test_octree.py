"""The octree (``accel/octree.py`` built, ``jrt/octree.py`` traced).

Builder: the arrays decoded against the documented layout by an independent walk (a tree of
interior rows in breadth-first order, eight children each, cells halved at the stored float32
centres, leaf codes over disjoint slot ranges, all in the local frame around ``frame``, a
point of the triangles' bounding box); the statistics recomputed from the decoded
cells; and the reference rule checked densely, leaf by leaf against every triangle, with the
shared exact triangle-box test on the widened leaf cell: a leaf references a triangle if and
only if the triangle (in the local frame) touches the leaf's widened cell.

Traversal: the same hits as brute force, bit for bit, with every kernel: on the camel (20k
camera and 20k incoherent rays, closest hit and ``occluded``),
and on random soups (hypothesis) with axis-aligned
flat triangles, triangles lying exactly in the octree's mid-planes and on the root cube's
faces, rays with ±0.0 direction components, origins exactly on cell faces and at cell
centres, rays lying in a mid-plane, and soups far from the origin. The soups' trees are
padded to fixed shapes so that every example runs the same compiled kernels.

Far from the origin: the camel moved by 1e3 and 1e5 and scaled by 1e-4 and 1e4 builds the
references it builds at the origin (the margins follow the scene's extent, not its
position) and gives brute force's hits; so does a scene of two camels 1e3 apart.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from test_bvh_build import chain, expected_ids, half_area, random_mesh, stacked
from test_bvh_traversal import (
    CAP,
    KERNELS,
    assert_same_hits,
    check_closest_hit_matches_brute,
    check_occluded_matches_brute,
    fixed_shape_brute,
    rays,
    signed_zeros,
    soup,
)

import accel
import jrt
from accel import octree
from accel.geometry import (
    CELL_MARGIN,
    float32_down,
    float32_up,
    frame_origin,
    local_corners,
    triangles_overlap_boxes,
)
from accel.structure import Structure
from jrt.engine import POSITION_DEPENDENT_KERNELS, StackOverflowError
from jrt.raysets import incoherent_set
from jrt.trace import as_numpy

STAT_KEYS = {
    "build_seconds", "max_leaf_size", "max_depth", "triangles", "degenerate_skipped", "cells",
    "nodes", "interior_cells", "leaves", "empty_leaves", "depth", "references",
    "references_per_triangle", "references_per_leaf_mean", "references_per_leaf_max",
    "leaves_over_max_depth", "sah_cost", "bytes",
}
PROPERTY = settings(max_examples=20, deadline=None, database=None)

@pytest.fixture(scope="module")
def camel_octree(camel):
    return accel.build("octree", camel.vertices, camel.faces)


# ---------------------------------------------------------------------------------------------
# An independent decoder of the layout
# ---------------------------------------------------------------------------------------------


def decode(structure) -> dict:
    """Walk the tree level by level from row 0, asserting its shape on the way.

    Returns the interior cells' boxes and depths, and the leaves' boxes, depths, slot
    ranges and references (float64 boxes: a child is its parent's box cut at the parent's
    stored float32 centre, the root is ``centre +- half`` evaluated in float32).
    """
    nodes = np.asarray(structure["nodes"])
    assert nodes.dtype == np.float32 and nodes.ndim == 2 and nodes.shape[1] == 12
    refs = nodes.view(np.int32)[:, 4:12]
    bits = structure.layout_value("leaf_bits")
    m = nodes.shape[0]
    assert m >= 1, "the root is always an interior row"
    centre, half = nodes[0, :3], nodes[0, 3]
    rows = np.zeros(1, np.int64)
    lo = (centre - half).astype(np.float64)[None]
    hi = (centre + half).astype(np.float64)[None]
    seen = np.zeros(m, np.int64)
    seen[0] = 1
    interior = {"lo": [], "hi": [], "depth": [], "row": []}
    leaves = {"lo": [], "hi": [], "depth": [], "ref": []}
    bit = ((np.arange(8)[:, None] >> np.arange(3)) & 1).astype(bool)
    depth = 0
    while rows.size:
        interior["lo"].append(lo)
        interior["hi"].append(hi)
        interior["depth"].append(np.full(rows.size, depth))
        interior["row"].append(rows)
        c = nodes[rows, :3].astype(np.float64)
        # Below the root (split at its stored centre), a cell's centre is the float32
        # midpoint of its faces.
        if depth:
            np.testing.assert_array_equal(nodes[rows, :3], ((lo + hi) / 2).astype(np.float32))
        np.testing.assert_array_equal(nodes[rows, 3], np.float32(half / 2.0**depth))
        child_lo = np.where(bit[None], c[:, None], lo[:, None]).reshape(-1, 3)
        child_hi = np.where(bit[None], hi[:, None], c[:, None]).reshape(-1, 3)
        child_ref = refs[rows].reshape(-1).astype(np.int64)
        inner = child_ref >= 0
        assert (child_ref[inner] > np.repeat(rows, 8)[inner]).all(), "not breadth first"
        assert (child_ref[inner] < m).all()
        seen[child_ref[inner]] += 1
        leaves["lo"].append(child_lo[~inner])
        leaves["hi"].append(child_hi[~inner])
        leaves["depth"].append(np.full((~inner).sum(), depth + 1))
        leaves["ref"].append(child_ref[~inner])
        rows, lo, hi = child_ref[inner], child_lo[inner], child_hi[inner]
        depth += 1
    assert (seen == 1).all(), "every interior row is referenced exactly once"
    out = {k: np.concatenate(v) for k, v in interior.items()}
    out = {"interior_" + k: v for k, v in out.items()}
    out.update({"leaf_" + k: np.concatenate(v) for k, v in leaves.items()})
    code = ~out["leaf_ref"]
    out["leaf_first"], out["leaf_count"] = code >> bits, code & ((1 << bits) - 1)
    empty = out["leaf_count"] == 0
    assert (out["leaf_ref"][empty] == -1).all(), "an empty leaf is always -1"
    return out


def leaf_of_slots(decoded, slots: int) -> np.ndarray:
    """The leaf owning each slot of ``references``, asserting the ranges tile [0, R)."""
    first, count = decoded["leaf_first"], decoded["leaf_count"]
    owner = np.full(slots, -1, np.int64)
    leaf = np.repeat(np.arange(first.size), count)
    slot = np.repeat(first, count) + np.arange(count.sum()) - np.repeat(
        np.cumsum(count) - count, count)
    assert slot.size == slots and (slot < slots).all()
    owner[slot] = leaf
    assert (owner >= 0).all() and (np.bincount(slot, minlength=slots) <= 1).all()
    return owner


def dense_overlaps(local, lo, hi, tri_ids) -> list[np.ndarray]:
    """For each triangle row in ``tri_ids``: the leaves whose cell, widened by CELL_MARGIN
    of its size and of the triangle's extent, it touches, every leaf tested (a
    bounding-box cut first, then the exact separating-axis test). ``local``: the
    triangles in the tree's frame (float64), as the cells are."""
    tri = np.asarray(local, np.float64)
    out = []
    for t in tri_ids:
        tlo, thi = tri[t].min(axis=0), tri[t].max(axis=0)
        grow = CELL_MARGIN * ((hi - lo) + (thi - tlo).max())
        wlo, whi = lo - grow, hi + grow
        near = np.flatnonzero(np.all((tlo <= whi) & (thi >= wlo), axis=1))
        hit = triangles_overlap_boxes(np.repeat(tri[t][None], near.size, 0), wlo[near],
                                      whi[near])
        out.append(near[hit])
    return out


def expected_default_depth(vertices, faces, ids):
    """The default depth, from the triangles in float64: the larger of floor(log4 N) and
    ceil(log2 S), S the bounding box's largest side over the median triangle's."""
    tris = np.asarray(vertices, np.float64)[np.asarray(faces)[ids]]
    if tris.shape[0] == 0:
        return octree.default_max_depth(0)
    sides = (tris.max(axis=1) - tris.min(axis=1)).max(axis=1)
    corners = tris.reshape(-1, 3)
    ratio = (corners.max(axis=0) - corners.min(axis=0)).max() / np.median(sides)
    return octree.default_max_depth(ids.size, ratio)


def check_octree(structure, vertices, faces, *, sample=None, rng=None, **params):
    """The arrays against the documented layout, the reference rule and the stats."""
    assert structure.kind == "octree"
    stats = structure.stats
    assert set(stats) == STAT_KEYS
    k = params.get("max_leaf_size", octree.DEFAULT_MAX_LEAF_SIZE)
    ids = expected_ids(vertices, faces)
    limit = params.get("max_depth") or expected_default_depth(vertices, faces, ids)
    assert stats["max_leaf_size"] == k and stats["max_depth"] == limit
    np.testing.assert_array_equal(structure["triangle_ids"], ids)
    assert structure["triangle_ids"].dtype == np.int32
    np.testing.assert_array_equal(
        structure["triangles"], np.asarray(vertices, np.float32)[np.asarray(faces)[ids]])
    triangles = structure["triangles"]
    references = np.asarray(structure["references"])
    assert references.dtype == np.int32
    # The local frame (a point of the triangles' bounding box); the cells are local.
    frame = np.asarray(structure["frame"])
    assert frame.dtype == np.float32 and frame.shape == (3,)
    np.testing.assert_array_equal(frame, frame_origin(triangles))
    if not ids.size:
        np.testing.assert_array_equal(frame, 0)
    local = local_corners(triangles, frame)

    d = decode(structure)
    slots = stats["references"]
    # (A tree without triangles keeps one unused slot for the engine's gather.)
    assert references.size == max(slots, 1)
    references = references[:slots]
    assert ((references >= 0) & (references < len(ids))).all()
    owner = leaf_of_slots(d, slots)
    count, depth = d["leaf_count"], d["leaf_depth"]
    # The root is cubic and contains every triangle.
    root_lo, root_hi = d["interior_lo"][0], d["interior_hi"][0]
    if ids.size:
        assert (local.min(axis=(0, 1)) >= root_lo).all()
        assert (local.max(axis=(0, 1)) <= root_hi).all()
    # Splitting rule: leaves hold at most k unless at the depth limit.
    assert depth.max() <= limit
    assert ((count <= k) | (depth == limit)).all()
    assert stats["leaves_over_max_depth"] == int((count > k).sum())
    # No triangle referenced twice by one leaf.
    pairs = owner * (len(ids) + 1) + references
    assert np.unique(pairs).size == pairs.size

    # The reference rule, densely: leaf L references t iff t touches L's widened cell.
    rows = np.arange(len(ids)) if sample is None else rng.choice(
        len(ids), min(sample, len(ids)), replace=False)
    want = dense_overlaps(local, d["leaf_lo"], d["leaf_hi"], rows)
    for t, leaves in zip(rows, want, strict=True):
        got = np.sort(owner[references == t])
        np.testing.assert_array_equal(got, leaves, err_msg=f"triangle row {t}")
    if ids.size:
        assert np.unique(references).size == len(ids), "a triangle without a leaf"

    # Statistics, recomputed from the decoded cells.
    interior_count = d["interior_row"].size
    assert stats["interior_cells"] == interior_count == structure["nodes"].shape[0]
    assert stats["leaves"] == count.size
    assert stats["cells"] == stats["nodes"] == interior_count + count.size
    assert stats["empty_leaves"] == int((count == 0).sum())
    assert stats["depth"] == int(depth.max())
    assert stats["references"] == int(count.sum())
    assert stats["references_per_leaf_max"] == int(count.max())
    nonempty = count[count > 0]
    assert stats["references_per_leaf_mean"] == pytest.approx(
        nonempty.mean() if nonempty.size else 0.0)
    assert stats["references_per_triangle"] == pytest.approx(
        references.size / len(ids) if len(ids) else 0.0)
    assert stats["triangles"] == len(ids)
    assert stats["degenerate_skipped"] == len(faces) - len(ids)
    area = half_area(d["interior_lo"], d["interior_hi"])
    leaf_area = half_area(d["leaf_lo"], d["leaf_hi"])
    sah = (0.5 * area.sum() + (leaf_area * count).sum()) / area[0]
    assert stats["sah_cost"] == pytest.approx(sah, rel=1e-9)
    assert stats["bytes"] == structure.nbytes
    return d


# ---------------------------------------------------------------------------------------------
# Builder
# ---------------------------------------------------------------------------------------------


def test_camel_build_is_consistent(camel, camel_octree):
    check_octree(camel_octree, camel.vertices, camel.faces, sample=300,
                 rng=np.random.default_rng(0))
    stats = camel_octree.stats
    assert stats["depth"] == stats["max_depth"] == octree.default_max_depth(len(camel.faces))
    assert stats["triangles"] == len(camel.faces)


def test_camel_build_is_deterministic(camel, camel_octree):
    again = accel.build("octree", camel.vertices, camel.faces)
    for name, array in camel_octree.arrays.items():
        np.testing.assert_array_equal(np.asarray(again[name]), np.asarray(array))


@PROPERTY
@given(
    seed=st.integers(0, 2**32 - 1),
    n=st.integers(1, 150),
    grid=st.booleans(),
    shared=st.booleans(),
    degenerate=st.sampled_from([0.0, 0.1, 0.5]),
    duplicates=st.sampled_from([0.0, 0.2, 0.9]),
    max_leaf_size=st.sampled_from([1, 2, 4, 8, 255]),
    max_depth=st.sampled_from([None, 1, 2, 4, 6]),
)
def test_random_soup_build_is_consistent(seed, n, grid, shared, degenerate, duplicates,
                                         **params):
    vertices, faces = random_mesh(seed, n, grid=grid, shared=shared, degenerate=degenerate,
                                  duplicates=duplicates)
    structure = accel.build("octree", vertices, faces, **params)
    check_octree(structure, vertices, faces, **params)


def test_default_depth_is_floor_log4():
    for n in [0, 1, 3, 4, 5, 15, 16, 17, 200, 69_092, 4**12 - 1, 4**12, 4**40]:
        floor_log4 = (n.bit_length() - 1) // 2 if n else 0
        want = min(octree.MAX_DEPTH_LIMIT, max(1, floor_log4))
        assert octree.default_max_depth(n) == want, n


def test_default_depth_reaches_the_triangles_size():
    """At least ceil(log2 S) levels, S the scene's size over a typical triangle's: exact
    at powers of two, capped at MAX_DEPTH_LIMIT, never below floor(log4 N)."""
    for k in range(1, 30):
        assert octree.default_max_depth(1, 2.0**k) == k
        assert octree.default_max_depth(1, 2.0**k * (1 + 2**-40)) == k + 1
    assert octree.default_max_depth(1, 2.0**60) == octree.MAX_DEPTH_LIMIT
    assert octree.default_max_depth(4**9, 2.0**3) == 9
    sides = np.float64([10, 1, 1])  # three triangles' largest sides, in a box 11 wide
    lo, hi = np.float64([0, 0, 0]), np.float64([11, 1, 1])
    assert octree.size_ratio(sides, lo, hi) == 11.0  # box side 11 over the median side 1
    assert octree.size_ratio(np.zeros(0), None, None) == 1.0


def test_a_small_object_in_a_large_scene_is_subdivided_to_its_triangles():
    """The scene suite's stadium: the camel at the centre of a stadium some 1000 times its
    size. At depth floor(log4 N) = 8 a leaf held 20,010 triangles, more than a leaf
    reference can count beside the references (the build failed); at the triangles' size
    its leaves stay small, and its hits are the BVH's (brute force's own float32 answers
    are off on this scene: tests/test_scenes.py)."""
    from jrt.scenes import scene_mesh

    mesh = scene_mesh("stadium")
    structure = accel.build("octree", mesh.vertices, mesh.faces)
    check_octree(structure, mesh.vertices, mesh.faces, sample=300,
                 rng=np.random.default_rng(0))
    stats = structure.stats
    assert stats["max_depth"] == 18 and stats["references_per_leaf_max"] <= 64, stats
    origins, directions = incoherent_set(mesh.vertices, 2048, seed=5)
    want = as_numpy(jrt.closest_hit(accel.build("bvh", mesh.vertices, mesh.faces), origins,
                                    directions))
    assert (want["triangle"] >= 0).mean() > 0.2
    assert_same_hits(as_numpy(jrt.closest_hit(structure, origins, directions)), want,
                     origins, directions, "octree on the stadium")


def test_depth_limit_leaves_a_big_leaf():
    vertices, faces = chain(-20, 12)
    structure = accel.build("octree", vertices, faces, max_leaf_size=1, max_depth=12)
    check_octree(structure, vertices, faces, max_leaf_size=1, max_depth=12)
    stats = structure.stats
    assert stats["depth"] == 12 and stats["leaves_over_max_depth"] >= 1
    assert stats["references_per_leaf_max"] > 1
    corners = vertices.reshape(-1, 3, 3)
    origins = corners.mean(axis=1)
    origins[:, 2] = corners[:, 1, 0] - corners[:, 0, 0]
    directions = np.tile(np.float32([0, -0.0, -1]), (len(origins), 1))
    brute = accel.build("brute", vertices, faces)
    # (One kernel: each shape compiles anew; the soups and the camel cover them all.)
    got = as_numpy(jrt.closest_hit(structure, origins, directions))
    want = as_numpy(jrt.closest_hit(brute, origins, directions))
    assert_same_hits(got, want, origins, directions, "depth limit")
    assert (got["triangle"] >= 0).mean() > 0.5


@pytest.mark.parametrize("vertex_count", [0, 3])
def test_empty_mesh(vertex_count):
    vertices = np.zeros((vertex_count, 3), np.float32)
    faces = np.zeros((0, 3), np.int32)
    structure = accel.build("octree", vertices, faces)
    check_octree(structure, vertices, faces)
    stats = structure.stats
    # The root is always split: eight empty leaves.
    assert (stats["triangles"], stats["cells"], stats["leaves"], stats["empty_leaves"],
            stats["depth"], stats["references"]) == (0, 9, 8, 8, 1, 0)
    origins = np.float32([[0, 0, -1], [0.5, 0.5, 0.5], [0, 0, 0]])
    directions = np.float32([[0, 0, 1], [1, 0, 0], [0, -1, 0]])
    hits = as_numpy(jrt.closest_hit(structure, origins, directions))
    np.testing.assert_array_equal(hits["triangle"], -1)
    np.testing.assert_array_equal(hits["t"], np.inf)
    np.testing.assert_array_equal(np.asarray(jrt.occluded(structure, origins, directions)),
                                  False)


def test_all_degenerate_mesh():
    vertices = np.float32([[0, 0, 0], [1, 1, 1], [2, 2, 2]])
    faces = np.int32([[0, 1, 2], [0, 0, 1], [2, 2, 2]])
    structure = accel.build("octree", vertices, faces)
    check_octree(structure, vertices, faces)
    assert structure.stats["degenerate_skipped"] == 3 and structure.stats["triangles"] == 0
    hits = as_numpy(jrt.closest_hit(structure, np.float32([[1, 1, 0]]),
                                    np.float32([[0, 0, 1]])))
    assert hits["triangle"][0] == -1


@pytest.mark.parametrize(("count", "max_leaf_size"), [(1, 1), (2, 1), (3, 1), (3, 4)])
def test_tiny_meshes_build_and_hit(count, max_leaf_size):
    vertices, faces = stacked(count)
    structure = accel.build("octree", vertices, faces, max_leaf_size=max_leaf_size)
    check_octree(structure, vertices, faces, max_leaf_size=max_leaf_size)
    if count == 1:
        assert structure.stats["depth"] == 1 and structure.stats["interior_cells"] == 1
    top = count + 1.0
    origins = np.float32([[0.5, 0.5, 0], [0.5, 0.5, top], [0.5, 0.5, 1.5], [0.5, 0.5, 1.5],
                          [9, 9, 0]])
    directions = np.float32([[0, 0, 1], [0, 0, -1], [0, 0, 1], [0, 0, -1], [0, 0, 1]])
    expected_triangle = [0, count - 1, 1 if count > 1 else -1, 0, -1]
    expected_t = [1, 1, 0.5 if count > 1 else np.inf, 0.5, np.inf]
    hits = as_numpy(jrt.closest_hit(structure, origins, directions))
    np.testing.assert_array_equal(hits["triangle"], expected_triangle)
    np.testing.assert_array_equal(hits["t"], np.float32(expected_t))
    occ = np.asarray(jrt.occluded(structure, origins, directions))
    np.testing.assert_array_equal(occ, np.asarray(expected_triangle) >= 0)


def test_degenerate_faces_are_skipped():
    vertices, faces = stacked(3)
    extra = np.float32([[0.5, 0.5, 0.5], [1.5, 1.5, 0.5], [2.5, 2.5, 0.5]])
    vertices = np.concatenate([vertices, extra])
    faces = np.concatenate([np.int32([[9, 10, 11], [0, 0, 1]]), faces,
                            np.int32([[9, 9, 9], [3, 4, 3]])])
    structure = accel.build("octree", vertices, faces, max_leaf_size=1)
    check_octree(structure, vertices, faces, max_leaf_size=1)
    assert structure.stats["degenerate_skipped"] == 4
    hits = as_numpy(jrt.closest_hit(structure, np.float32([[0.5, 0.5, 0]]),
                                    np.float32([[0, 0, 1]])))
    assert hits["triangle"][0] == 2 and hits["t"][0] == 1


BAD_PARAMS = [
    ("max_leaf_size", 0), ("max_leaf_size", -1), ("max_leaf_size", 256),
    ("max_leaf_size", 2.5), ("max_leaf_size", "4"), ("max_leaf_size", None),
    ("max_leaf_size", True), ("max_depth", 0), ("max_depth", -2),
    ("max_depth", octree.MAX_DEPTH_LIMIT + 1), ("max_depth", 4.0), ("max_depth", "8"),
    ("max_depth", False),
]


@pytest.mark.parametrize(("name", "value"), BAD_PARAMS)
def test_bad_parameters_raise(name, value):
    vertices, faces = stacked(2)
    with pytest.raises(ValueError, match=f"octree: {name} must be"):
        accel.build("octree", vertices, faces, **{name: value})


def test_unknown_parameter_raises():
    vertices, faces = stacked(2)
    with pytest.raises(TypeError):
        accel.build("octree", vertices, faces, bins=16)


@pytest.mark.parametrize(("name", "value"), [
    ("max_leaf_size", 1), ("max_leaf_size", 255), ("max_depth", 1),
    ("max_depth", octree.MAX_DEPTH_LIMIT), ("max_leaf_size", np.int64(3)),
])
def test_parameter_bounds_are_accepted(name, value):
    vertices, faces = random_mesh(1, 40, grid=False, shared=False, degenerate=0, duplicates=0)
    structure = accel.build("octree", vertices, faces, **{name: value})
    check_octree(structure, vertices, faces, **{name: value})


def test_non_finite_vertices_raise():
    vertices, faces = stacked(2)
    vertices[1, 0] = np.nan
    with pytest.raises(ValueError, match="finite"):
        accel.build("octree", vertices, faces)


# ---------------------------------------------------------------------------------------------
# The camel: closest hit, occluded, counters
# ---------------------------------------------------------------------------------------------


def test_camel_counters(camel_octree, camel_rays, brute_hits):
    origins, directions = camel_rays["incoherent"]
    hits, count = jrt.closest_hit(camel_octree, origins, directions, counters=True)
    got = as_numpy(hits)
    assert_same_hits(got, brute_hits("watertight", "incoherent"), origins, directions,
                     "counters")
    hit = got["triangle"] >= 0
    steps, tests, leaves = (np.asarray(a) for a in count)
    stats = camel_octree.stats
    assert (steps >= 1).all() and (steps >= leaves).all(), "every leaf costs a step"
    assert (tests[hit] >= 1).all() and (leaves <= tests).all()
    assert (tests <= stats["references"]).all()
    assert (leaves <= stats["leaves"] - stats["empty_leaves"]).all()
    assert tests.mean() < 0.01 * stats["triangles"]
    mask, occ = jrt.occluded(camel_octree, origins, directions, counters=True)
    np.testing.assert_array_equal(np.asarray(mask), hit)
    # Any-hit follows the closest-hit traversal up to its first hit, then stops.
    for a, b in zip(occ, count, strict=True):
        assert (np.asarray(a) <= np.asarray(b)).all()


# ---------------------------------------------------------------------------------------------
# Edge cases of the parametric traversal
# ---------------------------------------------------------------------------------------------


def test_a_lone_ray_that_misses_the_root():
    """One lane whose interval is empty (t0 > t1): the step's shared computation is then
    skipped, and its all-zero answer must read as "no child" (this once looped forever)."""
    vertices, faces = stacked(3)
    structure = accel.build("octree", vertices, faces, max_leaf_size=1)
    for o, d in [([9, 9, 0], [0, 0, 1]), ([0.5, 0.5, -1], [0, 0, -1])]:
        hits = as_numpy(jrt.closest_hit(structure, np.float32([o]), np.float32([d])))
        assert hits["triangle"][0] == -1
        assert not np.asarray(jrt.occluded(structure, np.float32([o]), np.float32([d])))[0]


def grid_mesh():
    """Unit squares (two triangles each) tiling the planes z = 0, 1, 2, 3, 4 over
    [0, 4]^2: the root cube is [0, 4]^3, so its mid-planes and many of its cells'
    faces fall on the squares' edges and on the layers."""
    quads = []
    for z in range(5):
        for x in range(4):
            for y in range(4):
                a, b, c, e = [x, y, z], [x + 1, y, z], [x + 1, y + 1, z], [x, y + 1, z]
                quads += [[a, b, c], [a, c, e]]
    corners = np.float32(quads)
    return corners.reshape(-1, 3), np.arange(corners.shape[0] * 3, dtype=np.int32).reshape(-1, 3)


@pytest.mark.parametrize("max_leaf_size", [1, 4])
def test_rays_on_cell_faces_and_centres(max_leaf_size):
    """Axis-parallel rays (±0.0 components) lying in mid-planes, through cell centres and
    along cell edges, from origins on cell faces and at cell corners."""
    vertices, faces = grid_mesh()
    structure = accel.build("octree", vertices, faces, max_leaf_size=max_leaf_size,
                            max_depth=4)
    d = check_octree(structure, vertices, faces, max_leaf_size=max_leaf_size, max_depth=4)
    centre = d["interior_lo"][0] + (d["interior_hi"][0] - d["interior_lo"][0]) / 2
    assert (centre + structure["frame"] == 2).all()
    values = np.float32([0, 0.5, 1, 1.5, 2, 2.25, 3, 3.5, 4])
    rng = np.random.default_rng(3)
    n = 512
    origins = values[rng.integers(0, values.size, (n, 3))]
    directions = signed_zeros(rng, (n, 3))
    axis = rng.integers(0, 3, n)
    directions[np.arange(n), axis] = np.where(rng.random(n) < 0.5, 1, -1)
    # Some start outside the cube, some exactly on its faces.
    outside = rng.random(n) < 0.3
    origins[outside, axis[outside]] = np.where(directions[outside, axis[outside]] > 0, -1, 5)
    brute = accel.build("brute", vertices, faces)
    for kernel in KERNELS:
        want = as_numpy(jrt.closest_hit(brute, origins, directions, kernel=kernel))
        got = as_numpy(jrt.closest_hit(structure, origins, directions, kernel=kernel))
        assert_same_hits(got, want, origins, directions, kernel)
        assert (want["triangle"] >= 0).mean() > 0.2


# ---------------------------------------------------------------------------------------------
# Random soups (hypothesis)
# ---------------------------------------------------------------------------------------------

NODE_CAP = 8192
REFERENCE_CAP = 1 << 16
LEAF_BITS = 8  # leaves of up to 255 references
PLANE_TRIANGLES = 40


def fits(structure: Structure) -> bool:
    return (structure["nodes"].shape[0] <= NODE_CAP
            and structure["references"].size <= REFERENCE_CAP)


def fixed_shape(structure: Structure, *, rows=NODE_CAP, slots=REFERENCE_CAP, triangles=CAP,
                leaf_bits=LEAF_BITS) -> Structure:
    """The same tree with ``rows`` node rows, ``slots`` reference slots, ``triangles``
    triangle rows and leaf references of ``leaf_bits`` (unreferenced zero rows and slots
    as padding), so that trees of one padded shape share every compiled kernel."""
    nodes = np.asarray(structure["nodes"])
    m, r, t = nodes.shape[0], structure["references"].size, structure.num_triangles
    assert m <= rows and r <= slots
    bits = structure.layout_value("leaf_bits")
    assert bits <= leaf_bits and t <= triangles
    refs = nodes.view(np.int32)[:, 4:12]
    code = ~refs
    padded = np.zeros((rows, 12), np.float32)
    padded[:m] = nodes
    padded.view(np.int32)[:m, 4:12] = np.where(
        refs >= 0, refs, ~(((code >> bits) << leaf_bits) | (code & ((1 << bits) - 1))))
    references = np.zeros(slots, np.int32)
    references[:r] = structure["references"]
    corners = np.zeros((triangles, 3, 3), np.float32)
    corners[:t] = structure["triangles"]
    ids = np.full(triangles, -1, np.int32)
    ids[:t] = structure["triangle_ids"]
    return Structure(kind="octree", arrays={"nodes": padded, "references": references,
                                            "triangles": corners, "triangle_ids": ids,
                                            "frame": structure["frame"]},
                     layout=(("leaf_bits", leaf_bits),), stats=structure.stats)


def plane_values(structure) -> list[np.ndarray]:
    """Per axis: the world coordinates of the tree's mid-planes and of the root cube's
    faces (stored in the local frame). A plane ``c`` is at ``frame + c``; where that sum
    is not a float32, the two float32 values around it stand for it (a point there is
    moved by ``o - frame`` to within an ulp of the plane, on either side)."""
    nodes = np.asarray(structure["nodes"])
    frame = np.asarray(structure["frame"], np.float64)
    centre, half = nodes[0, :3], nodes[0, 3]
    out = []
    for a in range(3):
        local = np.concatenate([nodes[:, a], [centre[a] - half, centre[a] + half]])
        world = local.astype(np.float64) + frame[a]
        out.append(np.unique(np.concatenate([float32_down(world), float32_up(world)])))
    return out


def in_planes(rng, vertices, planes, count):
    """``count`` axis-aligned flat triangles lying exactly in mid-planes (or root faces)
    inside the soup's bounding box, their other coordinates from the soup's vertices."""
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    tri = vertices[rng.integers(0, len(vertices), (count, 3))].copy()
    for i in range(count):
        axis = rng.integers(0, 3)
        inside = planes[axis][(planes[axis] >= lo[axis]) & (planes[axis] <= hi[axis])]
        if inside.size:
            tri[i, :, axis] = inside[rng.integers(0, inside.size)]
    return tri.reshape(-1, 3)


def plane_rays(rng, vertices, planes, centres, origins, directions):
    """Half the rays rewritten to start exactly on the tree's planes: at cell centres, on
    a mid-plane with the ray lying in it (a ±0.0 component), on root cube faces, axis-
    parallel with ±0.0 components, or aimed at a vertex."""
    n = len(origins) // 2
    rows = rng.choice(len(origins), n, replace=False)
    o, d = origins.copy(), directions.copy()
    kind = rng.integers(0, 4, n)
    for row, k in zip(rows, kind, strict=True):
        if k == 0:  # at a cell centre
            o[row] = centres[rng.integers(0, len(centres))]
        else:  # each coordinate a plane value
            o[row] = [planes[a][rng.integers(0, planes[a].size)] for a in range(3)]
        if k == 1:  # lying in the mid-plane of one axis
            d[row] = rng.normal(size=3)
            d[row] /= np.linalg.norm(d[row])
            d[row, rng.integers(0, 3)] = signed_zeros(rng, 1)[0]
        elif k == 2:  # axis-parallel
            d[row] = signed_zeros(rng, 3)
            d[row, rng.integers(0, 3)] = 1 if rng.random() < 0.5 else -1
        else:  # at a vertex
            v = vertices[rng.integers(0, len(vertices))].astype(np.float64) - o[row]
            norm = np.linalg.norm(v)
            d[row] = v / norm if norm > 0 else [0, 0, 1]
    return o, d.astype(np.float32)


@st.composite
def soups(draw):
    """(vertices, faces, build parameters, origins, directions, rng) of one example."""
    seed = draw(st.integers(0, 2**32 - 1))
    n = draw(st.integers(10, CAP - PLANE_TRIANGLES))
    grid = draw(st.booleans())
    flat = draw(st.sampled_from([0.0, 0.3, 1.0]))
    duplicates = draw(st.sampled_from([0.0, 0.1, 0.5]))
    shared = draw(st.sampled_from([0.0, 0.5, 2.0]))
    offset = draw(st.sampled_from([0.0, 0.0, 100.0, -3000.0]))
    params = {"max_leaf_size": draw(st.sampled_from([1, 2, 4, 8])),
              "max_depth": draw(st.sampled_from([None, 3, 5, 5]))}
    rng = np.random.default_rng(seed)
    vertices, faces = soup(rng, n, grid=grid, flat=flat, duplicates=duplicates, shared=shared)
    vertices = (vertices + np.float32(offset)).astype(np.float32)
    # Triangles in the planes the tree splits at (the root cube depends only on the
    # bounding box, which these stay inside, so the planes are the final tree's too).
    first = octree.build(vertices, faces, **params)
    extra = in_planes(rng, vertices, plane_values(first), PLANE_TRIANGLES)
    vertices = np.concatenate([vertices, extra.astype(np.float32)])
    faces = np.arange(len(vertices), dtype=np.int32).reshape(-1, 3)
    origins, directions = rays(rng, vertices, faces)
    structure = octree.build(vertices, faces, **params)
    centres = np.asarray(structure["nodes"])[:, :3].astype(np.float64) + structure["frame"]
    origins, directions = plane_rays(rng, vertices, plane_values(structure),
                                     centres.astype(np.float32), origins, directions)
    return vertices, faces, params, structure, origins, directions, rng


def soup_structures(case):
    vertices, faces, params, structure, origins, directions, rng = case
    assume(fits(structure))
    unpadded = accel.build("brute", vertices, faces)
    scale = float(np.abs(vertices).max()) * 4
    return (params, unpadded, fixed_shape(structure), fixed_shape_brute(unpadded), scale,
            origins, directions, rng)


@PROPERTY
@given(case=soups())
def test_soup_closest_hit_matches_brute(case):
    params, unpadded, tree, brute, scale, origins, directions, rng = soup_structures(case)
    check_closest_hit_matches_brute(tree, brute, unpadded, origins, directions, rng, scale,
                                    f"octree {params}")


@PROPERTY
@given(case=soups())
def test_soup_occluded_matches_brute(case):
    params, unpadded, tree, brute, scale, origins, directions, rng = soup_structures(case)
    check_occluded_matches_brute(tree, brute, unpadded, origins, directions, rng, scale,
                                 f"octree {params}")


def test_stack_overflow_raises():
    rng = np.random.default_rng(11)
    vertices, faces = soup(rng, CAP, grid=False, flat=0.3, duplicates=0.0, shared=0.5)
    origins, directions = rays(rng, vertices, faces)
    structure = accel.build("octree", vertices, faces, max_leaf_size=1, max_depth=6)
    assert structure.stats["depth"] >= 4
    tree = fixed_shape(structure)
    with pytest.raises(StackOverflowError, match="stack_size"):
        jrt.closest_hit(tree, origins, directions, lanes=64, stack_size=1)
    with pytest.raises(StackOverflowError):
        jrt.occluded(tree, origins, directions, lanes=32, stack_size=1)
    got = as_numpy(jrt.closest_hit(tree, origins, directions, lanes=64))
    brute = fixed_shape_brute(accel.build("brute", vertices, faces))
    assert_same_hits(got, as_numpy(jrt.closest_hit(brute, origins, directions)), origins,
                     directions, "default stack")


# ---------------------------------------------------------------------------------------------
# Far from the origin, and at other scales: the local frame
# ---------------------------------------------------------------------------------------------

#: The camel moved and scaled, in float64 (then rounded to float32). The moves are
#: integers, so the moved float32 mesh moves back exactly (``far_camels``).
FAR = {
    "moved 1e3": (np.float64([1000, -700, 1300]), 1.0),
    "moved 1e5": (np.float64([100_000, -70_000, 130_000]), 1.0),
    "scaled 1e-4": (np.zeros(3), 1e-4),
    "scaled 1e4": (np.zeros(3), 1e4),
}
FAR_RAYS = 1000


def rays_at_vertices(vertices, source, count, seed):
    """``count`` rays from the point ``source`` aimed at random vertices (they meet edges
    and corners)."""
    v = np.asarray(vertices, np.float64)
    rng = np.random.default_rng(seed)
    origins = np.tile(np.asarray(source, np.float32), (count, 1))
    directions = v[rng.integers(0, len(v), count)] - origins
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    return origins, directions.astype(np.float32)


def aimed_rays(vertices, count, seed):
    """``count`` rays: half from a sphere around the mesh (``incoherent_set``), half from
    a point inside its bounding box aimed at its vertices."""
    v = np.asarray(vertices, np.float64)
    lo, hi = v.min(axis=0), v.max(axis=0)
    source = lo + np.random.default_rng(seed).uniform(0.3, 0.7, 3) * (hi - lo)
    o1, d1 = incoherent_set(vertices, count - count // 2, seed=seed)
    o2, d2 = rays_at_vertices(vertices, source, count // 2, seed)
    return np.concatenate([o1, o2]), np.concatenate([d1, d2])


#: The two-camel scene's depth limit (see test_two_camels_far_apart_match_brute).
TWO_CAMELS_DEPTH = 14


def two_camels(camel):
    """Two camels 1e3 apart, both moved by FAR["moved 1e3"]: vertices, faces."""
    v = camel.vertices.astype(np.float64) + FAR["moved 1e3"][0]
    first = v.astype(np.float32)
    second = (v + [1000.0, 0.0, 0.0]).astype(np.float32)
    return (np.concatenate([first, second]),
            np.concatenate([camel.faces, camel.faces + len(v)]))


@pytest.fixture(scope="module")
def far_camels(camel19k):
    """name -> (vertices, faces, octree, the octree padded, brute force padded, origins,
    directions) for the camel at the origin, every case of FAR and "two camels". The
    padded structures share one shape, so each kernel compiles once for all of them. A
    moved mesh is also built moved back (exactly): "<name> back" (no rays)."""
    faces = camel19k.faces
    base = camel19k.vertices.astype(np.float64)
    meshes = {"origin": (camel19k.vertices, faces)}
    for name, (move, scale) in FAR.items():
        meshes[name] = ((base * scale + move).astype(np.float32), faces)
        if scale == 1.0:
            back = meshes[name][0].astype(np.float64) - move
            assert (back.astype(np.float32) == back).all()
            meshes[name + " back"] = (back.astype(np.float32), faces)
    meshes["two camels"] = two_camels(camel19k)
    trees = {name: octree.build(v, f, max_depth=TWO_CAMELS_DEPTH if name == "two camels"
                                else None) for name, (v, f) in meshes.items()}
    rows = max(t["nodes"].shape[0] for t in trees.values())
    slots = max(t["references"].size for t in trees.values())
    bits = max(t.layout_value("leaf_bits") for t in trees.values())
    t = max(len(f) for _, f in meshes.values())
    out = {}
    for seed, (name, (v, f)) in enumerate(meshes.items()):
        tree = trees[name]
        brute = accel.build("brute", v, f)
        corners = np.zeros((t, 3, 3), np.float32)
        corners[:brute.num_triangles] = brute["triangles"]
        ids = np.arange(t, dtype=np.int32) + 10 * t  # padding rows: zero, never hit
        ids[:brute.num_triangles] = brute["triangle_ids"]
        padded_brute = Structure(kind="brute",
                                 arrays={"triangles": corners, "triangle_ids": ids})
        if name == "two camels":  # around each, and from each at the other's vertices
            half = len(v) // 2
            first, second = v[:half], v[half:]
            parts = [aimed_rays(first, FAR_RAYS * 3 // 10, seed),
                     aimed_rays(second, FAR_RAYS * 3 // 10, seed + 1),
                     rays_at_vertices(second, first.mean(axis=0), FAR_RAYS // 5, seed + 2),
                     rays_at_vertices(first, second.mean(axis=0), FAR_RAYS // 5, seed + 3)]
            rays = (np.concatenate([p[0] for p in parts]),
                    np.concatenate([p[1] for p in parts]))
        else:
            rays = aimed_rays(v, FAR_RAYS, seed)
        out[name] = (v, f, tree, fixed_shape(tree, rows=rows, slots=slots, triangles=t,
                                             leaf_bits=bits), padded_brute, *rays)
    return out


def test_far_camels_build_the_same_references(far_camels):
    """Moved 1e5 away, the margins in world coordinates (2^-16 of 1.3e5 = 2.0) would
    swallow the camel (1 across) whole in every cell; in the local frame each build
    references about what it does at the origin. A move rounds the vertices to float32
    at the new magnitude (by 2^-7 at 1e5, the size of the smaller triangles, a third of
    which become degenerate; most vertices then lie on the tree's planes), so it is
    compared with the same float32 mesh moved back exactly; a scale with the origin's
    mesh. (In world coordinates the camel moved by 1e3 failed to build: 29M references.)"""
    origin = far_camels["origin"][2].stats
    for name, (_, scale) in FAR.items():
        v, f, tree = far_camels[name][:3]
        stats = tree.stats
        check_octree(tree, v, f, sample=50, rng=np.random.default_rng(1))
        assert (np.abs(tree["frame"]) > 0).all() == (scale == 1.0), name
        same = far_camels[name + " back"][2] if scale == 1.0 else far_camels["origin"][2]
        assert stats["triangles"] == same.stats["triangles"], name
        assert stats["depth"] == same.stats["depth"], name
        # (Within 10 %: the planes of the two frames round differently, and at 1e5 most
        # vertices lie on a plane of one tree or the other.)
        for key in ("references", "leaves", "interior_cells"):
            assert stats[key] == pytest.approx(same.stats[key], rel=0.1), (name, key)
        assert stats["references"] <= 1.05 * origin["references"], name
        # The same root cube, scaled.
        assert tree["nodes"][0, 3] == pytest.approx(same["nodes"][0, 3] * scale, rel=1e-5)


def far_hits_match_brute(far_camels, name, kernel):
    _, _, _, tree, brute, origins, directions = far_camels[name]
    if kernel in POSITION_DEPENDENT_KERNELS:
        # Its margins grow with |frame| (jrt.engine.margin_pad): 2^-16 of 2.6e5 at 1e5,
        # wider than the camel, so there every ray tests every reference. A quarter of
        # the rays (the same count in every case: one compiled shape).
        origins, directions = origins[::4], directions[::4]
    want = as_numpy(jrt.closest_hit(brute, origins, directions, kernel=kernel))
    got = as_numpy(jrt.closest_hit(tree, origins, directions, kernel=kernel))
    assert (want["triangle"] >= 0).mean() > 0.3, name
    assert_same_hits(got, want, origins, directions, f"octree {name} {kernel}")


#: Kernels of the far tests: watertight runs on the far camels under every structure in
#: tests/test_anywhere.py; the plane kernel's margins grow with the frame's magnitude
#: (jrt.engine.margin_pad), so far away every ray tests every reference (slow, not new).
FAR_KERNELS = ("moller_trumbore",)


@pytest.mark.parametrize("kernel", FAR_KERNELS)
def test_far_camels_closest_hit_matches_brute(far_camels, kernel):
    """FAR_RAYS rays per case (half from around the camel, half from inside its box aimed
    at its vertices): brute force's hits, bit for bit, wherever the camel sits."""
    for name in ["origin", *FAR]:
        far_hits_match_brute(far_camels, name, kernel)


@pytest.mark.parametrize("kernel", FAR_KERNELS)
def test_two_camels_far_apart_match_brute(far_camels, kernel):
    """Two camels 1e3 apart, moved by (1000, -700, 1300): the scene is 1e3 across, its
    cells at depth 14 a sixteenth of a camel (1e3 / 2^15), each widened by 2^-16 of its
    own size and of its triangles' (not of the scene's 1e3). Rays around each camel, and
    from each camel aimed at the other's vertices (t about 1e3)."""
    v, f, tree = far_camels["two camels"][:3]
    assert tree.stats["depth"] == TWO_CAMELS_DEPTH
    assert tree.stats["references"] < 3 * len(f)
    np.testing.assert_array_equal(tree["frame"], v.min(axis=0) * [1, 0, 1]
                                  + v.max(axis=0) * [0, 1, 0])  # the corner nearest 0
    far_hits_match_brute(far_camels, "two camels", kernel)
