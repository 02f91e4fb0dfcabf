"""jrt.spectral against colour-science's own conversions (never against this module's outputs).

The oracle is colour-science: ``colour.sd_to_XYZ(..., method="Integration")`` on spectral
distributions aligned (with colour's own ``align``) to the same 1 nm wavelengths as the
tables, ``colour.XYZ_to_RGB`` / ``colour.XYZ_to_sRGB``, ``colour.cctf_encoding`` and
``colour.recovery.RGB_to_sd_Mallett2019``; the CIE white point from ``colour.CCS_ILLUMINANTS``.
"""

from __future__ import annotations

import colour
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jrt import spectral
from jrt.spectral import (
    OBSERVER,
    encode_srgb,
    reflectance_to_xyz,
    rgb_tables,
    rgb_to_reflectance,
    spectral_tables,
    spectrum_to_linear_srgb,
    spectrum_to_srgb,
    spectrum_to_xyz,
    xyz_to_linear_srgb,
)

#: 400 bins of 1 nm over 380-780 nm: their centres are colour's SpectralShape(380.5, 779.5, 1).
FINE = 400
SHAPE = colour.SpectralShape(380.5, 779.5, 1)
CHECKER = colour.SDS_COLOURCHECKERS["ColorChecker N Ohta"]
PATCHES = ["dark skin", "blue sky", "foliage", "orange", "purple", "cyan", "white 9.5 (.05 D)"]


@pytest.fixture(scope="module")
def fine():
    return spectral_tables(FINE)


@pytest.fixture(scope="module")
def tables16():
    return spectral_tables(16)


def _aligned(sd):
    return sd.copy().align(SHAPE)


def _sd(values, name):
    return colour.SpectralDistribution(dict(zip(SHAPE.wavelengths, values, strict=True)), name=name)


def _test_spectra():
    """A few reflectances: ColorChecker patches, a flat 0.5 grey, a narrow band at 550 nm."""
    wl = SHAPE.wavelengths
    sds = [_aligned(CHECKER[name]) for name in PATCHES]
    sds.append(_sd(np.full(wl.shape, 0.5), "grey 0.5"))
    sds.append(_sd(np.exp(-0.5 * ((wl - 550.0) / 5.0) ** 2), "narrow 550"))
    return sds


def _colour_xyz(sd, illuminant="D65"):
    """colour-science's XYZ (scaled to Y = 1 for the perfect reflector), same wavelengths."""
    cmfs = colour.MSDS_CMFS[OBSERVER].copy().align(SHAPE)
    lamp = colour.SDS_ILLUMINANTS[illuminant].copy().align(SHAPE)
    return colour.sd_to_XYZ(sd, cmfs, lamp, method="Integration") / 100.0


def _colour_linear_srgb(xyz):
    return colour.XYZ_to_RGB(
        xyz, "sRGB", chromatic_adaptation_transform=None, apply_cctf_encoding=False
    )


# ------------------------------------------------------------------------------- the tables


def test_tables_layout_and_pytree(fine):
    t = spectral_tables(16)
    assert t.samples == 16
    for name, shape in [
        ("wavelengths", (16,)),
        ("weights", (16,)),
        ("cmfs", (16, 3)),
        ("illuminant", (16,)),
        ("basis", (16, 3)),
        ("xyz_to_rgb", (3, 3)),
        ("k", ()),
    ]:
        value = getattr(t, name)
        assert value.shape == shape, name
        assert value.dtype == jnp.float32, name
    # Midpoint rule: bin centres, each weighted by the bin width.
    np.testing.assert_allclose(t.wavelengths, 380.0 + 25.0 * (np.arange(16) + 0.5))
    np.testing.assert_allclose(t.weights, 25.0)
    np.testing.assert_allclose(fine.wavelengths, SHAPE.wavelengths, rtol=0, atol=1e-4)
    # The tables are colour's data aligned to the same wavelengths (colour's interpolators).
    np.testing.assert_allclose(
        fine.cmfs, colour.MSDS_CMFS[OBSERVER].copy().align(SHAPE).values, atol=1e-6
    )
    lamp = colour.SDS_ILLUMINANTS["D65"].copy().align(SHAPE).values
    np.testing.assert_allclose(fine.illuminant, lamp, rtol=1e-6)
    np.testing.assert_allclose(
        fine.xyz_to_rgb, colour.RGB_COLOURSPACES["sRGB"].matrix_XYZ_to_RGB, rtol=1e-6
    )
    leaves = jax.tree_util.tree_leaves(t)
    assert len(leaves) == 7
    # Tables go into jit as an argument: the same program serves any tables of that size.
    radiance = t.illuminant * 0.5
    np.testing.assert_allclose(
        jax.jit(spectrum_to_srgb)(radiance, t), spectrum_to_srgb(radiance, t), atol=1e-6
    )


