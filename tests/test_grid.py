"""The uniform grid (``accel/grid.py`` built, ``jrt/grid.py`` traced).

Builder: the arrays decoded against the documented layout (grid row in the local frame,
the frame, compressed-row cell lists, skip distances); the reference rule checked by an
independent dense test (every (cell, triangle) pair, the cell boxes rebuilt from the
documented planes and widened, then the shared exact triangle-box test on the corners in
the frame): a cell references exactly the triangles that touch its widened box; the skip
distances against a brute-force Chebyshev distance; the resolution against the closed
forms of the density rule (3-D, planar, thin, clamped); statistics recomputed; parameter
errors; empty, one-triangle, all-degenerate and flat meshes; the 19k camel moved 1e3 and
1e5 times its size away, or scaled by 1e-4 and 1e4, builds the grid (cells, about the
references) it builds at the origin.

Traversal: the same hits as brute force, bit for bit, with every kernel: on the camel (20k
camera and 20k incoherent rays, closest hit and ``occluded``), a hit found in a cell but
lying beyond it, and random soups (hypothesis) whose axis-aligned flat triangles are moved
exactly onto cell faces (some of them spanning many cells), with rays from origins exactly
on cell faces and at grid corners, rays running inside a cell face (a ±0.0 direction
component), and the soups' own axis-parallel rays. Soup grids are padded to fixed shapes so
that every example runs the same compiled kernels. With the watertight and Möller–Trumbore
kernels (whose rounding does not grow with the distance from the coordinate origin): on
the moved and scaled camels and on two camels 1e3 apart, far from the origin.
"""

from __future__ import annotations

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
    signed_zeros,
    soup,
)

import accel
import jrt
from accel import grid
from accel.geometry import (
    CELL_MARGIN,
    float32_down,
    float32_up,
    frame_origin,
    local_corners,
    triangles_overlap_boxes,
    widen_boxes,
)
from accel.structure import Structure
from jrt.raysets import incoherent_set
from jrt.trace import as_numpy

STAT_KEYS = {
    "build_seconds", "density", "max_resolution", "max_skip", "triangles",
    "degenerate_skipped", "resolution", "cells", "nodes", "non_empty_cells", "leaves",
    "depth", "references", "references_per_cell_mean", "references_per_leaf_mean",
    "references_per_leaf_max", "expected_cells_visited", "expected_triangle_tests",
    "sah_cost", "bytes",
}
PROPERTY = settings(max_examples=20, deadline=None, database=None)
CELL_CAP = 1 << 14  # soup grids are padded to these shapes
REFERENCE_CAP = 1 << 17



@pytest.fixture(scope="module")
def camel_grid(camel_structures):
    return camel_structures("grid")


# ---------------------------------------------------------------------------------------------
# An independent decoder of the layout
# ---------------------------------------------------------------------------------------------


def expected_ids(vertices, faces) -> np.ndarray:
    corners = np.asarray(vertices, np.float32)[np.asarray(faces)].astype(np.float64)
    if len(corners) == 0:
        return np.zeros(0, np.int64)
    normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    return np.flatnonzero(np.any(normal != 0, axis=1))


def planes_of(structure) -> list[np.ndarray]:
    """Per axis, the float32 planes lo + m * size, m = 0..n (as documented), in the grid's
    frame."""
    g = np.asarray(structure["grid"])
    res = g.view(np.int32)[12:15]
    return [np.float32(g[a]) + np.arange(res[a] + 1, dtype=np.float32) * np.float32(g[6 + a])
            for a in range(3)]


def decode(structure) -> dict:
    """The grid's arrays checked against the documented layout: the resolution, the cell
    of every reference slot and the reference rows."""
    g = np.asarray(structure["grid"])
    assert g.dtype == np.float32 and g.shape == (16,)
    res = g.view(np.int32)[12:15].astype(np.int64)
    assert g.view(np.int32)[15] == 0 and np.all(res >= 1)
    lo, hi = g[0:3].astype(np.float64), g[3:6].astype(np.float64)
    extent = hi - lo
    assert np.all(extent >= 0)
    flat = extent == 0
    np.testing.assert_array_equal(g[6:9], np.where(flat, 0, extent / res).astype(np.float32))
    np.testing.assert_array_equal(
        g[9:12], np.where(flat, 0, res / np.where(flat, 1, extent)).astype(np.float32))
    cells = int(res.prod())
    starts = np.asarray(structure["cell_start"])
    assert starts.dtype == np.int32 and starts.shape == (cells + 1,)
    assert starts[0] == 0 and np.all(np.diff(starts) >= 0)
    total = int(starts[-1])
    references = np.asarray(structure["references"])
    assert references.dtype == np.int32 and references.shape == (max(total, 1),)
    counts = np.diff(starts).astype(np.int64)
    cell = np.repeat(np.arange(cells), counts)
    rows = references[:total].astype(np.int64)
    assert np.all((rows >= 0) & (rows < max(structure.num_triangles, 1)))
    same = cell[1:] == cell[:-1]
    assert np.all(rows[1:][same] > rows[:-1][same]), "a cell's rows are not ascending"
    skip = np.asarray(structure["skip"])
    assert skip.dtype == np.int8 and skip.shape == (cells,)
    frame = np.asarray(structure["frame"])
    assert frame.dtype == np.float32 and frame.shape == (3,)
    assert structure.layout == ()
    return {"res": res, "cells": cells, "counts": counts, "cell": cell, "rows": rows,
            "skip": skip, "lo": lo, "hi": hi, "frame": frame}


