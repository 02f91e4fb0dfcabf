"""Batched renders (jrt.batch) against loops of single renders (jrt.whitted).

Every expectation is a Python loop of :func:`jrt.whitted.render_radiance` calls, one per
batch item, never a stored answer. Small images (24x18, 4 wavelength samples, depth 3) of
the glass camel on the 19k-triangle camel keep the file fast; the tests share compiled
programs (same shapes), so each distinct program compiles once.
"""

from __future__ import annotations

import dataclasses
import inspect
import json
import os
import re
import subprocess
import sys
import textwrap
from pathlib import Path

import jax
import numpy as np
import pytest
from skimage import io

from jrt import batch, whitted
from jrt.cli import main
from jrt.scene import builtin_toml, parse_scene

W, H, DEPTH, SAMPLES = 24, 18, 3, 4
ROOT = Path(__file__).resolve().parents[1]


def glass_toml() -> str:
    return builtin_toml("glass-camel").replace('mesh = "camel"', 'mesh = "camel-19k"')


@pytest.fixture(scope="module")
def glass19k():
    return whitted.prepare(parse_scene(glass_toml(), source="test glass-camel"),
                           samples=SAMPLES)


def single(setup, chunk):
    """One W x H render with the plain renderer: what a batch item must equal."""
    radiance, _ = whitted.render_radiance(setup, width=W, height=H, max_depth=DEPTH,
                                          chunk=chunk)
    return radiance


#: A batch item equals its single render to float32 rounding, peak-relative (the criterion
#: the cross-device test below uses too): the shading is the same function compiled for a
#: batch's shape, so a value may move by a few ulps, which the refractions amplify. On an
#: AVX2 host (8-wide vectors) 2 of 1,728 values of a 24x18 glass-camel frame differed by
#: 7.8e-5 (3e-6 of the value, 1e-6 of the peak), before and after the engine's entry pass
#: alike; a wrong hit moves a pixel by a share of the peak, not by 1e-5 of it.
LOOP_TOLERANCE = 1e-5
#: ...except where such an ulp decides a branch: a child whose weight sits at the
#: renderer's pruning threshold (1e-3) is traced in one render and pruned in the other. A
#: few values in a thousand may move by up to that threshold's share of the peak (one of
#: 1,728 moved by 1.02e-5 of the peak in a wavelength-band batch on the AVX2 host).
BRANCH_FLIPS, PRUNE_SHARE = 0.003, 1e-3


def loop_mismatch(item, expected):
    """Why a batch item is not its single render by the criterion above, or None."""
    peak = np.abs(expected).max()
    diff = np.abs(np.asarray(item, np.float64) - expected)
    off = diff > LOOP_TOLERANCE * peak
    if off.mean() > BRANCH_FLIPS:
        return (f"{int(off.sum())} of {diff.size} values differ by more than "
                f"{LOOP_TOLERANCE} of the peak; largest {diff.max() / peak:.3g}")
    if diff.max() > PRUNE_SHARE * peak:
        return f"largest difference {diff.max() / peak:.3g} of the peak, above {PRUNE_SHARE}"
    return None


def assert_equal_to_loop(radiance, loop):
    assert radiance.shape == (len(loop), H, W, loop[0].shape[-1])
    for item, expected in zip(radiance, loop, strict=True):
        problem = loop_mismatch(item, expected)
        assert problem is None, problem


# --------------------------------------------------------------------------- equal to the loop