def test_single_sample_is_one_wavelength():
    t = spectral_tables(1)
    np.testing.assert_allclose(t.wavelengths, [580.0])
    np.testing.assert_allclose(t.weights, [400.0])
    xyz = reflectance_to_xyz(jnp.ones(1), t)
    assert float(xyz[1]) == pytest.approx(1.0, abs=1e-6)
    # The colour of the 580 nm spectral line (at Y = 1): its chromaticity is the CMFs' there.
    cmf = colour.MSDS_CMFS[OBSERVER][580.0]
    np.testing.assert_allclose(colour.XYZ_to_xy(np.asarray(xyz)), colour.XYZ_to_xy(cmf), atol=1e-5)
    srgb = jax.jit(spectrum_to_srgb)(t.illuminant, t)
    assert np.all((np.asarray(srgb) >= 0) & (np.asarray(srgb) <= 1))


# ------------------------------------------------------------------- against colour-science


@pytest.mark.parametrize("illuminant", ["D65", "A"])
def test_xyz_matches_colour_integration(illuminant):
    t = spectral_tables(FINE, illuminant)
    for sd in _test_spectra():
        expected = _colour_xyz(sd, illuminant)
        got = reflectance_to_xyz(jnp.asarray(sd.values), t)
        np.testing.assert_allclose(got, expected, rtol=0, atol=1e-5, err_msg=sd.name)
        # spectrum_to_xyz takes radiance: the lamp multiplied in by the caller.
        got = spectrum_to_xyz(jnp.asarray(sd.values) * t.illuminant, t)
        np.testing.assert_allclose(got, expected, rtol=0, atol=1e-5, err_msg=sd.name)


def test_srgb_matches_colour(fine):
    for sd in _test_spectra():
        xyz = _colour_xyz(sd)
        linear = _colour_linear_srgb(xyz)
        np.testing.assert_allclose(
            xyz_to_linear_srgb(jnp.asarray(xyz), fine), linear, atol=1e-5, err_msg=sd.name
        )
        got = spectrum_to_srgb(jnp.asarray(sd.values) * fine.illuminant, fine)
        if np.all((linear >= 0) & (linear <= 1)):
            expected = colour.XYZ_to_sRGB(xyz)  # the whole chain: matrix + IEC curve
        else:  # this module's documented rule: clip the linear channels, then encode
            expected = colour.cctf_encoding(np.clip(linear, 0, 1), "sRGB")
        np.testing.assert_allclose(got, expected, atol=1e-5, err_msg=sd.name)


def test_encode_matches_colour_cctf():
    x = np.concatenate([np.linspace(0.0, 1.0, 2001), np.geomspace(1e-6, 1e-2, 200)])
    got = encode_srgb(jnp.asarray(x, jnp.float32))
    np.testing.assert_allclose(got, colour.cctf_encoding(x, "sRGB"), rtol=0, atol=1e-6)


def test_out_of_gamut_is_clipped_per_channel(fine):
    # Encoding clips: negative -> 0, over-exposed -> 1; the matrix alone does not clip.
    np.testing.assert_array_equal(
        encode_srgb(jnp.array([-0.5, -1e-9, 1.0, 2.0, jnp.inf])), [0.0, 0.0, 1.0, 1.0, 1.0]
    )
    # A 520 nm line is far outside the sRGB gamut: negative red in linear, 0 once encoded.
    line = (np.abs(np.asarray(fine.wavelengths) - 520.0) < 1.0).astype(np.float32)
    radiance = jnp.asarray(line) * fine.illuminant * 50.0
    linear = np.asarray(spectrum_to_linear_srgb(radiance, fine))
    assert linear[0] < 0 and linear[1] > 1
    expected = colour.cctf_encoding(
        np.clip(_colour_linear_srgb(_colour_xyz(_sd(line * 50, "l"))), 0, 1), "sRGB"
    )
    srgb = np.asarray(spectrum_to_srgb(radiance, fine))
    np.testing.assert_allclose(srgb, expected, atol=1e-5)
    assert srgb[0] == 0.0 and srgb[1] == 1.0
    # The gradient stays finite at and below 0 (the curve's power is guarded).
    grad = jax.grad(lambda v: encode_srgb(v).sum())(jnp.array([-1.0, 0.0, 1e-4, 0.5, 2.0]))
    assert np.all(np.isfinite(np.asarray(grad)))