def widened_cells(structure, cells: np.ndarray):
    """float64 [K, 3] lower and upper corners of the given cells, widened as documented:
    widen_boxes, plus CELL_MARGIN of the grid box's largest corner coordinate."""
    g = np.asarray(structure["grid"])
    res = g.view(np.int32)[12:15].astype(np.int64)
    planes = planes_of(structure)
    index = [cells % res[0], (cells // res[0]) % res[1], cells // (res[0] * res[1])]
    lo = np.stack([planes[a][index[a]] for a in range(3)], axis=1)
    hi = np.stack([planes[a][index[a] + 1] for a in range(3)], axis=1)
    wlo, whi = widen_boxes(lo, hi)
    scale = CELL_MARGIN * np.abs(g[0:6].astype(np.float64)).max()
    return wlo - scale, whi + scale


def world_planes(planes, frame) -> list[np.ndarray]:
    """Per axis, the world positions (float32) of those of the frame's ``planes`` that
    ``plane + frame`` represents exactly: a point there lies exactly on the plane once the
    engine moves it into the frame (``o - frame`` is then exact). All of them, rounded,
    on an axis where none is exact (every one is where the frame is 0)."""
    frame = np.asarray(frame, np.float32).astype(np.float64)
    out = []
    for axis, p in enumerate(planes):
        world = (p.astype(np.float64) + frame[axis]).astype(np.float32)
        exact = world.astype(np.float64) - frame[axis] == p
        out.append(world[exact] if exact.any() else world)
    return out


def check_references(structure, cells=None):
    """Dense test: each of ``cells`` (all by default) references exactly the triangles
    that touch its widened box (every pair tested: a bounds test, then the exact one),
    both in the grid's frame."""
    layout = decode(structure)
    cells = np.arange(layout["cells"]) if cells is None else np.unique(cells)
    tris = local_corners(structure["triangles"], structure["frame"])
    wlo, whi = widened_cells(structure, cells)
    tlo, thi = tris.min(axis=1), tris.max(axis=1)
    near = np.all((tlo[None] <= whi[:, None]) & (thi[None] >= wlo[:, None]), axis=2)
    c, t = np.nonzero(near)
    touch = np.zeros_like(near)
    touch[c, t] = triangles_overlap_boxes(tris[t], wlo[c], whi[c])
    listed = np.zeros_like(near)
    sel = np.isin(layout["cell"], cells)
    listed[np.searchsorted(cells, layout["cell"][sel]), layout["rows"][sel]] = True
    missing = np.argwhere(touch & ~listed)
    extra = np.argwhere(listed & ~touch)
    assert missing.size == 0, f"(cell, row) pairs not referenced: {missing[:5].tolist()}"
    assert extra.size == 0, f"references to triangles that miss the cell: {extra[:5].tolist()}"
    if len(tris) and cells.size == layout["cells"]:
        assert np.all(np.bincount(layout["rows"], minlength=len(tris)) >= 1)


def check_skip(structure, cells=None):
    """The skip distances against a brute-force Chebyshev distance to the occupied cells."""
    layout = decode(structure)
    res, cap = layout["res"], structure.stats["max_skip"]
    if cells is None:  # all of them, or a sample of 2000 of a large grid
        cells = np.arange(layout["cells"])
        if cells.size > 2000:
            cells = np.random.default_rng(cells.size).choice(cells, 2000, replace=False)
    occupied = np.flatnonzero(layout["counts"] > 0)

    def coords(c):
        return np.stack([c % res[0], (c // res[0]) % res[1], c // (res[0] * res[1])], axis=1)

    want = np.full(cells.shape, cap, np.int64)
    a, b = coords(cells), coords(occupied)
    for start in range(0, len(b), 2048):
        d = np.abs(a[:, None] - b[None, start:start + 2048]).max(axis=2)
        want = np.minimum(want, d.min(axis=1, initial=cap))
    np.testing.assert_array_equal(layout["skip"][cells], want)


def check_structure(structure, vertices, faces):
    """Triangles, bounds and statistics as documented."""
    vertices = np.asarray(vertices, np.float32)
    faces = np.asarray(faces)
    layout = decode(structure)
    assert structure.kind == "grid"
    assert set(structure.arrays) == {"grid", "cell_start", "skip", "references", "triangles",
                                     "triangle_ids", "frame"}
    keep = expected_ids(vertices, faces)
    np.testing.assert_array_equal(structure["triangle_ids"], keep)
    assert structure["triangle_ids"].dtype == np.int32
    triangles = np.asarray(structure["triangles"])
    assert triangles.dtype == np.float32
    np.testing.assert_array_equal(triangles, vertices[faces[keep]].reshape(-1, 3, 3))
    # The frame, and the grid box in it: the local corners' bounds rounded outward.
    np.testing.assert_array_equal(layout["frame"], frame_origin(triangles))
    if len(keep):
        local = local_corners(triangles, layout["frame"])
        np.testing.assert_array_equal(layout["lo"], float32_down(local.min(axis=(0, 1))))
        np.testing.assert_array_equal(layout["hi"], float32_up(local.max(axis=(0, 1))))
        assert np.all(layout["lo"] <= local.min(axis=(0, 1)))
        assert np.all(layout["hi"] >= local.max(axis=(0, 1)))
    else:
        np.testing.assert_array_equal(structure["grid"][0:6], 0)
        np.testing.assert_array_equal(layout["frame"], 0)
        np.testing.assert_array_equal(layout["res"], 1)
        np.testing.assert_array_equal(structure["references"], [0])
    stats = structure.stats
    assert set(stats) == STAT_KEYS
    counts = layout["counts"]
    filled = counts[counts > 0]
    assert stats["triangles"] == len(keep) == structure.num_triangles
    assert stats["degenerate_skipped"] == len(faces) - len(keep)
    assert stats["resolution"] == tuple(int(r) for r in layout["res"])
    assert stats["cells"] == stats["nodes"] == layout["cells"]
    assert stats["non_empty_cells"] == stats["leaves"] == len(filled)
    assert stats["depth"] == 1
    assert stats["references"] == counts.sum()
    assert stats["references_per_cell_mean"] == pytest.approx(counts.mean())
    assert stats["references_per_leaf_mean"] == pytest.approx(
        filled.mean() if len(filled) else 0.0)
    assert stats["references_per_leaf_max"] == (filled.max() if len(filled) else 0)
    assert stats["bytes"] == structure.nbytes
    assert stats["build_seconds"] >= 0
    # The grid cost: cells and references seen by a random line through the box (Crofton).
    extent = layout["hi"] - layout["lo"]
    size = extent / layout["res"]

    def area(e):
        return 2 * (e[0] * e[1] + e[1] * e[2] + e[2] * e[0])

    ratio = area(size) / area(extent) if area(extent) > 0 else 1.0
    assert stats["expected_cells_visited"] == pytest.approx(layout["cells"] * ratio)
    assert stats["expected_triangle_tests"] == pytest.approx(counts.sum() * ratio)
    assert stats["sah_cost"] == pytest.approx(
        grid.TRAVERSAL_COST * layout["cells"] * ratio
        + grid.INTERSECTION_COST * counts.sum() * ratio)
    return layout


# ---------------------------------------------------------------------------------------------
# Builder
# ---------------------------------------------------------------------------------------------


def test_camel_build_is_consistent(camel, camel_grid):
    layout = check_structure(camel_grid, camel.vertices, camel.faces)
    # The density rule, no axis thin or clamped on the camel: ceil(extent * cbrt(lambda N/V)).
    n = camel_grid.num_triangles
    density = grid.DEFAULT_DENSITY
    extent = layout["hi"] - layout["lo"]
    scale = np.cbrt(density * n / extent.prod())
    np.testing.assert_array_equal(layout["res"], np.ceil(extent * scale))
    assert density * n <= layout["cells"] <= np.prod(extent * scale + 1)
    assert camel_grid.stats["max_skip"] == grid.DEFAULT_MAX_SKIP
    # The reference rule on a sample of cells (the non-empty ones favoured), every triangle.
    rng = np.random.default_rng(0)
    filled = np.flatnonzero(layout["counts"])
    cells = np.union1d(rng.choice(filled, 150, replace=False),
                       rng.choice(layout["cells"], 100, replace=False))
    check_references(camel_grid, cells)
    check_skip(camel_grid, rng.choice(layout["cells"], 3000, replace=False))
    # A triangle in several cells: references outnumber the triangles.
    assert camel_grid.stats["references"] > n


def test_resolution_follows_the_density_rule():
    # A box 4 x 2 x 1 of 100 random triangles.
    rng = np.random.default_rng(1)
    base = np.float32([[0, 0, 0], [4, 2, 1], [4, 2.0, 0.5]])
    vertices = np.concatenate([base, rng.uniform([0, 0, 0], [4, 2, 1], (297, 3))])
    faces = np.arange(300).reshape(100, 3)
    s = accel.build("grid", vertices, faces, density=3.0)
    extent = (s["grid"][3:6] - s["grid"][0:3]).astype(np.float64)
    want = np.ceil(extent * np.cbrt(3.0 * s.num_triangles / extent.prod()))
    assert s.stats["resolution"] == tuple(want.astype(int))
    # Clamped per axis.
    s = accel.build("grid", vertices, faces, density=3.0, max_resolution=5)
    assert s.stats["resolution"] == tuple(np.minimum(want, 5).astype(int))
    # Planar (z = 0): one cell on z, the rest by area: ceil(extent * sqrt(lambda N / A)).
    planar = vertices.copy()
    planar[:, 2] = 0
    s = accel.build("grid", planar, faces, density=3.0)
    extent = (s["grid"][3:6] - s["grid"][0:3]).astype(np.float64)
    n = s.num_triangles
    want = np.ceil(extent[:2] * np.sqrt(3.0 * n / extent[:2].prod()))
    assert s.stats["resolution"] == (*want.astype(int), 1)
    check_structure(s, planar, faces)
    check_references(s)
    # Thin (z extent 1e-4: under one cell by the 3-D rule): the planar rule as well.
    thin = planar.copy()
    thin[:, 2] = rng.uniform(0, 1e-4, len(thin)).astype(np.float32)
    s = accel.build("grid", thin, faces, density=3.0)
    extent = (s["grid"][3:6] - s["grid"][0:3]).astype(np.float64)
    want = np.ceil(extent[:2] * np.sqrt(3.0 * s.num_triangles / extent[:2].prod()))
    assert s.stats["resolution"] == (*want.astype(int), 1)
    # A line of triangles (extent on x only): all the cells on x, clamped.
    line = np.zeros((300, 3), np.float32)
    line[:, 0] = rng.uniform(0, 100, 300)
    line[0::3, 1] = 1e-3  # not degenerate, but thin in y and z
    line[1::3, 2] = 1e-3
    s = accel.build("grid", line, faces, density=3.0, max_resolution=64)
    assert s.stats["resolution"] == (64, 1, 1)
    check_references(s)


@pytest.mark.parametrize(("param", "value", "message"), [
    ("density", 0, "density must be a positive finite number"),
    ("density", -1.0, "density must be a positive finite number"),
    ("density", float("nan"), "density must be a positive finite number"),
    ("density", float("inf"), "density must be a positive finite number"),
    ("density", 1e5, "density must be a positive finite number of at most 1e4"),
    ("density", "8", "density must be"),
    ("density", True, "density must be"),
    ("max_resolution", 0, r"max_resolution must be an integer in \[1, 1024\], got 0"),
    ("max_resolution", 1025, "max_resolution must be an integer"),
    ("max_resolution", 16.0, "max_resolution must be an integer"),
    ("max_skip", -1, r"max_skip must be an integer in \[0, 127\], got -1"),
    ("max_skip", 128, "max_skip must be an integer"),
    ("max_skip", 2.0, "max_skip must be an integer"),
])
def test_bad_parameters_raise(param, value, message):
    with pytest.raises(ValueError, match=f"grid: {message}"):
        accel.build("grid", *TINY_MESH, **{param: value})


def test_unknown_parameter_raises():
    with pytest.raises(TypeError):
        accel.build("grid", *TINY_MESH, bins=4)


TINY_MESH = (np.float32([[-1, -1, 1], [3, -1, 1], [-1, 3, 1]]), np.int32([[0, 1, 2]]))
FLAT_MESH = (np.float32([[x, y, 0.5] for x in range(5) for y in range(5)]),
             np.int32([[5 * x + y, 5 * x + y + 5, 5 * x + y + 1] for x in range(4)
                       for y in range(4)]))
TINY_MESHES = {
    "empty": (np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32)),
    "one triangle": TINY_MESH,
    "all degenerate": (np.float32([[0, 0, 0], [1, 1, 1], [2, 2, 2], [3, 0, 0]]),
                       np.int32([[0, 1, 2], [3, 3, 0], [1, 1, 1]])),
    "flat": FLAT_MESH,
    "one degenerate among two": (np.float32([[0, 0, 0], [1, 0, 0], [0, 1, 0], [2, 2, 2]]),
                                 np.int32([[0, 1, 2], [3, 3, 3]])),
}


@pytest.mark.parametrize("name", list(TINY_MESHES))
def test_tiny_meshes_build_and_trace(name):
    vertices, faces = TINY_MESHES[name]
    s = accel.build("grid", vertices, faces)
    check_structure(s, vertices, faces)
    check_references(s)
    check_skip(s)
    if name == "flat":
        assert s.stats["resolution"][2] == 1 and s.stats["cells"] > 1
    # Traced at the soups' shapes (N_RAYS rays, padded arrays): no compile of its own.
    rng = np.random.default_rng(3)
    origins = rng.uniform(-2, 4, (N_RAYS, 3)).astype(np.float32)
    targets = rng.uniform(-0.5, 3.5, (N_RAYS, 3)).astype(np.float32)
    targets[:, 2] = np.where(rng.random(N_RAYS) < 0.5, 0.5, targets[:, 2])
    directions = targets - origins
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    # A quarter: from the box's corners and faces (z = 0.5 is the flat mesh's plane),
    # axis-parallel with ±0.0 components, or grazing the plane z = 0.5.
    special = np.arange(N_RAYS // 4)
    g, frame = s["grid"], s["frame"]
    corners = np.float32([g[0:3] + frame, g[3:6] + frame, [0, 0, 0.5], [1, 2, 0.5]])
    origins[special] = corners[special % 4]
    origins[special[::3], 0] = rng.uniform(-0.5, 3.5, special[::3].size)
    d = signed_zeros(rng, (special.size, 3))
    d[np.arange(special.size), special % 3] = np.where(special % 2, 1.0, -1.0)
    d[1::4] = [0.8, 0.6, 0.0]
    d[2::4] = [0.6, -0.8, 1e-6]
    directions[special] = d
    brute = fixed_shape_brute(accel.build("brute", vertices, faces))
    padded = fixed_shape_grid(s)
    for kernel in KERNELS:
        want = as_numpy(jrt.closest_hit(brute, origins, directions, kernel=kernel))
        got = as_numpy(jrt.closest_hit(padded, origins, directions, kernel=kernel, lanes=64))
        assert_same_hits(got, want, origins, directions, f"{name}/{kernel}")
        np.testing.assert_array_equal(
            np.asarray(jrt.occluded(padded, origins, directions, kernel=kernel, lanes=32)),
            want["triangle"] >= 0)
    if s.num_triangles:
        assert (want["triangle"] >= 0).any()


# ---------------------------------------------------------------------------------------------
# Traversal: the camel
# ---------------------------------------------------------------------------------------------


def test_camel_counters_and_plain_dda(camel, camel_grid, camel_rays, brute_hits):
    """Leaps take fewer steps than the plain DDA (max_skip=0), and both give brute force's
    hits; no walk takes more steps than the cells along the three axes."""
    origins, directions = camel_rays["incoherent"]
    want = brute_hits("watertight", "incoherent")
    hits, count = jrt.closest_hit(camel_grid, origins, directions, counters=True)
    assert_same_hits(as_numpy(hits), want, origins, directions, "leaps")
    plain = accel.build("grid", camel.vertices, camel.faces, max_skip=0)
    assert not np.asarray(plain["skip"]).any()
    plain_hits, plain_count = jrt.closest_hit(plain, origins, directions, counters=True)
    assert_same_hits(as_numpy(plain_hits), want, origins, directions, "plain DDA")
    steps, tests, leaves = (np.asarray(a) for a in count)
    plain_steps = np.asarray(plain_count.steps)
    hit = want["triangle"] >= 0
    assert (steps >= 1).all() and (steps <= sum(camel_grid.stats["resolution"]) + 1).all()
    assert (tests[hit] >= 1).all() and (leaves <= tests).all()
    # The same cells are tested (only empty ones are leapt over), but for a few rays where
    # the point located after a leap lies within rounding of a cell face.
    assert np.mean(tests != np.asarray(plain_count.tests)) < 1e-3
    assert steps.mean() < 0.5 * plain_steps.mean()
    assert tests.mean() < 0.01 * camel_grid.num_triangles


def test_a_hit_beyond_its_cell_does_not_end_the_walk():
    """Face 0 lies in the ray's first cells, nearly along the ray, and is hit at x = 9;
    face 1 faces the ray at x = 5. The walk tests face 0 in its first cell (a hit far
    beyond that cell) and must go on to face 1."""
    vertices = np.float32([
        [0, -1, 0.555], [0, 2, 0.555], [10, 0.5, 0.605],  # z = 0.6 + (x - 9) / 200
        [5, 0, 0], [5, 1, 0], [5, 0.5, 1],
    ])
    faces = np.int32([[0, 1, 2], [3, 4, 5]])
    s = accel.build("grid", vertices, faces, density=500.0)
    assert s.stats["resolution"][0] >= 10
    # (N_RAYS rays and padded arrays: the soups' compiled kernels.)
    origins = np.tile(np.float32([[0.0, 0.5, 0.6], [-1.0, 0.5, 0.6]]), (N_RAYS // 2, 1))
    directions = np.tile(np.float32([[1, 0, -0.0], [1, 0.0, 0]]), (N_RAYS // 2, 1))
    brute = fixed_shape_brute(accel.build("brute", vertices, faces))
    padded = fixed_shape_grid(s)
    for kernel in KERNELS:
        want = as_numpy(jrt.closest_hit(brute, origins, directions, kernel=kernel))
        np.testing.assert_array_equal(want["triangle"], 1)
        np.testing.assert_allclose(want["t"][:2], [5, 6])
        got = as_numpy(jrt.closest_hit(padded, origins, directions, kernel=kernel, lanes=64))
        assert_same_hits(got, want, origins, directions, kernel)
    # Face 0 is referenced by the cell where the first ray starts (so it is tested, and
    # hit at t = 9, before face 1), and by every cell up to x = 9 (it is tested again).
    layout = decode(s)
    g = s["grid"]
    index = np.floor((origins[0] - s["frame"] - g[0:3]) * g[9:12]).astype(int)
    start_cell = index[0] + layout["res"][0] * (index[1] + layout["res"][1] * index[2])
    assert 0 in layout["rows"][layout["cell"] == start_cell]
    _, count = jrt.closest_hit(s, origins[:2], directions[:2], counters=True)
    assert np.all(np.asarray(count.tests) > 2)


# ---------------------------------------------------------------------------------------------
# Far from the coordinate origin, and scaled: the local frame
# ---------------------------------------------------------------------------------------------

#: (offset, scale) of the 19k camel, applied in float64, then rounded to float32. Moved,
#: the camel lies 1e3 and 1e5 times its size from the coordinate origin (at 1e5 a float32
#: ulp is 2^-7, and about 30 % of its triangles round to degenerate ones).
TRANSFORMS = {
    "moved 1e3": ((1000.0, -700.0, 1300.0), 1.0),
    "moved 1e5": ((1e5, -7e4, 1.3e5), 1.0),
    "scaled 1e-4": ((0.0, 0.0, 0.0), 1e-4),
    "scaled 1e4": ((0.0, 0.0, 0.0), 1e4),
}
#: Two camels 1e3 apart along x, far from the coordinate origin (a long thin grid: 512
#: cells on x, clamped, a few on y and z).
TWO_CAMELS = ((1000.0, -700.0, 1300.0), (2000.0, -700.0, 1300.0))
FAR_RAYS = 1024
#: A kernel whose rounding is relative to |v - o|, wherever the scene sits (the
#: plane-and-barycentric kernel's grows with the world coordinates: see ``accel.grid``);
#: watertight runs on the far camels under every structure in tests/test_anywhere.py.
FAR_KERNELS = ("moller_trumbore",)


def transformed(vertices, offset, scale) -> np.ndarray:
    return (np.asarray(vertices, np.float64) * scale + np.asarray(offset)).astype(np.float32)


@pytest.fixture(scope="module")
def far_scenes(camel19k):
    """name -> (vertices, faces, origins, directions): the transformed camels, with
    incoherent rays aimed at them, and the two camels, with rays aimed at each and rays
    from around each aimed at the other (a travel of 1e3)."""
    faces = np.asarray(camel19k.faces)
    scenes = {}
    for seed, (name, (offset, scale)) in enumerate(TRANSFORMS.items()):
        vertices = transformed(camel19k.vertices, offset, scale)
        scenes[name] = (vertices, faces, *incoherent_set(vertices, FAR_RAYS, seed=seed))
    a, b = (transformed(camel19k.vertices, offset, 1.0) for offset in TWO_CAMELS)
    quarter = FAR_RAYS // 4
    rng = np.random.default_rng(7)
    origins, directions = [], []
    for k, (here, there) in enumerate(((a, b), (b, a))):
        o, d = incoherent_set(here, quarter, seed=10 + k)
        origins += [o, o]
        target = there[rng.integers(0, len(there), quarter)].astype(np.float64)
        across = target - o
        directions += [d, (across / np.linalg.norm(across, axis=1, keepdims=True))]
    scenes["two camels"] = (np.concatenate([a, b]), np.concatenate([faces, faces + len(a)]),
                            np.concatenate(origins).astype(np.float32),
                            np.concatenate(directions).astype(np.float32))
    return scenes


@pytest.fixture(scope="module")
def far_grids(far_scenes):
    return {name: accel.build("grid", v, f) for name, (v, f, _, _) in far_scenes.items()}


@pytest.mark.parametrize("name", list(TRANSFORMS))
def test_far_or_scaled_camel_builds_the_grid_of_the_origin(camel19k, far_scenes, far_grids,
                                                           name):
    """Moved 1e3 or 1e5 times its size away, or scaled by 1e-4 or 1e4, the camel builds the
    grid it builds at the origin: the same cells, about as many references (a margin that
    grew with the distance from the coordinate origin multiplied them: 6x at 1e3 on the
    69k camel), and the layout and the reference rule hold in the grid's frame."""
    offset, scale = TRANSFORMS[name]
    vertices, faces = far_scenes[name][:2]
    s = far_grids[name]
    if scale == 1.0:  # the same float32 mesh, moved back to the origin (exactly)
        base = (vertices.astype(np.float64) - offset).astype(np.float32)
        np.testing.assert_array_equal(base.astype(np.float64) + offset, vertices)
        assert np.all(np.abs(s["frame"]) >= 0.5 * np.abs(offset))
    else:
        base = camel19k.vertices
        np.testing.assert_array_equal(s["frame"], 0)  # the camel's box holds the origin
    at_origin = accel.build("grid", base, faces)
    assert s.num_triangles == at_origin.num_triangles
    assert s.stats["resolution"] == at_origin.stats["resolution"]
    for key in ("references", "non_empty_cells"):
        assert s.stats[key] == pytest.approx(at_origin.stats[key], rel=0.02), key
    # The grid row holds local coordinates: of the scene's size, not of its position.
    g = s["grid"].astype(np.float64)
    extent = g[3:6] - g[0:3]
    assert np.abs(g[0:6]).max() <= 1.01 * extent.max()
    np.testing.assert_allclose(extent, (at_origin["grid"][3:6] - at_origin["grid"][0:3])
                               * scale, rtol=1e-3)
    layout = check_structure(s, vertices, faces)
    rng = np.random.default_rng(0)
    cells = np.union1d(rng.choice(np.flatnonzero(layout["counts"]), 100, replace=False),
                       rng.choice(layout["cells"], 50, replace=False))
    check_references(s, cells)
    check_skip(s, rng.choice(layout["cells"], 1000, replace=False))


def fixed_shape_scenes(far_grids):
    """Grids and brute forces of the far scenes padded to shared shapes: every scene runs
    the same compiled kernels."""
    triangle_cap = max(s.num_triangles for s in far_grids.values())
    cell_cap = max(s["cell_start"].shape[0] - 1 for s in far_grids.values())
    reference_cap = max(s["references"].shape[0] for s in far_grids.values())
    out = {}
    for name, s in far_grids.items():
        t = s.num_triangles
        triangles = np.zeros((triangle_cap, 3, 3), np.float32)
        triangles[:t] = s["triangles"]
        ids = np.arange(triangle_cap, dtype=np.int32) + 10 * triangle_cap  # never hit
        ids[:t] = s["triangle_ids"]
        brute = Structure(kind="brute", arrays={"triangles": triangles, "triangle_ids": ids})
        out[name] = (fixed_shape_grid(s, cell_cap, reference_cap, triangle_cap), brute)
    return out


@pytest.fixture(scope="module")
def far_padded(far_grids):
    return fixed_shape_scenes(far_grids)


@pytest.mark.parametrize("kernel", FAR_KERNELS)
@pytest.mark.parametrize("name", [*TRANSFORMS, "two camels"])
def test_far_or_scaled_camel_hits_match_brute(far_scenes, far_padded, name, kernel):
    """Brute force's hits, bit for bit, on the moved and scaled camels and on two camels 1e3
    apart (rays aimed at each, and from around each at the other)."""
    origins, directions = far_scenes[name][2:]
    padded, brute = far_padded[name]
    want = as_numpy(jrt.closest_hit(brute, origins, directions, kernel=kernel))
    got = as_numpy(jrt.closest_hit(padded, origins, directions, kernel=kernel))
    assert (want["triangle"] >= 0).mean() > 0.2
    assert_same_hits(got, want, origins, directions, f"grid {kernel}/{name}")


# ---------------------------------------------------------------------------------------------
# Random soups (hypothesis): flat triangles on cell faces, origins on faces and corners
# ---------------------------------------------------------------------------------------------


def fixed_shape_grid(structure: Structure, cell_cap: int = CELL_CAP,
                     reference_cap: int = REFERENCE_CAP, triangle_cap: int = CAP) -> Structure:
    """The same grid with ``cell_cap`` cells, ``reference_cap`` references and
    ``triangle_cap`` triangles (the cells beyond the grid are never addressed)."""
    cells = structure["cell_start"].shape[0] - 1
    references = structure["references"]
    assert cells <= cell_cap and references.shape[0] <= reference_cap
    starts = np.full(cell_cap + 1, structure["cell_start"][-1], np.int32)
    starts[:cells + 1] = structure["cell_start"]
    skip = np.zeros(cell_cap, np.int8)
    skip[:cells] = structure["skip"]
    refs = np.zeros(reference_cap, np.int32)
    refs[:references.shape[0]] = references
    t = structure.num_triangles
    triangles = np.zeros((triangle_cap, 3, 3), np.float32)
    triangles[:t] = structure["triangles"]
    ids = np.full(triangle_cap, -1, np.int32)
    ids[:t] = structure["triangle_ids"]
    return Structure(kind="grid", arrays={
        "grid": structure["grid"], "cell_start": starts, "skip": skip, "references": refs,
        "triangles": triangles, "triangle_ids": ids, "frame": structure["frame"]},
        stats=structure.stats)


def onto_cell_faces(rng, vertices, faces, params):
    """The soup with its axis-aligned flat triangles moved exactly onto cell faces and a
    few replaced by large flat triangles on cell faces (spanning many cells), keeping the
    grid (its bounds, frame and triangle count); returns the vertices and the grid's
    planes in world coordinates (those that ``plane + frame`` represents exactly, so
    that the moved triangles lie exactly on cell faces in the grid's frame too)."""
    first = accel.build("grid", vertices, faces, **params)
    frame = first["frame"]
    planes = world_planes(planes_of(first), frame)
    tri = vertices[faces].copy()
    if first.num_triangles:  # the bounds in world coordinates
        lo, hi = first["triangles"].min(axis=(0, 1)), first["triangles"].max(axis=(0, 1))
    else:
        lo = hi = np.zeros(3, np.float32)
    keep = np.zeros(len(faces), bool)
    keep[expected_ids(vertices, faces)] = True
    # Triangles that hold the box's bounds stay where they are.
    movable = keep & ~np.any((tri == lo) | (tri == hi), axis=(1, 2))
    inner = world_planes([p[1:-1] for p in planes_of(first)], frame)
    flat = np.all(tri == tri[:, :1], axis=1)  # [n, 3]: flat on that axis
    for row in np.flatnonzero(movable & flat.any(axis=1)):
        axis = int(np.flatnonzero(flat[row])[0])
        if inner[axis].size:
            tri[row, :, axis] = inner[axis][rng.integers(0, inner[axis].size)]
    extent = hi - lo
    for row in rng.permutation(np.flatnonzero(movable))[:4]:
        axis = int(rng.integers(0, 3))
        u, v = (axis + 1) % 3, (axis + 2) % 3
        if not inner[axis].size or extent[u] == 0 or extent[v] == 0:
            continue
        big = np.zeros((3, 3), np.float32)
        big[:, axis] = inner[axis][rng.integers(0, inner[axis].size)]
        big[:, u] = lo[u] + np.float32([0.1, 0.9, 0.1]) * extent[u]
        big[:, v] = lo[v] + np.float32([0.1, 0.1, 0.9]) * extent[v]
        tri[row] = big
    moved = tri.reshape(-1, 3)
    second = accel.build("grid", moved, faces, **params)
    np.testing.assert_array_equal(second["grid"], first["grid"])
    np.testing.assert_array_equal(second["frame"], frame)
    return moved, planes


def on_faces_and_corners(rng, vertices, faces, planes, origins, directions):
    """Rays from origins exactly on cell faces, at grid corners, and inside cell faces."""
    origins, directions = origins.copy(), directions.copy()
    n = len(origins)
    kind = rng.integers(0, 4, n)
    # 0: one origin coordinate on a cell face (the box's faces included).
    rows = np.flatnonzero(kind == 0)
    axis = rng.integers(0, 3, rows.size)
    for a in range(3):
        sel = rows[axis == a]
        origins[sel, a] = planes[a][rng.integers(0, planes[a].size, sel.size)]
    # 1: at a grid corner, aimed at a triangle's corner or axis-parallel.
    rows = np.flatnonzero(kind == 1)
    for a in range(3):
        origins[rows, a] = planes[a][rng.integers(0, planes[a].size, rows.size)]
    target = vertices[faces[rng.integers(0, len(faces), rows.size), rng.integers(0, 3, rows.size)]]
    d = target.astype(np.float64) - origins[rows]
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-30)
    d[np.all(d == 0, axis=1)] = [0, 0, 1]
    parallel = rng.random(rows.size) < 0.3
    d[parallel] = signed_zeros(rng, (parallel.sum(), 3))
    d[parallel, rng.integers(0, 3, parallel.sum())] = np.where(
        rng.random(parallel.sum()) < 0.5, 1, -1)
    directions[rows] = d
    # 2: inside a cell face: origin and target in the face, direction 0 on its axis. The
    # target: a point (a corner for half of them) of a flat triangle, in that triangle's
    # plane (a cell face, see onto_cell_faces), or of any triangle, in a random face.
    rows = np.flatnonzero(kind == 2)
    tri = vertices[faces]
    flat = np.all(tri == tri[:, :1], axis=1)
    flat_rows = np.flatnonzero(flat.any(axis=1))
    pick = (flat_rows[rng.integers(0, flat_rows.size, rows.size)] if flat_rows.size
            else rng.integers(0, len(faces), rows.size))
    b = rng.dirichlet(np.ones(3), rows.size)
    b[: rows.size // 2] = np.eye(3)[rng.integers(0, 3, rows.size // 2)]
    target = np.einsum("nk,nkj->nj", b, tri[pick].astype(np.float64)).astype(np.float32)
    axis = np.where(flat[pick].any(axis=1), np.argmax(flat[pick], axis=1),
                    rng.integers(0, 3, rows.size))
    plane = np.where(flat[pick].any(axis=1), tri[pick, 0, axis], np.array(
        [planes[a][rng.integers(0, planes[a].size)] for a in axis], np.float32))
    start = target + rng.normal(size=(rows.size, 3)).astype(np.float32)
    start[np.arange(rows.size), axis] = plane
    target[np.arange(rows.size), axis] = plane
    d = target.astype(np.float64) - start
    d[np.arange(rows.size), axis] = 0
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-30)
    d = d.astype(np.float32)
    d[np.arange(rows.size), axis] = signed_zeros(rng, rows.size)
    d[np.all(d == 0, axis=1)] = [1, 0, 0]
    origins[rows], directions[rows] = start, d
    return origins, directions.astype(np.float32)


@st.composite
def grid_soups(draw):
    """(vertices, faces, build parameters, origins, directions, rng) of one example."""
    seed = draw(st.integers(0, 2**32 - 1))
    n = draw(st.integers(10, CAP))
    on_lattice = draw(st.booleans())
    flat = draw(st.sampled_from([0.3, 1.0]))
    duplicates = draw(st.sampled_from([0.0, 0.1]))
    shared = draw(st.sampled_from([0.0, 0.5]))
    params = {
        "density": draw(st.sampled_from([0.5, 2.0, 8.0, 40.0])),
        "max_skip": draw(st.sampled_from([0, 2, 16])),
        "max_resolution": draw(st.sampled_from([3, 512])),
    }
    rng = np.random.default_rng(seed)
    vertices, faces = soup(rng, n, grid=on_lattice, flat=flat, duplicates=duplicates,
                           shared=shared)
    vertices, planes = onto_cell_faces(rng, vertices, faces, params)
    origins, directions = rays(rng, vertices, faces)
    origins, directions = on_faces_and_corners(rng, vertices, faces, planes, origins,
                                               directions)
    return vertices, faces, params, origins, directions, rng


def soup_structures(case):
    vertices, faces, params, origins, directions, rng = case
    unpadded = accel.build("brute", vertices, faces)
    structure = accel.build("grid", vertices, faces, **params)
    scale = float(np.abs(vertices).max()) * 4
    return (params, unpadded, structure, fixed_shape_grid(structure),
            fixed_shape_brute(unpadded), scale, origins, directions, rng)


@PROPERTY
@given(case=grid_soups())
def test_soup_build_is_consistent(case):
    vertices, faces, params = case[:3]
    structure = accel.build("grid", vertices, faces, **params)
    check_structure(structure, vertices, faces)
    check_references(structure)
    check_skip(structure)


@PROPERTY
@given(case=grid_soups())
def test_soup_closest_hit_matches_brute(case):
    params, unpadded, _, padded, brute, scale, origins, directions, rng = soup_structures(case)
    check_closest_hit_matches_brute(padded, brute, unpadded, origins, directions, rng, scale,
                                    f"grid {params}")


@PROPERTY
@given(case=grid_soups())
def test_soup_occluded_matches_brute(case):
    params, unpadded, _, padded, brute, scale, origins, directions, rng = soup_structures(case)
    check_occluded_matches_brute(padded, brute, unpadded, origins, directions, rng, scale,
                                 f"grid {params}")
