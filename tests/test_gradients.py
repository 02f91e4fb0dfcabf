"""Derivatives of the closest hit's ``t, u, v`` (``jrt.hit_derivatives``), against the
implicit derivative of the ray–plane system in float64.

Reference: ``A x = o - v0`` with ``A = [-d, v1 - v0, v2 - v0]`` (columns) and
``x = (t, u, v)``; differentiating the system (``dA x + A dx = do - dv0``) gives, per
input, ``dx/do = A^-1``, ``dx/dd = t A^-1``, ``dx/dv0 = -(1-u-v) A^-1``,
``dx/dv1 = -u A^-1``, ``dx/dv2 = -v A^-1``, all in float64 from the float64 triangle and
ray. jrt's forward mode
(``jax.jvp``), reverse mode (``jax.grad``) and ``jax.jacfwd`` must agree with it to 1e-3
(relative, on rays whose system is not ill-conditioned), under the BVH and brute force;
a miss has a zero, finite derivative, and ``occluded`` passes no derivative. On the 19k
camel and on a random soup of overlapping triangles.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import accel
import jrt
from jrt.raysets import incoherent_set

RAYS = 1024  # one size bucket
#: Rays whose float64 system has a condition number above this are left out of the 1e-3
#: comparison (a grazing ray's derivative is large and float32 loses digits on it).
CONDITION = 1e3
INPUTS = ("origins", "directions", "v0", "v1", "v2")


@pytest.fixture(scope="module")
def scene(camel19k):
    origins, directions = incoherent_set(camel19k.vertices, RAYS, seed=11)
    return {"mesh": camel19k, "origins": origins, "directions": directions,
            "bvh": accel.build("bvh", camel19k.vertices, camel19k.faces),
            "brute": accel.build("brute", camel19k.vertices, camel19k.faces)}


@pytest.fixture(scope="module")
def soup():
    """400 random triangles (sides up to half the cube) in the unit cube, seen by rays
    from a sphere around it: overlapping, of every orientation and aspect."""
    rng = np.random.default_rng(12)
    centres = rng.uniform(0.2, 0.8, (400, 1, 3))
    vertices = (centres + rng.uniform(-0.25, 0.25, (400, 3, 3))).reshape(-1, 3)
    mesh = jrt.mesh_from_arrays(vertices.astype(np.float32),
                                np.arange(1200, dtype=np.int32).reshape(400, 3))
    origins, directions = incoherent_set(mesh.vertices, RAYS, seed=13)
    return {"mesh": mesh, "origins": origins, "directions": directions,
            "bvh": accel.build("bvh", mesh.vertices, mesh.faces),
            "brute": accel.build("brute", mesh.vertices, mesh.faces)}


def reference(mesh, origins, directions, triangle):
    """float64 (t, u, v) [N, 3] and d(t, u, v)/d(input) [N, 3, 3] per input of INPUTS,
    and the condition number of each ray's system (implicit differentiation)."""
    tri = mesh.vertices.astype(np.float64)[mesh.faces[triangle]]
    o, d = origins.astype(np.float64), directions.astype(np.float64)
    a = np.stack([-d, tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]], axis=2)  # columns
    x = np.linalg.solve(a, (o - tri[:, 0])[..., None])[..., 0]
    inv = np.linalg.inv(a)
    t, u, v = x[:, 0, None, None], x[:, 1, None, None], x[:, 2, None, None]
    jac = {"origins": inv, "directions": t * inv, "v0": -(1 - u - v) * inv, "v1": -u * inv,
           "v2": -v * inv}
    return x, jac, np.linalg.cond(a)


def _structure_with(structure, triangles):
    return accel.Structure(structure.kind, dict(structure.arrays, triangles=triangles),
                           structure.layout)


