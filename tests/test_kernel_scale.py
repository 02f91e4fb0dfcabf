"""``watertight`` stays watertight at every scale: no ray from inside the closed camel misses.

The crack this guards against: pbrt-v4's rejection of hits below its error bound on t
(``t > δt``, section 6.8.7) rejected hits on the camel's slivers (one edge about 1e-4 of the
others) hundreds of units away, where ``δt`` exceeded ``t`` itself. A ray through a sliver's
short edge may hit only the sliver, so the ray went through the mesh. The failure was not
scale-specific; which rays hit it changes with the rounding, hence the sweep over scales.

Every case is built from the float32 scaled mesh (vertices x scale in float64, then cast),
so the aim points are the scaled float32 vertices and edge midpoints themselves.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import accel
import jrt
from benchmarks.stability import strictly_inside
from jrt.kernels import moller_trumbore, watertight

SCALES = (1e-4, 1.0, 1e2, 1e3, 1e4, 1e5)
#: Rays per scale: half aimed at the thinnest triangles' corners and edge midpoints, half at
#: random vertices and edge midpoints of the whole mesh.
RAYS_PER_SCALE = 1024
#: The thinnest triangles by area / longest edge² (the camel's are down to 4.5e-5).
SLIVERS = 64

# The reported case: the camel x 1000, a ray from inside aimed at vertex 28712.
CASE_SCALE = 1e3
CASE_ORIGIN = np.array([-0.024671832, 139.99922, -158.35655], np.float32)
CASE_DIRECTION = np.array([-0.36374733, 0.53204036, -0.76460510], np.float32)
CASE_VERTEX, CASE_FACE = 28712, 47892


def _scaled(camel, scale):
    return (camel.vertices.astype(np.float64) * scale).astype(np.float32)


def _plane_hit64(o, d, tri):
    """t and barycentrics (u, v) of the ray's crossing of the triangle's plane, in float64
    on the float32 inputs (independent of the kernels)."""
    o, d, (a, b, c) = (np.asarray(x, np.float64) for x in (o, d, tri))
    n = np.cross(b - a, c - a)
    t = n @ (a - o) / (n @ d)
    p = o + t * d
    nn = n @ n
    # p - a = u (b - a) + v (c - a), so (p - a) x (c - a) = u n and (b - a) x (p - a) = v n.
    return t, np.cross(p - a, c - a) @ n / nn, np.cross(b - a, p - a) @ n / nn


@pytest.mark.parametrize("x64", [False, True], ids=["float32", "float64"])
def test_sliver_hit_hundreds_of_units_away(camel, x64):
    """The reported case: ``watertight`` missed every triangle, while Möller–Trumbore hits
    face 47892 (a sliver: u = 0.98, v = 6e-6) at t = 348.306."""
    v32 = _scaled(camel, CASE_SCALE)
    faces = camel.faces
    assert CASE_VERTEX in faces[CASE_FACE]
    t64, u64, v64 = _plane_hit64(CASE_ORIGIN, CASE_DIRECTION, v32[faces[CASE_FACE]])
    # The ray does cross the face (float64, same float32 inputs), near its corner 28712.
    assert 348 < t64 < 349 and 0 < v64 < 1e-4 and 0.9 < u64 < 1, (t64, u64, v64)

    dtype = np.float64 if x64 else np.float32
    with jax.enable_x64(x64):
        tri = jnp.asarray(v32[faces].astype(dtype))
        o = jnp.asarray(CASE_ORIGIN.astype(dtype))[None]
        d = jnp.asarray(CASE_DIRECTION.astype(dtype))[None]
        args = (o, d, tri[:, 0], tri[:, 1], tri[:, 2])
        t_mt = np.asarray(jax.jit(moller_trumbore)(*args)[0])
        t, u, v = (np.asarray(a) for a in jax.jit(watertight)(*args))
    assert t.dtype == dtype
    assert not np.isnan(t).any() and not np.isnan(u).any() and not np.isnan(v).any()
    assert np.argmin(t_mt) == CASE_FACE
    best = int(np.argmin(t))
    assert np.isfinite(t[best]), "watertight misses every triangle"
    # The same face, or a neighbour around the aimed vertex tied with it.
    assert best == CASE_FACE or CASE_VERTEX in faces[best], (best, faces[best])
    np.testing.assert_allclose(t[best], t_mt[CASE_FACE], rtol=1e-5)
    np.testing.assert_allclose(t[best], t64, rtol=1e-5)
    # The face itself is hit (its edge functions agree; the hit is 348 units ahead).
    assert np.isfinite(t[CASE_FACE])
    np.testing.assert_allclose(t[CASE_FACE], t64, rtol=1e-5)


@pytest.fixture(scope="module")
def sweep_rays(camel):
    """Interior origins (winding number near 1, at scale 1) and per-ray targets: (kind,
    index) pairs, a vertex or an edge (its midpoint), half on the thinnest triangles."""
    rng = np.random.default_rng(11)
    v64, faces = camel.vertices.astype(np.float64), camel.faces
    lo, hi = v64.min(axis=0), v64.max(axis=0)
    candidates = lo + rng.uniform(size=(12 * RAYS_PER_SCALE, 3)) * (hi - lo)
    interior = candidates[strictly_inside(v64, faces, candidates)][:RAYS_PER_SCALE]
    assert len(interior) == RAYS_PER_SCALE

    corners = v64[faces]
    area2 = np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0],
                                    corners[:, 2] - corners[:, 0]), axis=1)
    longest = np.linalg.norm(corners - np.roll(corners, 1, axis=1), axis=2).max(axis=1)
    thin = faces[np.argsort(area2 / longest**2)[:SLIVERS]]

    def edges(f):
        e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
        return np.unique(np.sort(e, axis=1), axis=0)

    half, quarter = RAYS_PER_SCALE // 2, RAYS_PER_SCALE // 4
    all_edges, thin_edges, thin_vertices = edges(faces), edges(thin), np.unique(thin)
    vertex_targets = np.concatenate([rng.choice(thin_vertices, quarter),
                                     rng.choice(len(v64), half - quarter)])
    edge_targets = np.concatenate([thin_edges[rng.choice(len(thin_edges), quarter)],
                                   all_edges[rng.choice(len(all_edges), half - quarter)]])
    return interior, vertex_targets, edge_targets


@pytest.mark.parametrize("scale", SCALES, ids=[f"{s:g}" for s in SCALES])
def test_no_cracks_at_any_scale(camel, sweep_rays, scale):
    """Brute force: every ray from inside aimed at a vertex or an edge midpoint of the
    float32 scaled camel hits it."""
    interior, vertex_targets, edge_targets = sweep_rays
    v32 = _scaled(camel, scale)
    half = np.float32(0.5)
    targets = np.concatenate([v32[vertex_targets],
                              (v32[edge_targets[:, 0]] + v32[edge_targets[:, 1]]) * half])
    origins = (interior * scale).astype(np.float32)
    aim = targets.astype(np.float64) - origins
    directions = (aim / np.linalg.norm(aim, axis=1, keepdims=True)).astype(np.float32)

    structure = accel.build("brute", v32, camel.faces)
    hits = jrt.trace.as_numpy(jrt.closest_hit(structure, origins, directions,
                                              kernel="watertight"))
    missed = np.flatnonzero(hits["triangle"] < 0)
    assert missed.size == 0, (f"{missed.size} of {len(origins)} rays from inside miss at "
                              f"scale {scale:g}: {missed[:8].tolist()}")
    assert not np.isnan(hits["t"]).any()
