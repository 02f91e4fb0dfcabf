"""jrt.spectral against colour-science's own conversions (never against this module's outputs).

The oracle is colour-science: ``colour.sd_to_XYZ(..., method="Integration")`` on spectral
distributions aligned (with colour's own ``align``) to the same 1 nm wavelengths as the
tables, ``colour.XYZ_to_RGB`` / ``colour.XYZ_to_sRGB``, ``colour.cctf_encoding`` and
``colour.recovery.RGB_to_sd_Mallett2019``; the CIE white point from ``colour.CCS_ILLUMINANTS``.
The band integrals are checked against colour's distributions aligned (colour's own
interpolators) to 1/8 nm and summed by the trapezoid rule over each band.
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


#: colour's distributions aligned to 1/8 nm: the oracle for the tables' band integrals.
EIGHTH = colour.SpectralShape(360.0, 830.0, 0.125)


def _band_integrals(distribution, edges):
    """``∫_band f dλ`` per band [edges[i], edges[i+1]] (edges on the 1/8 nm grid) of
    colour's ``distribution`` aligned to 1/8 nm, by the trapezoid rule on that grid."""
    d = distribution.copy().align(EIGHTH)
    wl, values = d.wavelengths, d.values
    out = []
    for a, b in zip(edges[:-1], edges[1:], strict=True):
        inside = (wl >= a - 1e-6) & (wl <= b + 1e-6)
        out.append(np.trapezoid(values[inside], wl[inside], axis=0))
    return np.asarray(out)


def _white_xyz(illuminant, lo=380.0, hi=780.0):
    """colour's white point of the lamp over [lo, hi] (a perfect reflector, 1/8 nm), Y = 1."""
    shape = colour.SpectralShape(lo, hi, 0.125)
    cmfs = colour.MSDS_CMFS[OBSERVER].copy().align(shape)
    lamp = colour.SDS_ILLUMINANTS[illuminant].copy().align(shape)
    ones = colour.sd_ones(shape)
    return colour.sd_to_XYZ(ones, cmfs, lamp, method="Integration") / 100.0


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
    # Equal bands: the samples sit at the band centres, each weighted by the band width.
    np.testing.assert_allclose(t.wavelengths, 380.0 + 25.0 * (np.arange(16) + 0.5))
    np.testing.assert_allclose(t.weights, 25.0)
    np.testing.assert_allclose(fine.wavelengths, SHAPE.wavelengths, rtol=0, atol=1e-4)
    # D65 is linear between its 5 nm nodes: its mean over a 1 nm band is its centre value.
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


def test_single_sample_is_one_band():
    t = spectral_tables(1)
    np.testing.assert_allclose(t.wavelengths, [580.0])
    np.testing.assert_allclose(t.weights, [400.0])
    # One band over 380-780 nm: a white surface is the lamp's white point, not the colour of
    # the 580 nm line.
    xyz = reflectance_to_xyz(jnp.ones(1), t)
    assert float(xyz[1]) == pytest.approx(1.0, abs=1e-6)
    np.testing.assert_allclose(xyz, _white_xyz("D65"), atol=1e-5)
    srgb = jax.jit(spectrum_to_srgb)(t.illuminant, t)
    assert np.all((np.asarray(srgb) >= 0) & (np.asarray(srgb) <= 1))


@pytest.mark.parametrize("illuminant", ["D65", "A", "FL2"])
@pytest.mark.parametrize("samples, lo, hi", [(16, 380.0, 780.0), (5, 400.0, 700.0)])
def test_tables_integrate_each_band(illuminant, samples, lo, hi):
    """illuminant * weights, illuminant * cmfs * weights and basis * weights are the band
    integrals of S, S cmf and the Mallett basis (colour at 1/8 nm, Sprague between the
    CMFs' 1 nm nodes; the module is linear between them: 1.0e-4 of the largest band apart,
    at z̄'s peak, measured)."""
    t = spectral_tables(samples, illuminant, lo, hi)
    edges = np.linspace(lo, hi, samples + 1)
    lamp = colour.SDS_ILLUMINANTS[illuminant]
    cmfs = colour.MSDS_CMFS[OBSERVER].copy().align(EIGHTH)
    fine_lamp = lamp.copy().align(EIGHTH)
    lit = colour.MultiSpectralDistributions(
        cmfs.values * fine_lamp.values[:, None], cmfs.wavelengths
    )
    w = np.asarray(t.weights, np.float64)
    s_band = _band_integrals(lamp, edges)
    np.testing.assert_allclose(np.asarray(t.illuminant) * w, s_band, rtol=1e-6)
    lit_band = _band_integrals(lit, edges)
    got = np.asarray(t.illuminant)[:, None] * np.asarray(t.cmfs) * w[:, None]
    np.testing.assert_allclose(got, lit_band, rtol=0, atol=2e-4 * lit_band.max())
    basis = _band_integrals(colour.recovery.MSDS_BASIS_FUNCTIONS_sRGB_MALLETT2019, edges)
    np.testing.assert_allclose(np.asarray(t.basis) * w[:, None], basis, rtol=0, atol=2e-4 * w[0])
    # k normalises the whole range's luminance: ∫ S ybar dλ over [lo, hi].
    assert float(t.k) == pytest.approx(1.0 / lit_band[:, 1].sum(), rel=1e-4)


# ------------------------------------------------------------------------ neutrality

NEUTRAL_SAMPLES = [1, 2, 3, 4, 5, 7, 8, 16, 32, 100]