# ------------------------------------------------------------------------ white, lamps


def test_white_surface_under_d65(fine, tables16):
    perfect = _sd(np.ones(FINE), "perfect reflector")
    white = reflectance_to_xyz(jnp.ones(FINE), fine)
    np.testing.assert_allclose(white, _colour_xyz(perfect), atol=1e-5)
    assert float(white[1]) == pytest.approx(1.0, abs=1e-6)
    # The CIE D65 white point: xy is tabulated to 4 decimals, so xy agrees to 1e-4, Z to 1e-3.
    xy = colour.CCS_ILLUMINANTS[OBSERVER]["D65"]
    np.testing.assert_allclose(colour.XYZ_to_xy(np.asarray(white)), xy, atol=1e-4)
    np.testing.assert_allclose(white, colour.xy_to_XYZ(xy), atol=1e-3)
    # sRGB white: measured 1.9e-4 (380-780 nm), 8e-5 over the CIE tables' 360-830 nm.
    np.testing.assert_allclose(spectrum_to_srgb(fine.illuminant, fine), 1.0, atol=2.5e-4)
    wide = spectral_tables(470, lo=360.0, hi=830.0)
    np.testing.assert_allclose(spectrum_to_srgb(wide.illuminant, wide), 1.0, atol=1e-4)
    # 16 samples (25 nm bins): Y is still exactly 1, the chromaticity drifts by ~5e-4:
    # linear sRGB (1.0065, 0.9979, 1.0022), encoded within 1e-3 of white after the clip.
    w16 = reflectance_to_xyz(jnp.ones(16), tables16)
    assert float(w16[1]) == pytest.approx(1.0, abs=1e-6)
    np.testing.assert_allclose(colour.XYZ_to_xy(np.asarray(w16)), xy, atol=6e-4)
    np.testing.assert_allclose(xyz_to_linear_srgb(w16, tables16), 1.0, atol=7e-3)
    np.testing.assert_allclose(spectrum_to_srgb(tables16.illuminant, tables16), 1.0, atol=1e-3)


def test_illuminant_by_name_a_is_warmer(tables16):
    warm = spectral_tables(16, "A")
    srgb_a = np.asarray(spectrum_to_linear_srgb(warm.illuminant, warm))
    srgb_d65 = np.asarray(spectrum_to_linear_srgb(tables16.illuminant, tables16))
    assert srgb_a[0] > srgb_a[2] + 0.5
    assert abs(srgb_d65[0] - srgb_d65[2]) < 1e-2
    encoded = np.asarray(spectrum_to_srgb(warm.illuminant, warm))
    assert encoded[0] > encoded[2]
    # Lower-case names work as colour's mapping allows; a SpectralDistribution too.
    custom = spectral_tables(16, colour.SDS_ILLUMINANTS["A"])
    np.testing.assert_allclose(custom.illuminant, warm.illuminant)
    np.testing.assert_allclose(spectral_tables(16, "a").illuminant, warm.illuminant)


# --------------------------------------------------------------------- Mallett 2019 recovery

RGBS = np.array(
    [
        [1, 1, 1],
        [0.5, 0.5, 0.5],
        [0.8, 0.2, 0.1],
        [0.1, 0.6, 0.2],
        [0.2, 0.3, 0.9],
        [0.9, 0.8, 0.1],
    ],
    np.float32,
)


