"""``jrt.refit``: a structure moved with its mesh, without a rebuild.

Against brute force built on the moved mesh (every kernel, closest hit and any hit, bit
for bit), against the builder (refit to the unmoved vertices gives the built node rows),
against exact float64 boxes (every decoded child box holds the triangles below it), and
for the derivative it carries to the vertices (the float64 implicit derivative).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import accel
import jrt
from accel.bvh import EMPTY_SLOT, child_boxes, child_references
from benchmarks.refit import moved
from jrt.raysets import incoherent_set
from jrt.trace import as_numpy

RAYS = 1024


@pytest.fixture(scope="module")
def camel(camel19k):
    return camel19k.vertices, camel19k.faces, camel19k.diagonal


@pytest.fixture(scope="module")
def bvh(camel):
    return accel.build("bvh", camel[0], camel[1])


def subtree_boxes(structure):
    """Exact float64 boxes [K, W, 3] of every child of every node (the triangles below
    it), by a bottom-up pass over the rows in NumPy: independent of ``jrt.refit``."""
    width = structure.layout_value("width")
    bits = structure.layout_value("leaf_bits")
    refs = child_references(np.asarray(structure["nodes"]), width)
    tris = np.asarray(structure["triangles"], np.float64)
    lo = np.full(refs.shape + (3,), np.inf)
    hi = np.full(refs.shape + (3,), -np.inf)
    for row in range(len(refs) - 1, -1, -1):  # children come after their parents
        for c, ref in enumerate(refs[row]):
            if ref == EMPTY_SLOT:
                continue
            if ref >= 0:
                lo[row, c], hi[row, c] = lo[ref].min(axis=0), hi[ref].max(axis=0)
            else:
                first, count = (~ref) >> bits, (~ref) & ((1 << bits) - 1)
                block = tris[first:first + count].reshape(-1, 3)
                lo[row, c], hi[row, c] = block.min(axis=0), block.max(axis=0)
    return lo, hi, refs != EMPTY_SLOT


def assert_boxes_hold_their_triangles(structure):
    width = structure.layout_value("width")
    lo, hi, filled = subtree_boxes(structure)
    got_lo, got_hi = child_boxes(np.asarray(structure["nodes"]), width)
    frame = np.asarray(structure["frame"], np.float64)
    assert ((got_lo + frame <= lo) | ~filled[..., None]).all()
    assert ((got_hi + frame >= hi) | ~filled[..., None]).all()


def test_refit_to_the_same_vertices_gives_the_built_rows(bvh, camel):
    out = jrt.refit(bvh, camel[0], camel[1])
    for name in ("nodes", "triangles", "triangle_ids", "frame"):
        np.testing.assert_array_equal(np.asarray(out[name]), np.asarray(bvh[name]), name)
    assert out.layout == bvh.layout and out.kind == "bvh"


@pytest.mark.parametrize("shift,scale", [(0.0, 1.0), (1e3, 1.0), (-50.0, 1e-3)],
                         ids=["jitter", "far", "small"])
def test_hits_on_the_moved_mesh_are_brute_forces(bvh, camel, shift, scale):
    """Jittered, rotated, scaled and moved away (the frame moves with it): every kernel's
    closest hits and any hits on the refit BVH equal brute force's on the moved mesh."""
    vertices, faces, diagonal = camel
    new = moved(vertices, diagonal, seed=int(shift) % 7, shift=shift, scale=scale)
    refit = jax.jit(jrt.refit)(bvh, new, faces)
    assert_boxes_hold_their_triangles(refit)
    brute = accel.build("brute", new, faces)
    origins, directions = incoherent_set(new, RAYS, seed=5)
    tmax = np.full(RAYS, np.float32(0.4 * diagonal * scale))
    for kernel in jrt.KERNELS:
        got = as_numpy(jrt.closest_hit(refit, origins, directions, kernel=kernel))
        want = as_numpy(jrt.closest_hit(brute, origins, directions, kernel=kernel))
        for field in want:
            np.testing.assert_array_equal(got[field], want[field], f"{kernel} {field}")
        assert (want["triangle"] >= 0).sum() > RAYS // 5
        np.testing.assert_array_equal(
            np.asarray(jrt.occluded(refit, origins, directions, tmax=tmax, kernel=kernel)),
            np.asarray(jrt.occluded(brute, origins, directions, tmax=tmax, kernel=kernel)))


