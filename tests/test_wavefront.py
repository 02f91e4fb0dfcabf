"""The Whitted tree on the device (jrt.wavefront) against the host-stepped tree
(jrt.whitted.render_radiance), which the optics tests check against closed forms.

The 19k camel, small images. Each ray's path is the same computation in both, so the images
must agree to the float32 rounding of the accumulation (the device adds in float32, the host
in float64), and the statistics exactly.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jrt import wavefront, whitted
from jrt.scene import builtin_toml, parse_scene

SIZE = (48, 36)
DEPTH = 3  # the tree is unrolled level by level in the program: compile time grows with it


def camel_scene(name):
    text = builtin_toml(name).replace('mesh = "camel"', 'mesh = "camel-19k"')
    return parse_scene(text, source=f"test {name}")


@pytest.fixture(scope="module")
def setups():
    return {name: whitted.prepare(camel_scene(name), samples=4)
            for name in ("camel", "mirror-camel", "glass-camel")}


@pytest.fixture(scope="module")
def host(setups):
    """The host-stepped renders, the reference."""
    return {name: whitted.render_radiance(setup, width=SIZE[0], height=SIZE[1],
                                          max_depth=DEPTH, chunk=4096)
            for name, setup in setups.items()}


@pytest.mark.parametrize("name", ["camel", "mirror-camel"])
def test_opaque_and_mirror_trees_equal_the_host_tree(setups, host, name):
    want, want_stats = host[name]
    got, stats, capacities = wavefront.render_radiance(setups[name], width=SIZE[0],
                                                       height=SIZE[1], max_depth=DEPTH)
    assert got.shape == want.shape
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-6 * np.abs(want).max())
    assert stats.rays_per_level == want_stats.rays_per_level
    assert stats.shadow_rays == want_stats.shadow_rays
    assert len(capacities) == want_stats.max_depth
    assert all(c >= r for c, r in zip(capacities, stats.rays_per_level, strict=True))


def test_glass_tree_equals_the_host_tree(setups, host):
    want, want_stats = host["glass-camel"]
    got, stats, _ = wavefront.render_radiance(setups["glass-camel"], width=SIZE[0],
                                              height=SIZE[1], max_depth=DEPTH)
    assert stats.rays_per_level == want_stats.rays_per_level
    assert stats.rays_per_level[1] > 0.1 * stats.rays_per_level[0]  # glass: a real tree
    assert stats.shadow_rays == want_stats.shadow_rays
    np.testing.assert_allclose(stats.dropped_weight, want_stats.dropped_weight, rtol=1e-4)
    np.testing.assert_allclose(stats.truncated_weight, want_stats.truncated_weight, rtol=1e-4)
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-6 * np.abs(want).max())


def test_an_overflowing_level_is_reported_and_rendered_again(setups, host):
    """Capacities far too small: the pure function says which level overflowed and how much
    weight it could not trace; render_radiance grows them and loses nothing."""
    setup = setups["glass-camel"]
    camera = setup.camera(*SIZE)
    rays = whitted.camera_level(setup, camera)
    small = (len(rays),) + (64,) * (DEPTH - 1)
    _, stats = wavefront.trace_tree(
        setup.device_structure, setup.arrays, wavefront._pad(rays, small[0]),
        jnp.float32(setup.scene.settings.threshold), jax.random.PRNGKey(0),
        static=whitted._static(setup, "tree"), capacities=small, pixels=camera.num_rays,
        channels=setup.channels)
    demand = np.asarray(stats.demand)
    want_stats = host["glass-camel"][1]
    assert demand[0] == len(rays)
    assert demand[1] == want_stats.rays_per_level[1] > 64  # level 1's demand is exact
    assert np.asarray(stats.rays)[1] == 64
    assert float(np.asarray(stats.overflow_weight)[1]) > 0

    got, grown_stats, grown = wavefront.render_radiance(setup, width=SIZE[0], height=SIZE[1],
                                                        max_depth=DEPTH, capacities=small)
    assert grown_stats.rays_per_level == want_stats.rays_per_level
    assert all(c >= r for c, r in zip(grown, want_stats.rays_per_level, strict=True))
    again, _, _ = wavefront.render_radiance(setup, width=SIZE[0], height=SIZE[1],
                                            max_depth=DEPTH)
    np.testing.assert_array_equal(got, again)


def test_grown_capacities_fix_the_first_overflow_and_everything_after():
    assert wavefront.grown_capacities((4096, 1024, 1024, 1024), np.array([4096, 900, 2000, 5000])
                                      ) == (4096, 1024, 2048, 2048)


def test_bad_capacities_are_refused(setups):
    with pytest.raises(ValueError, match="capacities must be 3 level sizes, the first at least"):
        wavefront.render_radiance(setups["mirror-camel"], width=8, height=6, max_depth=3,
                                  capacities=(10, 10, 10))


def test_a_warm_tree_moves_nothing_between_host_and_device(setups):
    """Every level inside one program: with its arguments on the device, a warm call makes
    no transfer."""
    setup = setups["glass-camel"]
    camera = setup.camera(16, 12)
    rays = whitted.camera_level(setup, camera)
    capacities = (len(rays),) * DEPTH
    args = (setup.device_structure, setup.arrays, wavefront._pad(rays, capacities[0]),
            jnp.float32(setup.scene.settings.threshold), jax.random.PRNGKey(0))
    options = dict(static=whitted._static(setup, "tree"), capacities=capacities,
                   pixels=camera.num_rays, channels=setup.channels)
    program = wavefront.trace_tree.lower(*args, **options).compile()
    # The engine spreads the rays over the CPU devices: the arguments go where the
    # program wants them once, before the guard.
    args = jax.device_put(args, program.input_shardings[0])
    jax.block_until_ready(program(*args))
    with jax.transfer_guard("disallow"):
        radiance, stats = program(*args)
        jax.block_until_ready((radiance, stats))
    assert np.asarray(stats.rays)[0] == len(rays)
