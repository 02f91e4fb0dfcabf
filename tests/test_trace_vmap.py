"""``jax.vmap`` of the public queries (``jrt.closest_hit``, ``jrt.occluded``): their
``custom_vmap`` rule traces every batch item's rays in one engine call, and each item's
answers equal the call on that item alone, bit for bit (the reference: a loop of plain,
unbatched calls, which pad to a size bucket and run their own compiled program)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.extend import core as jax_core

import accel
import jrt
from jrt.raysets import incoherent_set

B, N = 3, 300
FIELDS = ("t", "triangle", "u", "v")


@pytest.fixture(scope="module")
def structures(camel19k):
    built = {}

    def get(name):
        if name not in built:
            built[name] = accel.build(name, camel19k)
        return built[name]

    return get


@pytest.fixture(scope="module")
def rays(camel19k):
    """[B, N, 3] origins and directions, and [B, N] tmax (a third finite)."""
    origins, directions = incoherent_set(camel19k.vertices, B * N, seed=7)
    rng = np.random.default_rng(7)
    tmax = np.where(rng.random(B * N) < 1 / 3, np.float32(0.8 * camel19k.diagonal), np.inf)
    return (origins.reshape(B, N, 3), directions.reshape(B, N, 3),
            tmax.astype(np.float32).reshape(B, N))


def assert_hits_equal(got, want):
    for field in FIELDS:
        np.testing.assert_array_equal(np.asarray(getattr(got, field)),
                                      np.asarray(getattr(want, field)), err_msg=field)


def stacked(hits_list):
    return jrt.Hits(*(np.stack([np.asarray(getattr(h, f)) for h in hits_list])
                      for f in FIELDS))


@pytest.mark.parametrize("kind", ["bvh", "grid", "brute"])
def test_vmap_closest_hit_equals_per_batch(structures, rays, kind):
    s = structures(kind)
    origins, directions, _ = rays
    got = jax.vmap(lambda o, d: jrt.closest_hit(s, o, d))(origins, directions)
    assert got.t.shape == (B, N)
    want = stacked([jrt.closest_hit(s, origins[b], directions[b]) for b in range(B)])
    assert_hits_equal(got, want)
    assert (want.triangle >= 0).mean() > 0.2  # the rays do hit the camel


def test_vmap_occluded_batched_tmax(structures, rays):
    s = structures("bvh")
    origins, directions, tmax = rays
    got = jax.vmap(lambda o, d, t: jrt.occluded(s, o, d, tmax=t))(origins, directions, tmax)
    want = np.stack([np.asarray(jrt.occluded(s, origins[b], directions[b], tmax=tmax[b]))
                     for b in range(B)])
    np.testing.assert_array_equal(np.asarray(got), want)
    # An independent reference: brute force's closest hit before tmax.
    brute = jrt.closest_hit(structures("brute"), origins.reshape(-1, 3),
                            directions.reshape(-1, 3), tmax=tmax.reshape(-1))
    np.testing.assert_array_equal(want.reshape(-1), np.asarray(brute.triangle) >= 0)
    assert 0 < want.mean() < 1


def test_vmap_shared_directions_and_counters(structures, rays):
    """in_axes=(0, None): origins batched, directions shared (broadcast); a scalar tmax;
    the counters come back per item too."""
    s = structures("bvh")
    origins, directions, _ = rays
    shared = directions[0]
    tmax = np.float32(2.0 * np.linalg.norm(np.ptp(origins.reshape(-1, 3), axis=0)))
    got, count = jax.vmap(lambda o, d: jrt.closest_hit(s, o, d, tmax=tmax, counters=True),
                          in_axes=(0, None))(origins, shared)
    assert count.steps.shape == (B, N)
    for b in range(B):
        hits, want = jrt.closest_hit(s, origins[b], shared, tmax=tmax, counters=True)
        assert_hits_equal(jax.tree.map(lambda a, b=b: a[b], got), hits)
        for field in ("steps", "tests", "leaves"):
            np.testing.assert_array_equal(np.asarray(getattr(count, field)[b]),
                                          np.asarray(getattr(want, field)), err_msg=field)


def test_vmap_inside_jit(structures, rays):
    s = structures("bvh")
    origins, directions, tmax = rays
    f = jax.jit(jax.vmap(lambda o, d, t: jrt.closest_hit(s, o, d, tmax=t)))
    got = f(jnp.asarray(origins), jnp.asarray(directions), jnp.asarray(tmax))
    want = stacked([jrt.closest_hit(s, origins[b], directions[b], tmax=tmax[b])
                    for b in range(B)])
    assert_hits_equal(got, want)


def test_nested_vmap_equals_loops(structures, camel19k):
    s = structures("bvh")
    outer, inner, n = 2, 3, 150  # 900 rays: the program of the tests above
    origins, directions = incoherent_set(camel19k.vertices, outer * inner * n, seed=11)
    origins = origins.reshape(outer, inner, n, 3)
    directions = directions.reshape(outer, inner, n, 3)
    f = jax.vmap(jax.vmap(lambda o, d: jrt.closest_hit(s, o, d)))
    got = f(origins, directions)
    assert got.t.shape == (outer, inner, n)
    for i in range(outer):
        for j in range(inner):
            assert_hits_equal(jax.tree.map(lambda a, i=i, j=j: a[i, j], got),
                              jrt.closest_hit(s, origins[i, j], directions[i, j]))
    # Both levels flattened into one call: one engine loop, on all the rays.
    batched = jax.make_jaxpr(f)(origins, directions)
    unbatched = jax.make_jaxpr(lambda o, d: jrt.closest_hit(s, o, d))(
        origins[0, 0], directions[0, 0])
    assert str(batched).count("while[") == str(unbatched).count("while[") >= 1
    assert while_loops(batched) == while_loops(unbatched)
    assert f"f32[{outer * inner * n},3]" in str(batched)


def while_loops(closed_jaxpr) -> list[tuple[int, ...]]:
    """Every while loop of a jaxpr (nested ones too), as the ranks of its carried arrays:
    a loop vmapped by JAX itself carries each array with one more axis (the batch)."""
    loops = []

    def walk(jaxpr):
        for eqn in jaxpr.eqns:
            if eqn.primitive.name == "while":
                loops.append(tuple(v.aval.ndim for v in eqn.outvars))
            for param in eqn.params.values():
                for sub in param if isinstance(param, tuple | list) else [param]:
                    if isinstance(sub, jax_core.ClosedJaxpr):
                        walk(sub.jaxpr)
                    elif isinstance(sub, jax_core.Jaxpr):
                        walk(sub)

    walk(closed_jaxpr.jaxpr)
    return sorted(loops)


@pytest.mark.parametrize("name", ["closest_hit", "occluded"])
def test_jaxpr_has_one_engine_loop(structures, rays, name):
    """The vmapped function holds as many while loops as the unbatched one (the engine's,
    once, not once per item) and traces the B x N rays laid end to end."""
    s = structures("bvh")
    origins, directions, _ = rays
    query = getattr(jrt, name)

    def f(o, d):
        return query(s, o, d)

    unbatched = jax.make_jaxpr(f)(origins[0], directions[0])
    batched = jax.make_jaxpr(jax.vmap(f))(origins, directions)
    loops = str(unbatched).count("while[")
    assert loops >= 1
    assert str(batched).count("while[") == loops
    # The same loops, not vmapped ones (whose carries would have one axis more)...
    assert while_loops(batched) == while_loops(unbatched)
    # ... on the rays laid end to end.
    assert f"f32[{B * N},3]" in str(batched)


def test_vmap_batched_structure_maps_items(structures, rays):
    """A structure batched along with the rays (one per item): the items go one at a
    time (lax.map), each equal to its own call."""
    s = structures("bvh")
    origins, directions, _ = rays
    batched = jax.tree.map(lambda a: np.stack([np.asarray(a)] * B), s)
    got = jax.vmap(lambda s, o, d: jrt.closest_hit(s, o, d))(batched, origins, directions)
    want = stacked([jrt.closest_hit(s, origins[b], directions[b]) for b in range(B)])
    assert_hits_equal(got, want)