@pytest.mark.parametrize("meshes", ["camel", "soup"])
@pytest.mark.parametrize("kind", ["bvh", "brute"])
def test_forward_and_reverse_derivatives_match_the_float64_implicit_derivative(
        request, meshes, kind):
    scene = request.getfixturevalue("scene" if meshes == "camel" else "soup")
    structure, mesh = scene[kind], scene["mesh"]
    o, d = scene["origins"], scene["directions"]
    tris = jnp.asarray(structure["triangles"])

    @jax.jit
    def tangents(o_dot, d_dot, tri_dot):
        def f(o, d, tris):
            h = jrt.closest_hit(_structure_with(structure, tris), o, d)
            return jnp.stack([h.t, h.u, h.v], axis=1)
        return jax.jvp(f, (o, d, tris), (o_dot, d_dot, tri_dot))

    hits = jrt.closest_hit(structure, o, d)
    hit = np.asarray(hits.triangle) >= 0
    x, jac, cond = reference(mesh, o[hit], d[hit], np.asarray(hits.triangle)[hit])
    good = cond < CONDITION
    assert good.sum() > 0.9 * hit.sum() and hit.sum() > 200
    # Norm-wise relative error per ray: against the largest entry of its whole Jacobian
    # (a single entry may be a small difference, (1 - u - v) near an edge, that float32
    # evaluates to its absolute, not its relative, precision).
    ray_scale = np.max([np.abs(j).max(axis=(1, 2)) for j in jac.values()], axis=0)[:, None]
    zero_r, zero_t = np.zeros_like(o), np.zeros_like(np.asarray(tris))
    for name in INPUTS:
        for axis in range(3):
            unit = np.zeros(3, np.float32)
            unit[axis] = 1
            if name in ("origins", "directions"):
                ray_dot = np.broadcast_to(unit, o.shape).astype(np.float32)
                args = (ray_dot, zero_r, zero_t) if name == "origins" else (
                    zero_r, ray_dot, zero_t)
            else:
                tri_dot = zero_t.copy()
                tri_dot[:, INPUTS.index(name) - 2, axis] = 1
                args = (zero_r, zero_r, tri_dot)
            primal, tangent = (np.asarray(a) for a in tangents(*args))
            np.testing.assert_allclose(primal[hit][good], x[good], rtol=1e-3, atol=1e-4)
            want = jac[name][:, :, axis]  # [N, 3]: d(t, u, v) / d(input[axis])
            error = np.abs(tangent[hit] - want) / ray_scale
            assert error[good].max() < 1e-3, (kind, name, axis, error[good].max())
            assert np.all(tangent[~hit] == 0), (kind, name, axis)

    # Reverse mode: the gradient of a weighted sum of t gives each ray's own row.
    weights = np.random.default_rng(0).uniform(0.5, 1.5, len(o)).astype(np.float32)

    def loss(o, d, tris):
        h = jrt.closest_hit(_structure_with(structure, tris), o, d)
        return jnp.sum(jnp.where(h.triangle >= 0, h.t, 0) * weights)

    g_o, g_d, g_tri = (np.asarray(g) for g in jax.grad(loss, argnums=(0, 1, 2))(o, d, tris))
    for g, name in ((g_o, "origins"), (g_d, "directions")):
        want = weights[hit, None] * jac[name][:, 0, :]
        error = np.abs(g[hit] - want) / (ray_scale * weights[hit, None])
        assert error[good].max() < 1e-3, name
        assert np.all(g[~hit] == 0)
    assert np.isfinite(g_tri).all()
    # The triangle rows' gradient: the rays' contributions summed per row.
    row_of_face = np.empty(len(mesh.faces), np.int64)
    row_of_face[np.asarray(structure["triangle_ids"])] = np.arange(len(g_tri))
    want_tri = np.zeros(g_tri.shape, np.float64)
    rows = row_of_face[np.asarray(hits.triangle)[hit]]
    for c, name in enumerate(INPUTS[2:]):
        np.add.at(want_tri[:, c], rows, weights[hit, None] * jac[name][:, 0, :])
    touched = np.zeros(len(g_tri), bool)
    touched[rows] = True
    np.testing.assert_allclose(g_tri[~touched], 0)
    bad_rows = np.unique(rows[~good])
    check = touched.copy()
    check[bad_rows] = False
    row_scale = np.zeros(len(g_tri))
    np.maximum.at(row_scale, rows, ray_scale[:, 0] * weights[hit])
    error = np.abs(g_tri - want_tri).max(axis=(1, 2)) / np.where(check, row_scale, 1)
    assert error[check].max() < 1e-3


