"""Batched renders (jrt.batch) against single renders of the pure renderer (jrt.wavefront).

Every expectation is a single render, ``wavefront.renderer(...)`` called on that item's
parameters, never a stored answer. Small images (24x18, 4 wavelength samples, depth 3) of
the glass camel on the 19k-triangle camel keep the file fast; the tests share compiled
programs (same shapes), so each distinct program compiles once.
"""

from __future__ import annotations

import dataclasses
import json
import os
import re
import subprocess
import sys
import textwrap
from pathlib import Path
from types import SimpleNamespace

import jax
import numpy as np
import pytest
from skimage import io

from jrt import batch, wavefront, whitted
from jrt.cli import main
from jrt.params import scene_arrays, scene_constants, scene_parameters
from jrt.scene import builtin_toml, parse_scene

W, H, DEPTH, SAMPLES = 24, 18, 3, 4
ROOT = Path(__file__).resolve().parents[1]


def glass_toml() -> str:
    return builtin_toml("glass-camel").replace('mesh = "camel"', 'mesh = "camel-19k"')


@pytest.fixture(scope="module")
def glass19k():
    return whitted.prepare(parse_scene(glass_toml(), source="test glass-camel"),
                           samples=SAMPLES)


def single(setup, params=None):
    """The W x H render of the pure renderer (its own parameters unless given), and its
    stats: what a batch item must equal."""
    render, own = wavefront.renderer(setup, width=W, height=H, max_depth=DEPTH)
    radiance = np.asarray(render(own if params is None else params), np.float64)
    return radiance, render.last_stats


def assert_equal_to_singles(radiance, stats, singles):
    """Item b is single render b to float32 rounding (rtol 1e-4, atol 1e-6 of the peak),
    and counts its rays as that render does.

    The batch and the single render are separate compiled programs, which XLA:CPU fuses
    and contracts into multiply-adds differently (by program and by the host's vector
    width); the glass camel's refractions amplify an ulp of a ray's direction: on an AMD
    EPYC Zen 2 host one pixel in 1,728 differed by 3.9e-5 of its value. A wrong item (its
    camera, its Cauchy B, its band) differs by percents."""
    assert radiance.shape == (len(singles), H, W, singles[0][0].shape[-1])
    assert radiance.dtype == np.float64
    for b, (item, (expected, st)) in enumerate(zip(radiance, singles, strict=True)):
        peak = np.abs(expected).max()
        np.testing.assert_allclose(item, expected, rtol=1e-4, atol=1e-6 * peak,
                                   err_msg=f"item {b}")
        assert stats.rays_per_level[b] == st.rays_per_level
        assert stats.shadow_rays[b] == st.shadow_rays


# --------------------------------------------------------------------------- equal to singles


