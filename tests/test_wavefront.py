"""The renderer (jrt.wavefront: every level of the tree in one compiled program, spectral
camera rays as bundles) against the host-stepped reference tree (jrt.host_tree.host_radiance),
which the optics tests check against closed forms.

The 19k camel, small images. Each ray's path is the same computation in both, so the images
must agree to the float32 rounding of the accumulation (the device adds in float32, the host
in float64), and the statistics exactly, a spectral bundle counting once at level 0.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jrt import host_tree, wavefront, whitted
from jrt.scene import builtin_toml, parse_scene

SIZE = (48, 36)
DEPTH = 3


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
    return {name: host_tree.host_radiance(setup, width=SIZE[0], height=SIZE[1],
                                        max_depth=DEPTH, chunk=4096)
            for name, setup in setups.items()}


@pytest.fixture(scope="module")
def renderers(setups):
    return {name: wavefront.renderer(setup, width=SIZE[0], height=SIZE[1], max_depth=DEPTH)
            for name, setup in setups.items()}


@pytest.mark.parametrize("name", ["camel", "mirror-camel", "glass-camel"])
def test_the_renderer_equals_the_host_tree(setups, host, renderers, name):
    want, want_stats = host[name]
    render, params = renderers[name]
    got = np.asarray(render(params), np.float64)
    stats = render.last_stats
    assert got.shape == want.shape
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-6 * np.abs(want).max())
    split = setups[name].channels if setups[name].spectral else 1
    assert stats.rays_per_level[0] * split == want_stats.rays_per_level[0]
    assert stats.rays_per_level[1:] == want_stats.rays_per_level[1:]
    assert stats.rays_per_pixel_by_depth == pytest.approx(want_stats.rays_per_pixel_by_depth)
    np.testing.assert_allclose(stats.dropped_weight, want_stats.dropped_weight, rtol=1e-4)
    np.testing.assert_allclose(stats.truncated_weight, want_stats.truncated_weight,
                               rtol=1e-4)
    if split == 1:
        assert stats.shadow_rays == want_stats.shadow_rays
    else:  # a bundle's samples share their first hit, and its shadow rays
        assert stats.shadow_rays < want_stats.shadow_rays
    assert all(c >= r for c, r in zip(render.capacities, stats.rays_per_level, strict=True))
    if name == "glass-camel":
        assert stats.rays_per_level[1] > 0.1 * want_stats.rays_per_level[0]  # a real tree


def test_an_overflowing_level_is_reported_and_rendered_again(setups, host):
    """Capacities far too small: the pure function says which level overflowed and how much
    weight it could not trace; the renderer grows them and loses nothing."""
    setup = setups["glass-camel"]
    bundles = SIZE[0] * SIZE[1]
    small = (wavefront.level_size(bundles),) + (64,) * (DEPTH - 1)
    render, params = wavefront.renderer(setup, width=SIZE[0], height=SIZE[1],
                                        max_depth=DEPTH, capacities=small)
    # The pure function, called as it is (its program is the one render(params) compiles
    # for these capacities next: compiled once, the second time read from JAX's cache).
    _, stats = render.trace(params)
    demand = np.asarray(stats.demand)
    want_stats = host["glass-camel"][1]
    assert demand[0] == bundles
    assert demand[1] == want_stats.rays_per_level[1] == 1336  # level 1's demand is exact
    assert np.asarray(stats.rays)[1] == 64
    assert float(np.asarray(stats.overflow_weight)[1]) > 0
    # What a call under jit checks at run time (a host callback), on these flags:
    with pytest.raises(OverflowError, match="level 1 of the Whitted tree needed 1,336 rays"):
        wavefront.check_tree(stats.demand, stats.status, capacities=render.capacities)

    got = np.asarray(render(params), np.float64)
    assert render.last_stats.rays_per_level[1:] == want_stats.rays_per_level[1:]
    assert all(c >= r for c, r in zip(render.capacities, want_stats.rays_per_level[1:],
                                      strict=False))
    want = host["glass-camel"][0]
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-6 * np.abs(want).max())


def test_grown_capacities_fix_the_first_overflow_and_everything_after():
    assert wavefront.grown_capacities((4096, 1024, 1024, 1024), np.array([4096, 900, 2000, 5000])
                                      ) == (4096, 1024, 2048, 2048)


def test_bad_capacities_are_refused(setups):
    with pytest.raises(ValueError, match="capacities must be 3 level sizes, the first at least"):
        wavefront.renderer(setups["mirror-camel"], width=8, height=6, max_depth=3,
                           capacities=(10, 10, 10))


def test_a_warm_render_moves_nothing_between_host_and_device(setups):
    """Every level inside one program: with the parameters on the device, a warm call makes
    no implicit transfer (its flags come back by one explicit device_get)."""
    render, params = wavefront.renderer(setups["glass-camel"], width=16, height=12,
                                        max_depth=DEPTH)
    params = jax.device_put(params)
    jax.block_until_ready(render(params))
    with jax.transfer_guard("disallow"):
        radiance = jax.block_until_ready(render(params))
    assert radiance.shape == (12, 16, 4) and render.last_stats.compile_seconds == 0


def test_vmap_over_parameter_sets_equals_the_single_renders(renderers):
    """Two glasses (Cauchy A) and two lamp intensities, stacked: jax.vmap(render) is one
    program and each item the single render of its parameters."""
    render, params = renderers["glass-camel"]
    items = []
    for a, intensity in ((1.45, 1.0), (1.6, 2.5)):
        p = jax.tree.map(lambda x: x, params)
        p["materials"]["glass"]["A"] = jnp.float32(a)
        p["lamps"][0]["intensity"] = jnp.float32(intensity)
        items.append(p)
    singles = [np.asarray(render(p)) for p in items]
    assert np.abs(singles[0] - singles[1]).max() > 0.01 * np.abs(singles[0]).max()
    stacked = jax.tree.map(lambda *x: jnp.stack(x), *items)
    batched = np.asarray(jax.vmap(render)(stacked))
    for got, want in zip(batched, singles, strict=True):
        np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-6 * np.abs(want).max())


def test_subpixel_samples_are_the_mean_of_a_finer_image(setups):
    """spp = 4 at W x H traces the rays through the Hammersley points (1/8, 1/8), (3/8, 5/8),
    (5/8, 3/8), (7/8, 7/8) of each pixel: the centres of four cells of a 4W x 4H image. The
    opaque camel (no glass to magnify a rounding of the rays): the anti-aliased image is the
    mean of those four pixels of the finer render."""
    w, h = 20, 15
    setup = setups["camel"]
    render, params = wavefront.renderer(setup, width=w, height=h, max_depth=1, spp=4)
    coarse = np.asarray(render(params), np.float64)
    fine_render, fine_params = wavefront.renderer(setup, width=4 * w, height=4 * h,
                                                  max_depth=1)
    fine_params["camera"] = params["camera"]  # the same camera (framed for the aspect)
    fine = np.asarray(fine_render(fine_params), np.float64).reshape(h, 4, w, 4, -1)
    cells = [(0, 0), (2, 1), (1, 2), (3, 3)]  # (row, column) in the pixel: (y, x) * 4
    want = np.mean([fine[:, r, :, c] for r, c in cells], axis=0)
    np.testing.assert_allclose(coarse, want, rtol=1e-4, atol=1e-5 * np.abs(want).max())
    centre = np.asarray(wavefront.renderer(setup, width=w, height=h, max_depth=1)[0](params))
    assert np.abs(coarse - centre).max() > 0.01 * np.abs(centre).max()  # it did move