def test_a_batch_of_cameras_equals_the_loop_of_single_renders(glass19k):
    cameras = batch.turntable(glass19k, 3, width=W, height=H)
    radiance, stats = batch.render_batch(glass19k, cameras=cameras, max_depth=DEPTH)
    loop = [single(batch.with_camera(glass19k, c), stats.chunk) for c in cameras]
    assert_equal_to_loop(radiance, loop)
    # The turntable turns: frame 0 is the scene's own view, the others differ from it.
    assert_equal_to_loop(radiance[:1], [single(glass19k, stats.chunk)])
    assert np.abs(radiance[1] - radiance[0]).max() > 1.0
    eye0, eye1 = np.subtract(cameras[0].eye, cameras[0].target), np.subtract(
        cameras[1].eye, cameras[1].target)
    assert np.isclose(np.degrees(np.arctan2(eye0[0], eye0[2]) - np.arctan2(eye1[0], eye1[2]))
                      % 360, 360 - 120, atol=1e-4)  # 360/3 degrees about +y
    assert eye0[1] == pytest.approx(eye1[1])
    assert stats.batch == 3 and stats.rays_per_level[0][0] == W * H * SAMPLES
    assert stats.items_per_call % len(jax.local_devices()) == 0


def test_a_material_sweep_equals_the_loop_of_single_renders(glass19k):
    scenes = batch.sweep_scenes(glass19k.scene, "glass.B=0.0:0.02:3")
    assert [s.material("glass").cauchy[1] for s in scenes] == pytest.approx([0, 0.01, 0.02])
    setup = whitted.prepare(scenes[0], structure=glass19k.structure, samples=SAMPLES,
                            features=batch.covering_features(scenes))
    assert setup.spectral  # B = 0 renders spectrally beside the dispersive items
    radiance, stats = batch.render_batch(setup, scenes=scenes, width=W, height=H,
                                         max_depth=DEPTH)
    loop = [single(whitted.prepare(s, structure=glass19k.structure, samples=SAMPLES,
                                   features=setup.features), stats.chunk) for s in scenes]
    assert_equal_to_loop(radiance, loop)
    assert np.abs(radiance[2] - radiance[0]).max() > 1e-3  # B changes the picture


def test_a_batch_of_wavelength_bands_equals_the_loop_of_single_renders(glass19k):
    bands = [[380.0, 480.0], [480.0, 580.0], [580.0, 780.0]]
    radiance, stats = batch.render_batch(glass19k, bands=bands, width=W, height=H,
                                         max_depth=DEPTH)
    loop = [single(batch.band_setup(glass19k, lo, hi), stats.chunk) for lo, hi in bands]
    assert_equal_to_loop(radiance, loop)
    srgb = batch.batch_to_srgb(radiance, glass19k, bands)
    assert srgb.shape == (3, H, W, 3) and srgb.min() >= 0 and srgb.max() <= 1
    # Each band has its own colour: blue, green, red dominate in turn.
    means = srgb.reshape(3, -1, 3).mean(axis=1)
    assert list(means.argmax(axis=1)) == [2, 1, 0]


