"""The BVH builder (``accel.build("bvh", ...)``): the arrays against their documented layout.

Everything here is recomputed from the arrays alone (the layout in ``accel/bvh.py``'s
docstring) and compared with what the builder reports in ``stats``:

- the node rows decode to a tree: row 0 the root, every other interior row referenced
  exactly once and only by an earlier row (breadth-first, so no cycle), every triangle row
  in exactly one leaf; a node of ``width`` slots has at least two children, and fewer
  than ``width`` only if all are leaves (the greedy collapse of a binary tree), and the
  children count is that of a binary tree collapsed (sum of children - 1 = leaves - 1);
- every child box, decoded from its bytes in its parent's frame (origin + q * scale in
  float32), contains the exact float32 bound of the triangles of its subtree and lies
  within one quantisation step of it; the frame is the union of the children's boxes and
  its scale the smallest power of two covering it in 255 steps;
- ``frame`` is the point of the triangles' box nearest the origin, and every box is in that frame
  (the triangles' exact boxes minus ``frame``, rounded outward to float32);
- ``triangle_ids`` is a permutation of the non-degenerate faces and ``triangles`` holds
  their corners;
- the counts, depth, leaf sizes, SAH cost and bytes of ``stats``.

Speed and scaling are measured by the benchmarks, never by timed tests.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import accel
import jrt
from jrt.trace import as_numpy

STAT_KEYS = {
    "build_seconds", "method", "bins", "max_leaf_size", "width", "binary_depth", "triangles",
    "degenerate_skipped",
    "nodes", "interior_nodes", "leaves", "depth", "triangles_per_leaf_mean",
    "triangles_per_leaf_max", "leaves_over_max_depth", "sah_cost", "bytes",
}
DEFAULTS = {"method": "sah", "bins": 16, "max_leaf_size": 4, "traversal_cost": 0.5,
            "intersection_cost": 1.0, "width": 4}
PROPERTY = settings(max_examples=100, deadline=None, database=None)


# ---------------------------------------------------------------------------------------------
# An independent decoder of the layout
# ---------------------------------------------------------------------------------------------


def expected_ids(vertices, faces) -> np.ndarray:
    """Faces of non-zero area, from the float32 corners evaluated in float64."""
    corners = np.asarray(vertices, np.float32)[np.asarray(faces)].astype(np.float64)
    if len(corners) == 0:
        return np.zeros(0, np.int64)
    normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    return np.flatnonzero(np.any(normal != 0, axis=1))


def half_area(lo, hi) -> np.ndarray:
    """Half the surface area of boxes [..., 3], in float64."""
    e = np.maximum(np.asarray(hi, np.float64) - np.asarray(lo, np.float64), 0.0)
    return e[..., 0] * e[..., 1] + e[..., 1] * e[..., 2] + e[..., 2] * e[..., 0]


def dequantise(origin, scale, q) -> np.ndarray:
    """The documented decode of bound bytes: origin + q * scale in float32 (q * scale exact)."""
    return (origin + np.asarray(q).astype(np.float32) * scale).astype(np.float32)


def decode(structure) -> dict:
    """Decode the node rows into a tree, asserting its shape on the way.

    Returns per (row, slot) of every child reference: ``is_node`` (an interior row),
    ``boxes`` [M, W, 2, 3] as stored, and the subtree's bounds and triangle count computed
    from the triangles; per leaf (empty slots included, count 0): first row, count, depth,
    row and slot; ``parent`` [M, 2] (row, slot) of every row but the root.
    """
    nodes = np.asarray(structure["nodes"])
    triangles = np.asarray(structure["triangles"])
    frame = np.asarray(structure["frame"])
    leaf_bits = structure.layout_value("leaf_bits")
    width = structure.layout_value("width")
    bound_words = -(-6 * width // 4)  # one byte a bound, six a child
    ref_col = 6 + bound_words  # after origin (3 words), scale (3) and the bounds
    row = -(-(ref_col + width) // 16) * 16  # whole 64-byte lines
    assert nodes.dtype == np.int32 and nodes.ndim == 2 and nodes.shape[1] == row
    assert nodes.shape[0] >= 1
    np.testing.assert_array_equal(nodes[:, ref_col + width:], 0)  # padding
    unused = np.ascontiguousarray(nodes[:, 6:ref_col]).view(np.uint8)[:, 6 * width:]
    np.testing.assert_array_equal(unused, 0)
    refs = nodes[:, ref_col:ref_col + width].astype(np.int64)
    origin = np.ascontiguousarray(nodes[:, 0:3]).view(np.float32)
    scale = np.ascontiguousarray(nodes[:, 3:6]).view(np.float32)
    # Little-endian bytes, field-major: byte f * W + c is field f of child c.
    q = np.ascontiguousarray(nodes[:, 6:ref_col]).view("<u1")[:, :6 * width]
    q = q.reshape(-1, 6, width).transpose(0, 2, 1).reshape(-1, width, 2, 3)  # [m, W, 2, 3]
    boxes = dequantise(origin[:, None, None, :], scale[:, None, None, :], q)
    m, t_count = nodes.shape[0], triangles.shape[0]

    # Interior references: every row but the root referenced exactly once, by an earlier
    # row (breadth first), hence reachable from the root and without cycles.
    is_node = refs >= 0
    parent_row, parent_slot = np.nonzero(is_node)
    child = refs[is_node]
    assert np.all((parent_row < child) & (child < m)), "a reference to an earlier row"
    np.testing.assert_array_equal(np.bincount(child, minlength=m), [0] + [1] * (m - 1))
    parent = np.zeros((m, 2), np.int64)  # (row, slot)
    parent[child] = np.stack([parent_row, parent_slot], axis=1)
    depth = np.zeros(m, np.int64)
    for _ in range(m):  # at most the tree's depth rounds
        new = depth.copy()
        new[child] = depth[parent_row] + 1
        if np.array_equal(new, depth):
            break
        depth = new

    # Leaves: every triangle row in exactly one of them.
    leaf_row, leaf_slot = np.nonzero(~is_node)
    code = ~refs[~is_node]
    first, count = code >> leaf_bits, code & ((1 << leaf_bits) - 1)
    assert np.all((first >= 0) & (first + count <= t_count))
    cover = np.zeros(t_count + 1, np.int64)
    np.add.at(cover, first, 1)
    np.add.at(cover, first + count, -1)
    np.testing.assert_array_equal(np.cumsum(cover)[:t_count], 1)

    # Subtree bounds and counts from the triangles, deepest rows first.
    lo = np.full((m, width, 3), np.inf, np.float32)
    hi = np.full((m, width, 3), -np.inf, np.float32)
    below = np.zeros((m, width), np.int64)
    full = count > 0
    if full.any():
        order = np.argsort(first[full])  # non-empty leaves tile the rows in this order
        starts = first[full][order]
        rows, slots = leaf_row[full][order], leaf_slot[full][order]
        # Each triangle's exact box in the local frame, rounded outward to float32.
        local = triangles.astype(np.float64) - frame.astype(np.float64)
        tri_lo, tri_hi = local.min(axis=1), local.max(axis=1)
        lo32, hi32 = tri_lo.astype(np.float32), tri_hi.astype(np.float32)
        lo32 = np.where(lo32 > tri_lo, np.nextafter(lo32, np.float32(-np.inf)), lo32)
        hi32 = np.where(hi32 < tri_hi, np.nextafter(hi32, np.float32(np.inf)), hi32)
        lo[rows, slots] = np.minimum.reduceat(lo32, starts)
        hi[rows, slots] = np.maximum.reduceat(hi32, starts)
    below[leaf_row, leaf_slot] = count
    for d in range(int(depth.max()), 0, -1):
        rows = np.flatnonzero(depth == d)
        p, ps = parent[rows, 0], parent[rows, 1]
        lo[p, ps] = lo[rows].min(axis=1)
        hi[p, ps] = hi[rows].max(axis=1)
        below[p, ps] = below[rows].sum(axis=1)
    return {"refs": refs, "is_node": is_node, "boxes": boxes, "width": width, "q": q,
            "origin": origin, "scale": scale,
            "lo": lo, "hi": hi, "below": below, "parent": parent, "leaf_bits": leaf_bits,
            "leaf_first": first, "leaf_count": count, "leaf_depth": depth[leaf_row] + 1,
            "leaf_row": leaf_row, "leaf_slot": leaf_slot}


def check_bvh(structure, vertices, faces, **params):
    """Every documented property of a build, recomputed from its arrays."""
    params = {**DEFAULTS, **params}
    vertices = np.asarray(vertices, np.float32)
    faces = np.asarray(faces)
    assert structure.kind == "bvh"
    assert set(structure.arrays) == {"nodes", "triangles", "triangle_ids", "frame"}
    stats = structure.stats
    assert set(stats) == STAT_KEYS
    nodes, triangles, ids = (np.asarray(structure[k]) for k in
                             ("nodes", "triangles", "triangle_ids"))
    assert triangles.dtype == np.float32 and ids.dtype == np.int32
    # The local frame: the point of the triangles' bounding box nearest the origin.
    corners = triangles.reshape(-1, 3)
    expected_frame = (np.minimum(np.maximum(0, corners.min(axis=0)), corners.max(axis=0))
                      if len(corners) else np.zeros(3)).astype(np.float32)
    np.testing.assert_array_equal(structure["frame"], expected_frame)

    # The triangles: a permutation of the non-degenerate faces, with their corners.
    keep = expected_ids(vertices, faces)
    t_count = len(keep)
    assert triangles.shape == (t_count, 3, 3) and ids.shape == (t_count,)
    np.testing.assert_array_equal(np.sort(ids), keep)
    np.testing.assert_array_equal(triangles, vertices[faces[ids]].reshape(-1, 3, 3))
    assert stats["triangles"] == t_count == structure.num_triangles
    assert stats["degenerate_skipped"] == len(faces) - t_count

    tree = decode(structure)
    counts, boxes, width = tree["leaf_count"], tree["boxes"], tree["width"]
    assert width == params["width"] == stats["width"]
    filled = tree["refs"] != ~0
    children = filled.sum(axis=1)
    # A mesh that is one leaf: one row, child 0 the leaf (of no triangle for an empty
    # mesh, which is the empty slot's code), the other slots empty.
    root_is_leaf = nodes.shape[0] == 1 and children[0] <= 1
    if root_is_leaf:
        assert int(tree["refs"][0, 0]) < 0 and filled[0, 0] == (t_count > 0)
        assert t_count <= params["max_leaf_size"]
        assert (tree["q"][0, 1:, 0] == 255).all() and (tree["q"][0, 1:, 1] == 0).all()
        np.testing.assert_array_equal(counts, [t_count] + [0] * (width - 1))
        interior, n_leaves, depth = 0, 1, 0
        real = counts[:1]
    else:
        # The greedy collapse: 2 to W children, fewer than W only when all are leaves.
        assert np.all(children >= 2)
        assert np.all((children == width) | ~(tree["is_node"].any(axis=1)))
        # Filled slots first; empty slots are the empty leaf with an inverted box.
        assert np.all(np.sort(~filled, axis=1, kind="stable") == ~filled)
        assert (tree["q"][~filled][:, 0] == 255).all() and (tree["q"][~filled][:, 1] == 0).all()
        real = counts[filled[tree["leaf_row"], tree["leaf_slot"]]]
        assert (real >= 1).all(), "an empty leaf in a tree with interior nodes"
        interior, n_leaves = nodes.shape[0], len(real)
        # A binary tree of n leaves has n - 1 interior nodes; a wide node of c children
        # stands for c - 1 of them.
        assert (children - 1).sum() == n_leaves - 1
        depth = int(tree["leaf_depth"].max())
    assert stats["interior_nodes"] == interior
    assert stats["leaves"] == n_leaves
    assert stats["nodes"] == interior + n_leaves
    assert stats["depth"] == depth
    assert depth <= stats["binary_depth"]
    if width == 2:
        assert stats["binary_depth"] == depth
    assert stats["triangles_per_leaf_max"] == int(real.max())
    assert stats["triangles_per_leaf_mean"] == pytest.approx(t_count / n_leaves, rel=1e-12)
    assert int(real.max()) < 2 ** tree["leaf_bits"]
    if stats["leaves_over_max_depth"] == 0:
        assert (real <= params["max_leaf_size"]).all()
    else:
        assert stats["binary_depth"] >= 64  # only the depth limit may leave a bigger leaf

    # Boxes: each contains the exact float32 bounds of its subtree's triangles, within one
    # quantisation step on each side; an empty slot's is inverted (lower 255, upper 0).
    empty = tree["below"] == 0
    np.testing.assert_array_equal(empty, ~filled)
    q, scale, origin = tree["q"], tree["scale"], tree["origin"]
    assert (q[empty][:, 0] == 255).all() and (q[empty][:, 1] == 0).all()
    exact = np.stack([tree["lo"], tree["hi"]], axis=2)  # [m, W, 2, 3]
    assert (boxes[~empty][:, 0] <= exact[~empty][:, 0]).all()
    assert (boxes[~empty][:, 1] >= exact[~empty][:, 1]).all()
    # One step tighter on either side no longer contains the exact box.
    frame_origin = np.broadcast_to(origin[:, None], q.shape[:2] + (3,))[~empty]
    frame_scale = np.broadcast_to(scale[:, None], q.shape[:2] + (3,))[~empty]
    q_lo, q_hi = q[~empty][:, 0].astype(np.int64), q[~empty][:, 1].astype(np.int64)
    tighter_lo = dequantise(frame_origin, frame_scale, np.minimum(q_lo + 1, 255))
    tighter_hi = dequantise(frame_origin, frame_scale, np.maximum(q_hi - 1, 0))
    assert ((tighter_lo >= exact[~empty][:, 0]) | (q_lo == 255)).all()
    assert ((tighter_hi <= exact[~empty][:, 1]) | (q_hi == 0)).all()
    # The frame: the union of the filled children's exact boxes, in steps of the smallest
    # power of two (at least 2^-100) that spans it in 255 of them.
    any_filled = filled.any(axis=1)
    lower = np.where(filled[..., None], tree["lo"], np.inf).min(axis=1)[any_filled]
    upper = np.where(filled[..., None], tree["hi"], -np.inf).max(axis=1)[any_filled]
    np.testing.assert_array_equal(origin[any_filled], lower)
    mantissa, _ = np.frexp(scale)
    assert (mantissa == 0.5).all(), "scales are powers of two"
    extent = upper.astype(np.float64) - lower
    frame = scale[any_filled].astype(np.float64)
    assert (255 * frame >= extent).all()
    assert ((255 * frame / 2 < extent) | (frame == 2.0**-100)).all()

    # The object median halves every interior node (the smaller half on the left); only
    # the binary tree shows its halves.
    if params["method"] == "median" and not root_is_leaf and width == 2:
        left, right = tree["below"][:, 0], tree["below"][:, 1]
        assert np.all((right - left == 0) | (right - left == 1))

    # SAH cost of the tree (C_T per interior node, C_I per triangle, by area over the root's).
    ct, ci = params["traversal_cost"], params["intersection_cost"]
    if t_count:
        root_area = half_area(boxes[0, filled[0], 0].min(axis=0),
                              boxes[0, filled[0], 1].max(axis=0))
        if root_is_leaf:
            root_area = half_area(*boxes[0, 0])
        assert root_area > 0
        areas = half_area(boxes[..., 0, :], boxes[..., 1, :])
        cost = ct * (areas[tree["is_node"]].sum() + root_area * (not root_is_leaf))
        cost += ci * (areas[tree["leaf_row"], tree["leaf_slot"]] * counts).sum()  # empty: 0
        assert stats["sah_cost"] == pytest.approx(cost / root_area, rel=1e-9)
    else:
        assert stats["sah_cost"] == 0

    assert stats["method"] == params["method"]
    assert stats["bins"] == params["bins"]
    assert stats["max_leaf_size"] == params["max_leaf_size"]
    assert stats["build_seconds"] >= 0
    stored = nodes.nbytes + triangles.nbytes + ids.nbytes + 12  # 12: the frame
    assert stats["bytes"] == stored == structure.nbytes
    return tree


# ---------------------------------------------------------------------------------------------
# The camel
# ---------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def camel_builds(camel):
    return {method: accel.build("bvh", camel.vertices, camel.faces, method=method)
            for method in ("sah", "median")}


@pytest.mark.parametrize("method", ["sah", "median"])
def test_camel_build_is_consistent(camel, camel_builds, method):
    structure = camel_builds[method]
    check_bvh(structure, camel.vertices, camel.faces, method=method)
    assert structure.stats["leaves_over_max_depth"] == 0
    assert structure.stats["triangles"] == len(camel.faces) - len(camel.degenerate)
    assert structure.stats["width"] == 4


@pytest.mark.parametrize("width", [2, 8])
def test_camel_build_other_widths_are_consistent(camel, camel_builds, width):
    structure = accel.build("bvh", camel.vertices, camel.faces, width=width)
    check_bvh(structure, camel.vertices, camel.faces, width=width)
    # The same binary tree under every width: the same leaves in the same order.
    np.testing.assert_array_equal(structure["triangle_ids"], camel_builds["sah"]["triangle_ids"])
    assert structure.stats["leaves"] == camel_builds["sah"].stats["leaves"]
    assert structure.stats["binary_depth"] == camel_builds["sah"].stats["binary_depth"]
    # Wider nodes: fewer rows and a shallower tree than width 4's; narrower, more.
    default = camel_builds["sah"].stats
    wider = width > default["width"]
    assert (structure.stats["interior_nodes"] < default["interior_nodes"]) == wider
    assert (structure.stats["depth"] < default["depth"]) == wider


def test_camel_median_costs_more_than_sah(camel_builds):
    sah, median = (camel_builds[m].stats["sah_cost"] for m in ("sah", "median"))
    print(f"\nSAH cost of the camel: sah {sah:.3f}, median {median:.3f}")
    assert median > sah


def test_camel_build_is_deterministic(camel, camel_builds):
    again = accel.build("bvh", camel.vertices, camel.faces, method="median")
    for name, array in camel_builds["median"].arrays.items():
        np.testing.assert_array_equal(again[name], array)


# ---------------------------------------------------------------------------------------------
# Random soups
# ---------------------------------------------------------------------------------------------


def random_mesh(seed, n, *, grid, shared, degenerate, duplicates):
    """A soup of n triangles (or an indexed mesh over a shared vertex pool).

    ``grid``: coordinates on a coarse grid (many exactly shared coordinates, axis-aligned
    flat and collinear triangles); ``degenerate``/``duplicates``: shares of faces made
    degenerate (repeated corner) or copied from another face.
    """
    rng = np.random.default_rng(seed)
    if grid:
        points = rng.integers(-4, 5, size=(3 * n, 3)) * 0.5
    else:
        centres = rng.uniform(-10, 10, size=(n, 1, 3))
        sizes = 10.0 ** rng.uniform(-3, 0.5, size=(n, 1, 1))
        points = (centres + sizes * rng.normal(size=(n, 3, 3))).reshape(-1, 3)
    vertices = points.astype(np.float32)
    if shared:
        faces = rng.integers(0, len(vertices), size=(n, 3))
    else:
        faces = np.arange(3 * n).reshape(n, 3)
    pick = rng.random(n)
    faces[pick < degenerate, 2] = faces[pick < degenerate, 0]
    dup = rng.random(n) < duplicates
    faces[dup] = faces[rng.integers(0, n, size=n)][dup]
    return vertices, faces.astype(np.int32)


@PROPERTY
@given(
    seed=st.integers(0, 2**32 - 1),
    n=st.integers(1, 200),
    grid=st.booleans(),
    shared=st.booleans(),
    degenerate=st.sampled_from([0.0, 0.1, 0.5]),
    duplicates=st.sampled_from([0.0, 0.2, 0.9]),
    method=st.sampled_from(["sah", "median"]),
    bins=st.sampled_from([2, 3, 16, 256]),
    max_leaf_size=st.sampled_from([1, 2, 4, 7, 255]),
    traversal_cost=st.sampled_from([0.01, 0.5, 8.0]),
    intersection_cost=st.sampled_from([0.25, 1.0]),
    width=st.sampled_from([2, 4, 8]),
)
def test_random_soup_build_is_consistent(seed, n, grid, shared, degenerate, duplicates,
                                         **params):
    vertices, faces = random_mesh(seed, n, grid=grid, shared=shared, degenerate=degenerate,
                                  duplicates=duplicates)
    structure = accel.build("bvh", vertices, faces, **params)
    check_bvh(structure, vertices, faces, **params)
    assert structure.stats["leaves_over_max_depth"] == 0


def chain(lo, hi):
    """Triangles of size 2^k at x = 2^k: binned SAH with 2 bins peels off one per level."""
    scale = 2.0 ** np.arange(lo, hi)
    corners = np.array([[0.75, 0, 0], [1.25, 0, 0], [1, 0.5, 0]])
    vertices = (corners[None] * scale[:, None, None]).reshape(-1, 3).astype(np.float32)
    return vertices, np.arange(len(vertices), dtype=np.int32).reshape(-1, 3)


def test_depth_limit_leaves_a_big_leaf():
    vertices, faces = chain(-40, 40)
    structure = accel.build("bvh", vertices, faces, bins=2, max_leaf_size=1)
    check_bvh(structure, vertices, faces, bins=2, max_leaf_size=1)
    stats = structure.stats
    assert stats["binary_depth"] == 64 and stats["leaves_over_max_depth"] >= 1
    assert stats["triangles_per_leaf_max"] > 1
    # Still traced like brute force: axis-parallel rays down onto every triangle.
    # Triangle k lies in z = 0 at scale 2^k: the ray starts 2^k above its centroid.
    corners = vertices.reshape(-1, 3, 3)
    origins = corners.mean(axis=1)
    origins[:, 2] = corners[:, 1, 0] - corners[:, 0, 0]
    directions = np.tile(np.float32([0, -0.0, -1]), (len(origins), 1))
    brute = accel.build("brute", vertices, faces)
    # (float32 kernels lose triangles of size 2^-40 or so: brute force misses them too.)
    moderate = np.abs(np.log2(origins[:, 2])) <= 16
    for kernel in jrt.KERNELS:
        got = as_numpy(jrt.closest_hit(structure, origins, directions, kernel=kernel))
        want = as_numpy(jrt.closest_hit(brute, origins, directions, kernel=kernel))
        np.testing.assert_array_equal(got["triangle"][moderate], np.flatnonzero(moderate))
        for key in want:
            np.testing.assert_array_equal(got[key], want[key])


# ---------------------------------------------------------------------------------------------
# Degenerate faces, empty and tiny meshes
# ---------------------------------------------------------------------------------------------


def stacked(count, *, z0=1.0):
    """``count`` triangles covering (0.5, 0.5) at z = z0, z0 + 1, ... (face k at z0 + k)."""
    base = np.array([[-1, -1, 0], [3, -1, 0], [-1, 3, 0]], np.float32)
    vertices = np.concatenate([base + np.float32([0, 0, z0 + k]) for k in range(count)])
    return vertices.reshape(-1, 3), np.arange(3 * count, dtype=np.int32).reshape(-1, 3)


def test_degenerate_faces_are_skipped():
    vertices, faces = stacked(3)
    extra = np.array([[0.5, 0.5, 0.5], [1.5, 1.5, 0.5], [2.5, 2.5, 0.5]], np.float32)
    vertices = np.concatenate([vertices, extra])
    degenerate = np.array([[9, 10, 11], [0, 0, 1], [9, 9, 9], [3, 4, 3]], np.int32)
    faces = np.concatenate([degenerate[:2], faces, degenerate[2:]])
    for max_leaf_size in (1, 4):
        structure = accel.build("bvh", vertices, faces, max_leaf_size=max_leaf_size)
        check_bvh(structure, vertices, faces, max_leaf_size=max_leaf_size)
        assert structure.stats["degenerate_skipped"] == 4
        np.testing.assert_array_equal(np.sort(structure["triangle_ids"]), [2, 3, 4])
        # A ray through the collinear face (at z = 0.5, below the first real face) hits the
        # nearest real face (index 2, at z = 1).
        hits = as_numpy(jrt.closest_hit(structure, np.float32([[0.5, 0.5, 0]]),
                                        np.float32([[0, 0, 1]])))
        assert hits["triangle"][0] == 2 and hits["t"][0] == 1


@pytest.mark.parametrize("vertex_count", [0, 3])
def test_empty_mesh_builds(vertex_count):
    vertices = np.zeros((vertex_count, 3), np.float32)
    faces = np.zeros((0, 3), np.int32)
    structure = accel.build("bvh", vertices, faces)
    check_bvh(structure, vertices, faces)
    assert structure.stats["triangles"] == 0 and structure.stats["nodes"] == 1
    assert structure.stats["leaves"] == 1 and structure.stats["depth"] == 0


@pytest.mark.parametrize("vertex_count", [0, 3])
def test_empty_mesh_traces_all_misses(vertex_count):
    vertices = np.zeros((vertex_count, 3), np.float32)
    structure = accel.build("bvh", vertices, np.zeros((0, 3), np.int32))
    origins = np.float32([[0, 0, -1], [0.5, 0.5, 0.5], [0, 0, 0]])
    directions = np.float32([[0, 0, 1], [1, 0, 0], [0, -1, 0]])
    for kernel in jrt.KERNELS:
        hits = as_numpy(jrt.closest_hit(structure, origins, directions, kernel=kernel))
        np.testing.assert_array_equal(hits["triangle"], -1)
        np.testing.assert_array_equal(hits["t"], np.inf)
        np.testing.assert_array_equal(hits["u"], 0)
        np.testing.assert_array_equal(hits["v"], 0)
        np.testing.assert_array_equal(
            np.asarray(jrt.occluded(structure, origins, directions, kernel=kernel)), False)


ALL_DEGENERATE = (np.float32([[0, 0, 0], [1, 1, 1], [2, 2, 2]]),
                  np.int32([[0, 1, 2], [0, 0, 1], [2, 2, 2]]))


def test_all_degenerate_mesh_builds_empty():
    structure = accel.build("bvh", *ALL_DEGENERATE)
    check_bvh(structure, *ALL_DEGENERATE)
    assert structure.stats["degenerate_skipped"] == 3
    assert structure.stats["triangles"] == 0


def test_all_degenerate_mesh_traces_all_misses():
    structure = accel.build("bvh", *ALL_DEGENERATE)
    hits = as_numpy(jrt.closest_hit(structure, np.float32([[1, 1, 0]]),
                                    np.float32([[0, 0, 1]])))
    assert hits["triangle"][0] == -1


@pytest.mark.parametrize("count", [1, 2, 3])
@pytest.mark.parametrize("max_leaf_size", [1, 4])
@pytest.mark.parametrize("method", ["sah", "median"])
def test_tiny_meshes_build_and_hit(count, max_leaf_size, method):
    vertices, faces = stacked(count)
    structure = accel.build("bvh", vertices, faces, method=method, max_leaf_size=max_leaf_size)
    check_bvh(structure, vertices, faces, method=method, max_leaf_size=max_leaf_size)
    if count <= max_leaf_size and method == "median":
        # (SAH may split a node that could be a leaf, when the split is cheaper.)
        assert structure.stats["interior_nodes"] == 0 and structure.stats["leaves"] == 1
    # Up from below (nearest: face 0), down from above (nearest: the last face), from
    # between faces 0 and 1 both ways, off to the side (a miss).
    top = count + 1.0
    origins = np.float32([[0.5, 0.5, 0], [0.5, 0.5, top], [0.5, 0.5, 1.5], [0.5, 0.5, 1.5],
                          [9, 9, 0]])
    directions = np.float32([[0, 0, 1], [0, 0, -1], [0, 0, 1], [0, 0, -1], [0, 0, 1]])
    expected_triangle = [0, count - 1, 1 if count > 1 else -1, 0, -1]
    expected_t = [1, 1, 0.5 if count > 1 else np.inf, 0.5, np.inf]
    # (One kernel: each shape compiles anew; tests/test_bvh_traversal.py covers them all.)
    hits = as_numpy(jrt.closest_hit(structure, origins, directions))
    np.testing.assert_array_equal(hits["triangle"], expected_triangle)
    np.testing.assert_array_equal(hits["t"], np.float32(expected_t))
    occ = np.asarray(jrt.occluded(structure, origins, directions))
    np.testing.assert_array_equal(occ, np.asarray(expected_triangle) >= 0)


# ---------------------------------------------------------------------------------------------
# Parameters
# ---------------------------------------------------------------------------------------------


BAD_PARAMS = [
    ("method", "sweep"),
    ("method", "SAH"),
    ("method", None),
    ("bins", 1),
    ("bins", 0),
    ("bins", 257),
    ("bins", 16.0),
    ("bins", "16"),
    ("max_leaf_size", 0),
    ("max_leaf_size", -1),
    ("max_leaf_size", 256),
    ("max_leaf_size", 2.5),
    ("traversal_cost", 0.0),
    ("traversal_cost", -0.5),
    ("traversal_cost", float("nan")),
    ("traversal_cost", float("inf")),
    ("intersection_cost", 0),
    ("intersection_cost", -1.0),
    ("intersection_cost", float("nan")),
    ("width", 3),
    ("width", 16),
    ("width", 4.0),
    ("width", True),
]


@pytest.mark.parametrize(("name", "value"), BAD_PARAMS)
def test_bad_parameters_raise(name, value):
    vertices, faces = stacked(2)
    with pytest.raises(ValueError, match=name):
        accel.build("bvh", vertices, faces, **{name: value})


@pytest.mark.parametrize(("name", "value"), [
    ("bins", 2), ("bins", 256), ("max_leaf_size", 1), ("max_leaf_size", 255),
    ("traversal_cost", 1e-6), ("intersection_cost", 100.0), ("bins", np.int64(8)),
    ("width", 2), ("width", 8), ("width", np.int64(4)),
])
def test_parameter_bounds_are_accepted(name, value):
    vertices, faces = random_mesh(1, 50, grid=False, shared=False, degenerate=0, duplicates=0)
    structure = accel.build("bvh", vertices, faces, **{name: value})
    check_bvh(structure, vertices, faces, **{name: value})


def test_unknown_builder_raises():
    vertices, faces = stacked(1)
    with pytest.raises(ValueError, match="quadtree"):
        accel.build("quadtree", vertices, faces)


@pytest.mark.parametrize("name", accel.NAMES)
@pytest.mark.parametrize("value", [np.nan, np.inf, -np.inf])
def test_non_finite_vertices_are_refused_by_every_builder(name, value):
    vertices, faces = stacked(2)
    vertices[4, 1] = value
    with pytest.raises(ValueError, match="vertex 4 .*allowed: finite"):
        accel.build(name, vertices, faces)


@pytest.mark.parametrize("op", [np.minimum, np.maximum])
@pytest.mark.parametrize("reverse", [False, True])
def test_sah_sweep_matches_numpy_accumulate(op, reverse):
    """The bin-by-bin sweep of the SAH gives NumPy's accumulate along the bins, from either
    end, with infinities (empty bins) and ties."""
    from accel.bvh import _sweep

    rng = np.random.default_rng(7)
    a = rng.integers(-3, 4, (3, 3, 16, 41)).astype(np.float32)
    a[rng.random(a.shape) < 0.2] = np.inf if op is np.minimum else -np.inf
    expected = (op.accumulate(a[:, :, ::-1], axis=2)[:, :, ::-1] if reverse
                else op.accumulate(a, axis=2))
    assert np.array_equal(_sweep(op, a, reverse=reverse), expected)


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("bins", [4, 16])
def test_sorted_sweep_finds_the_binned_sweeps_split(seed, bins):
    """A node of at most ``bins`` triangles is swept over its sorted triangles; that finds
    the binned sweep's split (the same cost, axis and bin, bit for bit), also with
    triangles sharing a bin, coincident centroids (no plane) and equal costs."""
    from accel.bvh import _binned_splits, _sorted_splits

    rng = np.random.default_rng(seed)
    counts = rng.integers(2, bins + 1, 300)
    seg = np.repeat(np.arange(counts.size), counts)
    # Coordinates on a coarse grid: shared bins, equal boxes and ties are common.
    lo = (rng.integers(0, 6, (seg.size, 3)) * 0.5).astype(np.float32)
    hi = lo + (rng.integers(0, 3, (seg.size, 3)) * 0.5).astype(np.float32)
    b = rng.integers(0, bins, (seg.size, 3))
    b[seg % 7 == 0] = 3 % bins  # whole nodes in one bin: no plane separates them
    node_lo = np.minimum.reduceat(lo, np.cumsum(counts) - counts).astype(np.float64)
    node_hi = np.maximum.reduceat(hi, np.cumsum(counts) - counts).astype(np.float64)
    e = np.maximum(node_hi - node_lo, 0)
    area = e[:, 0] * e[:, 1] + e[:, 1] * e[:, 2] + e[:, 2] * e[:, 0]
    binned = _binned_splits(lo, hi, b, seg, counts, area, bins, 0.5, 1.0)
    found = _sorted_splits(lo, hi, b, seg, counts, area, bins, bins, 0.5, 1.0)
    finite = np.isfinite(binned[0])
    assert (~finite).any() and finite.any()
    for ours, theirs in zip(found, binned, strict=True):  # cost, axis, bin
        assert np.array_equal(ours, theirs)