def test_a_batch_of_cameras_equals_the_single_renders(glass19k):
    cameras = batch.turntable(glass19k, 3, width=W, height=H)
    radiance, stats = batch.render_batch(glass19k, cameras=cameras, max_depth=DEPTH)
    singles = [single(batch.with_camera(glass19k, c)) for c in cameras]
    assert_equal_to_singles(radiance, stats, singles)
    # The turntable turns: frame 0 is the scene's own view, the others differ from it.
    np.testing.assert_array_equal(single(glass19k)[0], singles[0][0])
    assert np.abs(radiance[1] - radiance[0]).max() > 1.0
    eye0, eye1 = np.subtract(cameras[0].eye, cameras[0].target), np.subtract(
        cameras[1].eye, cameras[1].target)
    assert np.isclose(np.degrees(np.arctan2(eye0[0], eye0[2]) - np.arctan2(eye1[0], eye1[2]))
                      % 360, 360 - 120, atol=1e-4)  # 360/3 degrees about +y
    assert eye0[1] == pytest.approx(eye1[1])
    devices = len(jax.local_devices())
    assert stats.batch == 3 and stats.rays_per_level[0][0] == W * H  # bundles of samples
    assert stats.items_per_call == -(-3 // devices) * devices and stats.calls == 1
    assert stats.devices == devices and stats.capacities[0] >= W * H
    # Every item's parameters in one call (padded with a copy of item 0), split over the
    # devices along the batch axis.
    share = stats.items_per_call // devices
    assert sorted(stats.placement) == [(d.id, i * share, (i + 1) * share)
                                       for i, d in enumerate(jax.local_devices())]


def test_a_sweep_of_cauchy_b_equals_the_single_renders(glass19k):
    scenes = batch.sweep_scenes(glass19k.scene, "glass.B=0.0:0.02:3")
    assert [s.material("glass").cauchy[1] for s in scenes] == pytest.approx([0, 0.01, 0.02])
    setup = whitted.prepare(scenes[0], structure=glass19k.structure, samples=SAMPLES,
                            features=batch.covering_features(scenes))
    assert setup.spectral  # B = 0 renders spectrally beside the dispersive items
    radiance, stats = batch.render_batch(setup, scenes=scenes, width=W, height=H,
                                         max_depth=DEPTH)
    singles = [single(whitted.prepare(s, structure=glass19k.structure, samples=SAMPLES,
                                      features=setup.features)) for s in scenes]
    assert_equal_to_singles(radiance, stats, singles)
    assert np.abs(radiance[2] - radiance[0]).max() > 1e-3  # B changes the picture


def test_a_batch_of_wavelength_bands_equals_the_single_renders(glass19k):
    bands = [[380.0, 480.0], [480.0, 580.0], [580.0, 780.0]]
    radiance, stats = batch.render_batch(glass19k, bands=bands, width=W, height=H,
                                         max_depth=DEPTH)
    singles = [single(batch.band_setup(glass19k, lo, hi)) for lo, hi in bands]
    assert_equal_to_singles(radiance, stats, singles)
    srgb = batch.batch_to_srgb(radiance, glass19k, bands)
    assert srgb.shape == (3, H, W, 3) and srgb.min() >= 0 and srgb.max() <= 1
    # Each band has its own colour: blue, green, red dominate in turn.
    means = srgb.reshape(3, -1, 3).mean(axis=1)
    assert list(means.argmax(axis=1)) == [2, 1, 0]


def test_a_tiny_budget_renders_group_by_group_and_an_overflow_renders_again(glass19k):
    """One device's share a call; level capacities too small for level 1: the first group
    renders again with the capacities its items demanded (the largest over the group),
    which the renderer keeps for the next group; every item equals its single render."""
    cameras = batch.turntable(glass19k, 3, width=W, height=H)
    render = wavefront.cached_renderer(glass19k, width=W, height=H, max_depth=DEPTH,
                                       threshold=glass19k.scene.settings.threshold)
    saved = render.capacities
    render.capacities = (saved[0], 8, 8)
    try:
        radiance, stats = batch.render_batch(glass19k, cameras=cameras, max_depth=DEPTH,
                                             memory_bytes=1)
    finally:
        grown, render.capacities = render.capacities, saved
    devices = len(jax.local_devices())
    groups = -(-3 // devices)
    assert stats.items_per_call == devices and stats.calls == groups + 1
    assert stats.capacities == grown and grown[0] == saved[0]
    assert grown[1] == grown[2] >= max(r[1] for r in stats.rays_per_level) > 8
    assert_equal_to_singles(radiance, stats, [single(batch.with_camera(glass19k, c))
                                              for c in cameras])


def test_variant_parameters_are_the_parameters_of_the_prepared_variant(glass19k):
    """Writing a variant's values into the setup's parameters gives the arrays that
    preparing the variant gives (no BVH is built per item), for every sweepable field and
    the ambient share; a constant index becomes Cauchy's (A, 0)."""
    constants = scene_constants(glass19k)
    base = scene_parameters(glass19k, W, H)
    scene = glass19k.scene
    variants = [batch.sweep_scenes(scene, spec)[-1] for spec in (
        "glass.index=1.3:1.7:2", "glass.A=1.4:1.6:2", "glass.B=0.0:0.02:2",
        "floor.albedo=0.2:0.8:2")]
    variants.append(dataclasses.replace(scene, settings=dataclasses.replace(
        scene.settings, ambient=0.37)))
    for variant in variants:
        params = batch.variant_parameters(base, variant)
        assert set(params["materials"]["glass"]) == {"A", "B"}
        prepared = whitted.prepare(variant, structure=glass19k.structure, samples=SAMPLES,
                                   features=glass19k.features)
        want = scene_arrays(scene_parameters(prepared, W, H), constants)
        got = scene_arrays(params, constants)
        for name, a, b in zip(want._fields, want, got, strict=True):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b), err_msg=name)
    # The setup's parameters are copied, not written.
    untouched = scene_parameters(glass19k, W, H)
    assert jax.tree.structure(base) == jax.tree.structure(untouched)
    for a, b in zip(jax.tree.leaves(base), jax.tree.leaves(untouched), strict=True):
        np.testing.assert_array_equal(a, b)