@pytest.mark.parametrize("samples", NEUTRAL_SAMPLES)
def test_white_and_grey_do_not_depend_on_the_samples(samples):
    """A flat reflectance under the lamp is the lamp's white point (colour's, 1/8 nm) times
    its grey, whatever the number of samples. Under D65 that is neutral: R = G = B up to the
    IEC matrix's own mismatch with the CIE D65 white point (5.3e-4 linear, measured)."""
    t = spectral_tables(samples)
    white = _colour_linear_srgb(_white_xyz("D65"))
    assert np.ptp(white) < 6e-4  # the oracle itself: IEC matrix vs CIE D65, not sampling
    for grey in (1.0, 0.5, 0.18):
        linear = np.asarray(spectrum_to_linear_srgb(grey * t.illuminant, t))
        np.testing.assert_allclose(linear, grey * white, rtol=0, atol=1e-5 * grey)
        assert np.ptp(linear) < 6e-4 * grey
        # Encoded: the same grey within 2.5e-4 (0.06 of an 8-bit step).
        encoded = np.asarray(spectrum_to_srgb(grey * t.illuminant, t))
        np.testing.assert_allclose(
            encoded, colour.cctf_encoding(np.clip(grey * white, 0, 1), "sRGB"), atol=1e-5
        )
        assert np.ptp(encoded) < 2.5e-4
    # The renderer's path for a grey albedo: Mallett's band means sum to 1, so the flat 0.55.
    albedo = np.asarray(rgb_to_reflectance(jnp.full(3, 0.55), t))
    np.testing.assert_allclose(albedo, 0.55, atol=1e-5)
    floor = np.asarray(spectrum_to_linear_srgb(jnp.asarray(albedo) * t.illuminant, t))
    np.testing.assert_allclose(floor, 0.55 * white, atol=1e-5)


@pytest.mark.parametrize("illuminant, atol", [("A", 1e-5), ("FL2", 5e-5)])
@pytest.mark.parametrize("samples", [1, 3, 4, 16])
def test_white_is_the_lamps_white_point_for_any_samples(illuminant, atol, samples):
    """Any lamp: the white is the lamp's own white point (no chromatic adaptation: A stays
    warm), the same with 1 sample as with many, also on a range with fractional edges.
    (FL2's narrow mercury lines weigh the CMFs between 1 nm nodes, where the module is
    linear and colour's 1/8 nm alignment is Sprague: 3.2e-5 apart.)"""
    t = spectral_tables(samples, illuminant)
    white = reflectance_to_xyz(jnp.ones(samples), t)
    np.testing.assert_allclose(white, _white_xyz(illuminant), atol=atol)
    lo, hi = 400.3, 700.7
    one = reflectance_to_xyz(jnp.ones(1), spectral_tables(1, illuminant, lo, hi))
    many = reflectance_to_xyz(jnp.ones(samples), spectral_tables(samples, illuminant, lo, hi))
    np.testing.assert_allclose(many, one, atol=2e-6)


def test_lamp_dark_over_some_bands():
    """A lamp with no power below 500 nm: its dark bands get the plain band mean of the CMFs
    (finite, no 0/0), and the white is still the lamp's white point."""
    wl = np.arange(360.0, 831.0, 5.0)
    lamp = colour.SpectralDistribution(np.where(wl < 500.0, 0.0, 1.0), wl, name="dark blue")
    lamp.interpolator = colour.LinearInterpolator
    t = spectral_tables(8, lamp)
    for name in t._fields:
        assert np.all(np.isfinite(np.asarray(getattr(t, name)))), name
    assert float(t.illuminant[0]) == 0.0 and float(t.illuminant[-1]) == 1.0
    edges = np.linspace(380.0, 780.0, 9)
    mean_cmfs = _band_integrals(colour.MSDS_CMFS[OBSERVER], edges) / 50.0
    # (linear vs Sprague between 1 nm nodes: 7e-4 relative where x̄ is small, measured)
    np.testing.assert_allclose(t.cmfs[:2], mean_cmfs[:2], rtol=1e-3)
    shape = colour.SpectralShape(380.0, 780.0, 0.125)
    expected = colour.sd_to_XYZ(
        colour.sd_ones(shape), colour.MSDS_CMFS[OBSERVER].copy().align(shape),
        lamp.copy().align(shape), method="Integration",
    ) / 100.0
    np.testing.assert_allclose(reflectance_to_xyz(jnp.ones(8), t), expected, atol=1e-4)


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
        # 2e-5: the tables integrate S cmf over each 1 nm band (linear between the nodes),
        # colour sums its values at the band centres: 1e-5 apart in XYZ, steepened by the
        # curve (foliage's red: 1.0e-5).
        np.testing.assert_allclose(got, expected, atol=2e-5, err_msg=sd.name)


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
    # 16 samples (25 nm bands): the same white, Y = 1, the same chromaticity.
    w16 = reflectance_to_xyz(jnp.ones(16), tables16)
    assert float(w16[1]) == pytest.approx(1.0, abs=1e-6)
    np.testing.assert_allclose(w16, white, atol=2e-6)
    np.testing.assert_allclose(spectrum_to_srgb(tables16.illuminant, tables16), 1.0, atol=2.5e-4)


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
    edges = np.linspace(380.0, 780.0, FINE + 1)
    for rgb, got in zip(RGBS, reflectance, strict=True):
        expected = _aligned(colour.recovery.RGB_to_sd_Mallett2019(rgb.astype(np.float64)))
        # Band means over 1 nm: colour's spectrum at 1/8 nm averaged per band (the module
        # is linear between 1 nm nodes: 3e-3 apart where the basis is steepest), and within
        # 3e-3 of colour's value at the band centre.
        band = _band_integrals(colour.recovery.RGB_to_sd_Mallett2019(rgb.astype(np.float64)),
                               edges)
        np.testing.assert_allclose(got, band, atol=3e-3)
        np.testing.assert_allclose(got, expected.values, atol=3e-3)
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