def test_a_tiny_memory_budget_still_renders_the_same(glass19k):
    cameras = batch.turntable(glass19k, 3, width=W, height=H)
    radiance, stats = batch.render_batch(glass19k, cameras=cameras, max_depth=DEPTH,
                                         memory_bytes=1)
    devices = len(jax.local_devices())
    assert stats.chunk == batch.MIN_CHUNK and stats.items_per_call == devices
    assert stats.calls >= 3 * (W * H * SAMPLES // batch.MIN_CHUNK) // devices
    loop = [single(batch.with_camera(glass19k, c), batch.MIN_CHUNK) for c in cameras]
    assert_equal_to_loop(radiance, loop)


def test_the_plan_fits_the_budget():
    big = batch.plan_batch(36, 640 * 480, memory_bytes=64 << 30, devices=2, lamps=1)
    assert big.items == 36 and big.chunk == whitted.CHUNK and big.bytes <= 64 << 30
    small = batch.plan_batch(36, 640 * 480, memory_bytes=1 << 30, devices=2, lamps=1)
    assert 2 <= small.items < 36 and small.items % 2 == 0 and small.bytes <= 1 << 30
    one = batch.plan_batch(36, 640 * 480, memory_bytes=110 << 20, devices=1)
    assert one.items == 1 and batch.MIN_CHUNK < one.chunk < whitted.CHUNK
    assert one.bytes <= 110 << 20
    floor = batch.plan_batch(5, 100, memory_bytes=1, devices=4)
    assert (floor.items, floor.chunk) == (4, batch.MIN_CHUNK)
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
    loop = [whitted.render_radiance(batch.with_camera(setup, c), max_depth=3,
                                    chunk=stats.chunk)[0] for c in cameras]
    np.save(sys.argv[1], radiance)
    print(json.dumps({"devices": [d.id for d in jax.local_devices()],
                      "placement": stats.placement, "items_per_call": stats.items_per_call,
                      "equals_loop": all(loop_mismatch(r, l) is None
                                         for r, l in zip(radiance, loop)),
                      "loop_difference": max(float(np.abs(r - l).max())
                                             for r, l in zip(radiance, loop))}))
""")
# The subprocess judges its batch by this module's criterion, the same function.
SHARDED = (f"LOOP_TOLERANCE, BRANCH_FLIPS, PRUNE_SHARE = "
           f"{LOOP_TOLERANCE!r}, {BRANCH_FLIPS!r}, {PRUNE_SHARE!r}\n"
           + inspect.getsource(loop_mismatch) + SHARDED)


def _sharded(tmp_path, devices: int):
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(
        [str(ROOT), *filter(None, [os.environ.get("PYTHONPATH")])]))
    flags = [f for f in env.get("XLA_FLAGS", "").split()
             if not f.startswith("--xla_force_host_platform_device_count")]
    if devices > 1:
        flags.append(f"--xla_force_host_platform_device_count={devices}")
    env["XLA_FLAGS"] = " ".join(flags)
    env["JRT_CPU_DEVICES"] = str(devices)
    env["JAX_PLATFORMS"] = "cpu"  # XLA:CPU's virtual devices, also beside an accelerator
    out = tmp_path / f"radiance{devices}.npy"
    proc = subprocess.Popen([sys.executable, "-c", SHARDED, str(out)], env=env, cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    return proc, out


def test_the_batch_is_split_over_four_devices_and_equals_one_device(tmp_path):
    """Two processes, one with 4 XLA:CPU devices and one with 1, render the same 4 frames.

    In each the batch equals the loop of single renders (``LOOP_TOLERANCE``, 1e-5 of the
    peak). Between them the renders
    agree to float32 rounding (peak-relative 1e-5): jrt's *single* renders already differ
    by a few ulps between one device and several (the engine's hits are identical, the
    shading arithmetic is compiled differently around the engine's shard_map; measured
    2e-6 of the peak with jax 0.10.2), and the batch adds no difference of its own.
    """
    runs = {n: _sharded(tmp_path, n) for n in (4, 1)}  # both at once
    results = {}
    for n, (proc, out) in runs.items():
        stdout, stderr = proc.communicate(timeout=600)
        assert proc.returncode == 0, stderr[-3000:]
        results[n] = json.loads(stdout.strip().splitlines()[-1]), np.load(out)
    four, sharded = results[4]
    one, unsharded = results[1]
    # The work was split: 4 devices, each holding one of the 4 items of every call.
    assert four["devices"] == [0, 1, 2, 3] and four["items_per_call"] == 4
    assert sorted(tuple(p) for p in four["placement"]) == [(0, 0, 1), (1, 1, 2), (2, 2, 3),
                                                           (3, 3, 4)]
    assert one["devices"] == [0] and [tuple(p) for p in one["placement"]] == [(0, 0, 4)]
    # Each batch equals its process's loop of single renders.
    assert four["equals_loop"], four["loop_difference"]
    assert one["equals_loop"], one["loop_difference"]
    peak = np.abs(unsharded).max()
    assert sharded.shape == unsharded.shape == (4, H, W, SAMPLES)
    assert np.abs(sharded - unsharded).max() <= 1e-5 * peak


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
    with pytest.raises(ValueError, match="max_depth must be an integer in 1..64"):
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
    assert main(["render", "--turntable", "4", "-o", str(tmp_path / "t")]) == 2
    assert "--turntable applies to --scene renders" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["render", "--scene", "glass-camel", "--turntable", "0"])
    assert "N must be an integer >= 1 (the number of frames), got '0'" in (
        capsys.readouterr().err)