def test_jacfwd_and_vmap_give_each_rays_own_derivative(scene):
    """``jax.jacfwd`` of u with respect to the origins of 16 rays: diagonal blocks, each
    the float64 derivative; and ``jax.vmap`` of ``jax.grad`` over two ray sets equals the
    gradients taken one set at a time."""
    structure, mesh = scene["bvh"], scene["mesh"]
    hits = jrt.closest_hit(structure, scene["origins"], scene["directions"])
    hit = np.flatnonzero(np.asarray(hits.triangle) >= 0)[:16]
    o, d = scene["origins"][hit], scene["directions"][hit]
    jac = np.asarray(jax.jacfwd(lambda o: jrt.closest_hit(structure, o, d).u)(o))  # [16,16,3]
    _, want, cond = reference(mesh, o, d, np.asarray(hits.triangle)[hit])
    assert (cond < CONDITION).all()
    for i in range(16):
        off = np.delete(jac[i], i, axis=0)
        assert np.all(off == 0)
        scale = max(np.abs(j[i]).max() for j in want.values())
        assert np.abs(jac[i, i] - want["origins"][i, 1]).max() < 1e-3 * scale

    def loss(o):
        h = jrt.closest_hit(structure, o, d)
        return jnp.sum(jnp.where(h.triangle >= 0, h.t, 0))

    batch = np.stack([o, o + np.float32(1e-3)])
    both = np.asarray(jax.vmap(jax.grad(loss))(batch))
    for k in range(2):
        np.testing.assert_array_equal(both[k], np.asarray(jax.grad(loss)(batch[k])))


def test_misses_and_occluded_pass_no_derivative(scene):
    """Rays that miss everything have exactly zero derivatives with respect to the rays
    and every triangle row (row 0 included, never NaN); ``occluded`` inside a loss adds
    nothing to its gradient and breaks nothing."""
    structure, mesh = scene["bvh"], scene["mesh"]
    lo, hi = mesh.vertices.min(axis=0), mesh.vertices.max(axis=0)
    away = np.tile((hi + (hi - lo)).astype(np.float32), (RAYS, 1))
    up = np.tile(np.float32([0, 0, 1]), (RAYS, 1))  # pointing away from the mesh
    tris = jnp.asarray(structure["triangles"])

    def t_sum(o, tris):
        h = jrt.closest_hit(_structure_with(structure, tris), o, up)
        return jnp.sum(jnp.where(h.triangle >= 0, h.t, 0) + h.u + h.v)

    g_o, g_tri = jax.grad(t_sum, argnums=(0, 1))(away, tris)
    assert np.all(np.asarray(g_o) == 0) and np.all(np.asarray(g_tri) == 0)
    o, d = scene["origins"], scene["directions"]

    def with_mask(o):
        h = jrt.closest_hit(structure, o, d)
        blocked = jrt.occluded(structure, o, d, tmax=np.float32(0.5 * mesh.diagonal))
        return jnp.sum(jnp.where(h.triangle >= 0, h.t, 0)) + jnp.sum(blocked * 1.0)

    def without(o):
        h = jrt.closest_hit(structure, o, d)
        return jnp.sum(jnp.where(h.triangle >= 0, h.t, 0))

    got, want = np.asarray(jax.grad(with_mask)(o)), np.asarray(jax.grad(without)(o))
    assert np.isfinite(got).all() and np.array_equal(got, want)
    assert np.asarray(jax.grad(lambda o: jnp.sum(jrt.occluded(structure, o, d) * 1.0))(o)
                      ).max() == 0