def test_the_plan_fits_the_budget():
    big = batch.plan_batch(36, 2 * 307200, memory_bytes=64 << 30, devices=2, lamps=1)
    assert big.items == 36 and big.bytes <= 64 << 30
    small = batch.plan_batch(36, 2 * 307200, memory_bytes=4 << 30, devices=2, lamps=1)
    assert 2 <= small.items < 36 and small.items % 2 == 0 and small.bytes <= 4 << 30
    assert batch.plan_batch(3, 100, memory_bytes=1 << 30, devices=2).items == 4  # padded up
    floor = batch.plan_batch(5, 100, memory_bytes=1, devices=4)
    assert floor.items == 4 and floor.bytes > floor.budget  # the smallest call anyway
    for bad in (0, -1, 1.5, True):
        with pytest.raises(ValueError, match="batch must be a positive integer"):
            batch.plan_batch(bad, 100, memory_bytes=1)
    assert batch.memory_budget() >= 1 and batch.host_memory() > 0


# --------------------------------------------------------------------------- devices

SHARDED = textwrap.dedent("""
    import json, sys
    import numpy as np
    import jax
    from jrt import batch, whitted
    from jrt.scene import builtin_toml, parse_scene

    text = builtin_toml("glass-camel").replace('mesh = "camel"', 'mesh = "camel-19k"')
    setup = whitted.prepare(parse_scene(text, source="test"), samples=4)
    cameras = batch.turntable(setup, 4, width=24, height=18)
    radiance, stats = batch.render_batch(setup, cameras=cameras, max_depth=3)
    np.save(sys.argv[1], radiance)
    print(json.dumps({"devices": [d.id for d in jax.local_devices()],
                      "placement": stats.placement, "items_per_call": stats.items_per_call,
                      "rays_per_level": stats.rays_per_level,
                      "shadow_rays": stats.shadow_rays}))
""")