def test_mallett_matches_colour_recovery(fine):
    reflectance = np.asarray(rgb_to_reflectance(jnp.asarray(RGBS), fine))
    assert reflectance.shape == (len(RGBS), FINE)
    for rgb, got in zip(RGBS, reflectance, strict=True):
        expected = _aligned(colour.recovery.RGB_to_sd_Mallett2019(rgb.astype(np.float64)))
        np.testing.assert_allclose(got, expected.values, atol=1e-6)
        # Integrated back under D65 by colour itself, then by this module: the same rgb.
        back = _colour_linear_srgb(_colour_xyz(expected))
        np.testing.assert_allclose(back, rgb, atol=1e-3)
    back = spectrum_to_linear_srgb(jnp.asarray(reflectance) * fine.illuminant, fine)
    np.testing.assert_allclose(back, RGBS, atol=1e-3)
    # White -> a perfect reflector (the published basis sums to 1 within 1e-5).
    np.testing.assert_allclose(reflectance[0], 1.0, atol=2e-5)


def test_mallett_reflectance_in_unit_interval(fine, tables16):
    rgb = jax.random.uniform(jax.random.PRNGKey(0), (2000, 3))
    for t in (fine, tables16):
        r = np.asarray(rgb_to_reflectance(rgb, t))
        assert r.min() >= 0.0 and r.max() <= 1.0 + 2e-5
    # Linear, so vmappable and differentiable.
    jac = jax.jacobian(lambda c: reflectance_to_xyz(rgb_to_reflectance(c, tables16), tables16))
    assert np.all(np.isfinite(np.asarray(jac(jnp.array([0.3, 0.6, 0.2])))))
    batched = jax.vmap(rgb_to_reflectance, in_axes=(0, None))(rgb[:8], tables16)
    np.testing.assert_allclose(batched, rgb_to_reflectance(rgb[:8], tables16), atol=1e-7)


# ------------------------------------------------------------------------------ RGB mode


def test_rgb_tables():
    t = rgb_tables()
    assert t.samples == 3
    rgb = jax.random.uniform(jax.random.PRNGKey(1), (64, 3), minval=-0.2, maxval=1.5)
    # The three "samples" are linear sRGB: the XYZ round trip is the identity.
    np.testing.assert_allclose(spectrum_to_linear_srgb(rgb, t), rgb, atol=1e-5)
    np.testing.assert_allclose(rgb_to_reflectance(rgb, t), rgb, atol=1e-7)
    np.testing.assert_allclose(
        spectrum_to_xyz(rgb, t),
        colour.RGB_to_XYZ(
            np.asarray(rgb, np.float64),
            "sRGB",
            chromatic_adaptation_transform=None,
            apply_cctf_decoding=False,
        ),
        atol=1e-4,  # colour's RGB->XYZ matrix is derived from the primaries, not inverted
    )
    # The D65 lamp is white to the IEC matrix's rounding; A is the same colour as spectrally.
    np.testing.assert_allclose(t.illuminant, 1.0, atol=2e-4)
    a = rgb_tables("A")
    wide = spectral_tables(470, "A", lo=360.0, hi=830.0)
    np.testing.assert_allclose(
        a.illuminant, spectrum_to_linear_srgb(wide.illuminant, wide), atol=1e-5
    )
    assert float(spectrum_to_xyz(a.illuminant, a)[1]) == pytest.approx(1.0, abs=1e-5)


# ---------------------------------------------------------------------------- validation


@pytest.mark.parametrize("samples", [0, -3, 2.5, True, "16", None])
def test_bad_samples(samples):
    with pytest.raises(ValueError, match=r"samples must be an integer >= 1, got"):
        spectral_tables(samples)


@pytest.mark.parametrize(
    "lo, hi",
    [
        (350.0, 780.0),
        (380.0, 900.0),
        (500.0, 500.0),
        (600.0, 500.0),
        (float("nan"), 780.0),
        ("a", 780.0),
    ],
)
def test_bad_range(lo, hi):
    with pytest.raises(ValueError, match=r"(360 <= lo < hi <= 830|two numbers)") as info:
        spectral_tables(16, lo=lo, hi=hi)
    assert f"lo={lo!r}" in str(info.value)


def test_numpy_integer_samples_accepted():
    assert spectral_tables(np.int64(4)).samples == 4


@pytest.mark.parametrize("name", ["D66", "", 65])
def test_unknown_illuminant(name):
    with pytest.raises(ValueError, match="unknown illuminant") as info:
        spectral_tables(16, name)
    message = str(info.value)
    assert repr(name) in message
    assert "'D65'" in message and "'A'" in message


def test_module_exports_documented_constants():
    assert spectral.WAVELENGTH_MIN == 360.0 and spectral.WAVELENGTH_MAX == 830.0