@pytest.mark.parametrize("width", [2, 8])
def test_every_width_refits(camel, width):
    vertices, faces, diagonal = camel
    structure = accel.build("bvh", vertices, faces, width=width)
    new = moved(vertices, diagonal, seed=width)
    refit = jrt.refit(structure, new, faces)
    assert_boxes_hold_their_triangles(refit)
    origins, directions = incoherent_set(new, RAYS, seed=6)
    got = as_numpy(jrt.closest_hit(refit, origins, directions))
    want = as_numpy(jrt.closest_hit(accel.build("brute", new, faces), origins, directions))
    for field in want:
        np.testing.assert_array_equal(got[field], want[field], field)


def test_brute_force_refits(camel):
    vertices, faces, diagonal = camel
    new = moved(vertices, diagonal, seed=3)
    out = jrt.refit(accel.build("brute", vertices, faces), new, faces)
    np.testing.assert_array_equal(np.asarray(out["triangles"]),
                                  np.asarray(accel.build("brute", new, faces)["triangles"]))


def test_the_derivative_reaches_the_vertices(bvh, camel):
    """d(sum of t)/d(vertices) through refit: each hit's float64 implicit derivative with
    respect to its triangle's corners (dt/dv0 = -(1-u-v) e, dt/dv1 = -u e, dt/dv2 = -v e,
    e the first row of A^-1, A = [-d, v1 - v0, v2 - v0]), summed onto the vertices."""
    vertices, faces, _ = camel
    origins, directions = incoherent_set(vertices, RAYS, seed=8)

    def loss(v):
        h = jrt.closest_hit(jrt.refit(bvh, v, faces), origins, directions)
        return jnp.sum(jnp.where(h.triangle >= 0, h.t, 0))

    got = np.asarray(jax.grad(loss)(jnp.asarray(vertices)))
    hits = as_numpy(jrt.closest_hit(bvh, origins, directions))
    hit = hits["triangle"] >= 0
    face = faces[hits["triangle"][hit]]
    tri = vertices.astype(np.float64)[face]
    d = directions[hit].astype(np.float64)
    a = np.stack([-d, tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]], axis=2)
    x = np.linalg.solve(a, (origins[hit] - tri[:, 0])[..., None])[..., 0]
    first = np.linalg.inv(a)[:, 0, :]
    u, v = x[:, 1:2], x[:, 2:3]
    want = np.zeros(vertices.shape)
    for corner, weight in enumerate((-(1 - u - v), -u, -v)):
        np.add.at(want, face[:, corner], weight * first)
    assert np.isfinite(got).all()
    scale = np.abs(want).max()
    assert np.abs(got - want).max() < 1e-3 * scale
    untouched = np.setdiff1d(np.arange(len(vertices)), face)
    assert np.all(got[untouched] == 0)


@pytest.mark.parametrize("kind", ["kdtree", "octree", "bsp", "grid"])
def test_spatial_subdivisions_say_to_rebuild(kind):
    v = np.float32([[0, 0, 0], [1, 0, 0], [0, 1, 0]])
    f = np.int32([[0, 1, 2]])
    with pytest.raises(ValueError, match=rf"a {kind} cannot be refit.*accel.build\('{kind}'"):
        jrt.refit(accel.build(kind, v, f), v, f)


def test_bad_inputs_are_named(bvh, camel):
    vertices, faces, _ = camel
    with pytest.raises(ValueError, match=r"vertices must have shape \[V, 3\]"):
        jrt.refit(bvh, vertices[:, :2], faces)
    with pytest.raises(ValueError, match=r"faces must be integers of shape \[F, 3\]"):
        jrt.refit(bvh, vertices, faces.astype(np.float32))
    with pytest.raises(ValueError, match="faces index vertices 0..9"):
        jrt.refit(bvh, vertices[:10], faces)
    with pytest.raises(ValueError, match="pass the faces the structure was built from"):
        jrt.refit(bvh, vertices, faces[:100])
    bad = vertices.copy()
    bad[7, 1] = np.nan
    with pytest.raises(ValueError, match="vertex 7 is not finite"):
        jrt.refit(bvh, bad, faces)
    with pytest.raises(TypeError, match="structure from accel.build"):
        jrt.refit({"nodes": 1}, vertices, faces)