def test_the_batch_is_split_over_four_devices_and_equals_the_single_renders(tmp_path,
                                                                            glass19k):
    """A process with 4 XLA:CPU devices renders 4 frames, one item a device, each equal to
    its single render here (on this process's devices) to float32 rounding."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(
        [str(ROOT), *filter(None, [os.environ.get("PYTHONPATH")])]))
    flags = [f for f in env.get("XLA_FLAGS", "").split()
             if not f.startswith("--xla_force_host_platform_device_count")]
    env["XLA_FLAGS"] = " ".join([*flags, "--xla_force_host_platform_device_count=4"])
    env["JRT_CPU_DEVICES"] = "4"
    env["JAX_PLATFORMS"] = "cpu"  # XLA:CPU's virtual devices, also beside an accelerator
    out = tmp_path / "radiance.npy"
    proc = subprocess.run([sys.executable, "-c", SHARDED, str(out)], env=env, cwd=ROOT,
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    four = json.loads(proc.stdout.strip().splitlines()[-1])
    assert four["devices"] == [0, 1, 2, 3] and four["items_per_call"] == 4
    assert sorted(tuple(p) for p in four["placement"]) == [(0, 0, 1), (1, 1, 2), (2, 2, 3),
                                                           (3, 3, 4)]
    cameras = batch.turntable(glass19k, 4, width=W, height=H)
    singles = [single(batch.with_camera(glass19k, c)) for c in cameras]
    counts = SimpleNamespace(rays_per_level=[tuple(r) for r in four["rays_per_level"]],
                             shadow_rays=four["shadow_rays"])
    assert_equal_to_singles(np.load(out), counts, singles)


# --------------------------------------------------------------------------- bad input


def test_bad_batches_are_refused_with_what_is_allowed(glass19k):
    cams = batch.turntable(glass19k, 2, width=W, height=H)
    with pytest.raises(ValueError, match="needs cameras, scenes or bands"):
        batch.render_batch(glass19k)
    with pytest.raises(ValueError, match="one length B, got cameras 2, bands 3"):
        batch.render_batch(glass19k, cameras=cams, bands=[[400, 500]] * 3)
    with pytest.raises(ValueError, match="share an image size, got 24x18, 32x18"):
        batch.render_batch(glass19k, cameras=[cams[0], dataclasses.replace(cams[1], width=32)])
    with pytest.raises(ValueError, match=r"bands\[1\] = \[500, 900\] nm: .*360 <= lo < hi"):
        batch.render_batch(glass19k, bands=[[400, 500], [500, 900]])
    with pytest.raises(ValueError, match=r"shape \[B, 2\]"):
        batch.render_batch(glass19k, bands=[400, 500])
    rgb = dataclasses.replace(glass19k, features=dataclasses.replace(glass19k.features,
                                                                     dispersion=False))
    with pytest.raises(ValueError, match="need a spectral setup"):
        batch.render_batch(rgb, bands=[[400, 500]])
    with pytest.raises(ValueError, match="has dispersion .* renders in RGB"):
        batch.render_batch(rgb, scenes=[glass19k.scene])
    moved = dataclasses.replace(glass19k.scene, objects=tuple(
        dataclasses.replace(o, scale=2.0) for o in glass19k.scene.objects))
    with pytest.raises(ValueError, match="changes the objects"):
        batch.render_batch(glass19k, scenes=[moved])
    with pytest.raises(ValueError, match="max_depth must be in 1..64"):
        batch.render_batch(glass19k, cameras=cams, max_depth=0)
    with pytest.raises(ValueError, match="memory_bytes must be a positive integer"):
        batch.render_batch(glass19k, cameras=cams, memory_bytes=0)
    with pytest.raises(ValueError, match="frames must be a positive integer, got 0"):
        batch.turntable(glass19k, 0)


@pytest.mark.parametrize(("spec", "message"), [
    ("glassB=0.002:0.02:8", "malformed: expected MATERIAL.FIELD=START:STOP:N"),
    ("glass.B=0.002:0.02", "malformed"),
    ("glass.B=0.002:0.02:0", "N must be an integer >= 1 .* got 0"),
    ("glass.B=0.002:0.02:x", "N 'x' is not an integer"),
    ("glass.B=a:0.02:3", "START 'a' is not a number"),
    ("glas.B=0.002:0.02:3", "no material 'glas'; its materials: glass, floor"),
    ("glass.C=0.002:0.02:3", "no sweepable field 'C'; allowed: index, A, B"),
    ("floor.B=0.1:0.2:3", r"'floor' \(diffuse\) has no sweepable field 'B'; allowed: albedo"),
    ("glass.B=0.002:2:3", r"glass.B = 1.001 µm² is outside \[0, 1\]"),
    ("glass.index=0.5:1.5:3", r"glass.index = 0.5 is outside \(1, 5\]"),
])
def test_bad_sweeps_name_the_value_and_what_is_allowed(spec, message):
    scene = parse_scene(glass_toml(), source="test")
    with pytest.raises(ValueError, match=message):
        batch.sweep_scenes(scene, spec)


def test_sweep_values_are_linearly_spaced_and_set_the_field():
    sweep = batch.parse_sweep("glass.B=0.002:0.02:8")
    assert (sweep.material, sweep.field) == ("glass", "B")
    np.testing.assert_allclose(sweep.values, np.linspace(0.002, 0.02, 8))
    assert batch.parse_sweep("glass.index=1.5:1.7:1").values == (1.5,)
    scene = parse_scene(glass_toml(), source="test")
    a, b = scene.material("glass").cauchy
    index = batch.sweep_scenes(scene, "glass.index=1.4:1.6:2")
    assert [s.material("glass").index for s in index] == [1.4, 1.6]
    assert not any(s.features().dispersion for s in index)
    cauchy_a = batch.sweep_scenes(scene, "glass.A=1.4:1.6:2")
    assert [s.material("glass").cauchy for s in cauchy_a] == [(1.4, b), (1.6, b)]
    grey = batch.sweep_scenes(scene, "floor.albedo=0.2:0.8:2")
    assert grey[1].material("floor").albedo == (0.8, 0.8, 0.8)
    assert grey[1].material("glass") == scene.material("glass")


# --------------------------------------------------------------------------- the CLI


@pytest.fixture
def scene_file(tmp_path):
    path = tmp_path / "glass19k.toml"
    path.write_text(glass_toml())
    return path


SMALL = ["--width", str(W), "--height", str(H), "--samples", str(SAMPLES),
         "--depth", str(DEPTH)]


def test_cli_turntable_writes_the_frames_and_a_gif(tmp_path, scene_file, capsys):
    import imageio.v3 as iio

    out = tmp_path / "spin"
    code = main(["render", "--scene", str(scene_file), "--turntable", "3", "-o", str(out),
                 *SMALL])
    printed = capsys.readouterr()
    assert code == 0, printed.err
    frames = sorted(p.name for p in out.glob("frame_*.png"))
    assert frames == ["frame_000.png", "frame_001.png", "frame_002.png"]
    gif = iio.imread(out / "turntable.gif")
    assert gif.shape[0] == 3 and gif.shape[1:3] == (H, W)
    first = io.imread(out / "frame_000.png")
    assert first.shape == (H, W, 3) and first.dtype == np.uint8
    assert not np.array_equal(first, io.imread(out / "frame_001.png"))
    assert "3 images 24x18" in printed.out and "turntable.gif" in printed.out


def test_cli_sweep_writes_a_contact_sheet(tmp_path, scene_file, capsys):
    out = tmp_path / "sheet.png"
    code = main(["render", "--scene", str(scene_file), "--sweep", "glass.B=0.0:0.02:3",
                 "-o", str(out), *SMALL])
    printed = capsys.readouterr()
    assert code == 0, printed.err
    sheet = io.imread(out)
    assert sheet.ndim == 3 and sheet.shape[0] > 2 * H and sheet.shape[1] > 2 * W
    assert "sweep of glass.B: 3 images" in printed.out


@pytest.mark.parametrize(("args", "message"), [
    (["--sweep", "glass.C=0:1:3"], "no sweepable field 'C'; allowed: index, A, B"),
    (["--sweep", "glas.B=0:0.02:3"], "no material 'glas'"),
    (["--sweep", "glass.B=0:0.02:0"], "N must be an integer >= 1"),
    (["--sweep", "glass.B:0:0.02:3"], "malformed"),
    (["--sweep", "glass.B=0:0.02:2", "--turntable", "2"], "give one of them"),
])
def test_cli_bad_batches_are_errors(tmp_path, scene_file, capsys, args, message):
    code = main(["render", "--scene", str(scene_file), "-o", str(tmp_path / "x.png"), *args])
    err = capsys.readouterr().err
    assert code == 2 and "jrt render: error:" in err
    assert re.search(message, err), err


def test_cli_turntable_needs_a_scene_and_a_positive_count(tmp_path, capsys):
    assert main(["render", "bunny", "--turntable", "4", "-o", str(tmp_path / "t")]) == 2
    assert "--turntable applies to scene renders" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["render", "--scene", "glass-camel", "--turntable", "0"])
    assert "N must be an integer >= 1 (the number of frames), got '0'" in (
        capsys.readouterr().err)
