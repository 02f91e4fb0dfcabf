"""jrt under ``jax_enable_x64``: every public query works, and stays float32 inside.

x64 is a process-wide flag, so the x64 side runs in a subprocess (it would leak into the
other tests otherwise). There, two structures trace 1,100 rays of the 19k-triangle camel
(closest hit and any hit), a tiny Whitted render of the glass camel and a tiny batch run;
and every structure's programs are searched for 64-bit values (a float64 or int64
array that is not a weakly typed Python constant). Here, in float32 mode, brute force
traces the same rays: the x64 answers must be its answers bit for bit.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

import accel
import jrt
from jrt.trace import as_numpy

ROOT = Path(__file__).resolve().parents[1]
N = 1100
#: The structures traced under x64 (each compiles its programs, seconds apiece). Every
#: structure's programs are searched for 64-bit values, which is what would make its x64
#: answers differ from float32 mode's; these two also compare the answers themselves:
#: the engine's (the BVH's step) and brute force's chunks.
RUN = ("brute", "bvh")

X64_SCRIPT = r'''
import collections, functools, json, sys
import numpy as np
import jrt, accel, jax
from jax.extend import core
from jrt import batch, whitted
from jrt.scene import builtin_toml, parse_scene
from jrt.trace import as_numpy

jax.config.update("jax_enable_x64", True)
out, rays_file, RUN = sys.argv[1], sys.argv[2], sys.argv[3].split(",")
with np.load(rays_file) as f:
    o, d, t = f["origins"], f["directions"], f["tmax"]


def wide(jaxpr, found, where):
    """64-bit values computed in ``jaxpr`` and the programs it calls (weak constants aside)."""
    for eqn in jaxpr.eqns:
        for v in eqn.outvars:
            aval = getattr(v, "aval", None)
            dtype = getattr(aval, "dtype", None)
            kind = getattr(dtype, "kind", "")  # (PRNG key types have none)
            is_wide = (kind in ("f", "i", "u") and dtype.itemsize == 8
                       or kind == "c" and dtype.itemsize == 16)
            if is_wide and not getattr(aval, "weak_type", False):
                found[f"{where}: {eqn.primitive.name} {dtype}"] += 1
        for p in eqn.params.values():
            for sub in p if isinstance(p, (list, tuple)) else [p]:
                if isinstance(sub, core.ClosedJaxpr):
                    wide(sub.jaxpr, found, where)
                elif isinstance(sub, core.Jaxpr):
                    wide(sub, found, where)


found = collections.Counter()
mesh = jrt.load_mesh(jrt.mesh_path("camel-19k"))
arrays, dtypes = {}, {}
for kind in accel.NAMES:
    s = accel.build(kind, mesh)
    if kind in RUN:
        hits = jrt.closest_hit(s, o, d, tmax=t)
        occluded = jrt.occluded(s, o, d, tmax=t)
        dtypes[kind] = [str(a.dtype) for a in hits] + [str(occluded.dtype)]
        for name, value in as_numpy(hits).items():
            arrays[f"{kind}_{name}"] = value
        arrays[f"{kind}_occluded"] = np.asarray(occluded)
    queries = {"closest_hit": lambda o, d, t: jrt.closest_hit(s, o, d, tmax=t),
               "occluded": lambda o, d, t: jrt.occluded(s, o, d, tmax=t)}
    if kind != "brute":
        queries["counters"] = lambda o, d, t: jrt.closest_hit(s, o, d, tmax=t, counters=True)
    for name, fn in queries.items():
        wide(jax.make_jaxpr(fn)(o, d, t).jaxpr, found, f"{kind} {name}")

toml = builtin_toml("glass-camel").replace('mesh = "camel"', 'mesh = "camel-19k"')
setup = whitted.prepare(parse_scene(toml, source="glass-camel-19k"), samples=4)
for mode in whitted.MODES:  # the renderer's whole program, every level
    render, params = whitted.renderer(setup, width=4, height=4, max_depth=2, mode=mode)
    wide(jax.make_jaxpr(render.trace)(params).jaxpr, found, f"whitted {mode}")
image, _ = whitted.render_scene(setup, width=32, height=24, max_depth=2)
arrays["image"] = image
cameras = batch.turntable(setup, 2, width=32, height=24)
radiance, _ = batch.render_batch(setup, cameras=cameras, max_depth=2)
srgb = batch.batch_to_srgb(radiance, setup)
arrays["batch_srgb"] = srgb
np.savez(out + ".npz", **arrays)
with open(out + ".json", "w") as f:
    json.dump({"x64": bool(jax.config.jax_enable_x64), "dtypes": dtypes,
               "wide": dict(found), "image": str(image.dtype),
               "radiance": str(radiance.dtype), "batch_srgb": str(srgb.dtype)}, f)
'''


@pytest.fixture(scope="module")
def rays(camel19k_api_rays):
    return camel19k_api_rays


@pytest.fixture(scope="module")
def x64_run(rays, tmp_path_factory):
    """The x64 subprocess's answers (npz) and report (json)."""
    folder = tmp_path_factory.mktemp("x64")
    rays_file = folder / "rays.npz"
    np.savez(rays_file, origins=rays[0], directions=rays[1], tmax=rays[2])
    out = folder / "out"
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    done = subprocess.run([sys.executable, "-c", textwrap.dedent(X64_SCRIPT), str(out),
                           str(rays_file), ",".join(RUN)], capture_output=True, text=True, env=env,
                          cwd=ROOT, timeout=900)
    assert done.returncode == 0, done.stderr[-4000:]
    report = json.loads(Path(f"{out}.json").read_text())
    with np.load(f"{out}.npz") as f:
        arrays = {k: f[k] for k in f.files}
    return report, arrays


def test_the_subprocess_ran_under_x64(x64_run):
    assert x64_run[0]["x64"] is True


def test_no_64_bit_value_inside_any_program(x64_run):
    """Every structure's closest hit, any hit and counters, and the Whitted level function
    (tree and sampled) compute in float32 and int32 under x64."""
    assert x64_run[0]["wide"] == {}


@pytest.mark.parametrize("kind", RUN)
def test_x64_hits_are_brute_forces_float32_hits(kind, x64_run, rays, camel19k):
    report, arrays = x64_run
    assert report["dtypes"][kind] == ["float32", "int32", "float32", "float32", "bool"]
    brute = accel.build("brute", camel19k)
    o, d, t = rays
    want = as_numpy(jrt.closest_hit(brute, o, d, tmax=t))
    assert (want["triangle"] >= 0).mean() > 0.2
    for name, value in want.items():
        np.testing.assert_array_equal(arrays[f"{kind}_{name}"], value, err_msg=name)
    np.testing.assert_array_equal(arrays[f"{kind}_occluded"],
                                  np.asarray(jrt.occluded(brute, o, d, tmax=t)))


def test_renders_under_x64_are_float32_pictures(x64_run):
    report, arrays = x64_run
    assert report["image"] == "float32" and report["batch_srgb"] == "float32"
    for name, shape in (("image", (24, 32, 3)), ("batch_srgb", (2, 24, 32, 3))):
        picture = arrays[name]
        assert picture.shape == shape and np.isfinite(picture).all()
        assert 0 <= picture.min() and picture.max() <= 1
        assert picture.std() > 0.01  # the camel is in it, not a flat sky
