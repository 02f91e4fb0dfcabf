"""Images per second of a turntable of the glass camel: one batched render (jrt.batch,
``jax.vmap`` of the pure renderer) against a Python loop of single renders
(jrt.wavefront).

    python -m benchmarks.turntable [-o turntable.json] [--quick] [--frames N]
                                   [--width W --height H] [--samples S] [--depth D]
                                   [--mesh camel|camel-19k] [--repeats R]

The scene is the built-in ``glass-camel`` (its mesh swapped to ``--mesh``, by default the
19k-triangle camel) with ``--samples`` wavelength samples; the turntable is
:func:`jrt.batch.turntable` (N frames, 360/N degrees apart about +y, around the scene's
automatic framing, :func:`jrt.camera.frame_mesh`, which fits the camel's bounding sphere:
every frame shows the whole camel). Three ways to render the same N frames, each timed
after a warm-up pass over the same frames (compiling, and growing the level capacities,
left out and recorded apart), best of ``--repeats``:

* ``batched``: :func:`jrt.batch.render_batch` over the N cameras (its own memory plan);
* ``loop``: one :func:`jrt.wavefront.renderer` called N times, each frame's camera written
  into its parameters (the renderer's own capacities, grown in the warm-up);
* ``loop_same_capacities``: the same loop with a renderer made at the batch's level capacities
  (each frame the very program the batch vmaps: the fairer baseline).

``ratio`` is the batch's images/s over the faster loop's. The batch's images are checked
against the loops' (``max_abs_difference``, radiance; float32 rounding at most).
Output: ``{"kind": "turntable", "machine", "parameters", "batched", "loop",
"loop_same_capacities", "ratio", "max_abs_difference", "notes"}``, each timing with
``seconds``, ``images_per_second``, ``compile_seconds``, ``rays``, ``capacities``.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import platform
import sys
import time

import numpy as np

import jrt  # noqa: F401  (jrt sets XLA's flags before JAX starts)
from benchmarks.common import command_line, write_record

PROG = "python -m benchmarks.turntable"
SCENE = "glass-camel"
#: (full, quick) settings.
FRAMES = (24, 8)
SIZES = ((96, 72), (48, 36))
SAMPLES = (8, 4)
DEPTHS = (5, 3)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=PROG, description=__doc__.split("\n\n")[0])
    p.add_argument("-o", "--output", default="turntable.json", help="JSON to write")
    p.add_argument("--quick", action="store_true",
                   help=f"{FRAMES[1]} frames of {SIZES[1][0]}x{SIZES[1][1]}, {SAMPLES[1]} "
                   f"samples, depth {DEPTHS[1]} (default {FRAMES[0]} of "
                   f"{SIZES[0][0]}x{SIZES[0][1]}, {SAMPLES[0]} samples, depth {DEPTHS[0]})")
    p.add_argument("--frames", type=int, default=None, help="turntable frames")
    p.add_argument("--width", type=int, default=None, help="image width")
    p.add_argument("--height", type=int, default=None, help="image height")
    p.add_argument("--samples", type=int, default=None, help="wavelength samples")
    p.add_argument("--depth", type=int, default=None, help="Whitted depth")
    p.add_argument("--mesh", choices=("camel", "camel-19k"), default="camel-19k",
                   help="the camel mesh of the glass camel (default camel-19k)")
    p.add_argument("--repeats", type=int, default=1, help="timed runs of each (best kept)")
    return p


def glass_camel(mesh: str):
    """The built-in glass camel with its objects' mesh set to ``mesh``."""
    from jrt.scene import load_scene

    scene = load_scene(SCENE)
    return dataclasses.replace(scene, objects=tuple(dataclasses.replace(o, mesh=mesh)
                                                    for o in scene.objects))


def machine_record() -> dict:
    import jax

    return {"platform": platform.platform(), "processor": platform.machine(),
            "cpu_count": os.cpu_count(), "python": platform.python_version(),
            "jax": jax.__version__, "numpy": np.__version__,
            "jax_devices": [str(d) for d in jax.devices()]}


def _timed(fn, repeats: int):
    """(result of the fastest call, its seconds) over ``repeats`` calls."""
    best, result = float("inf"), None
    for _ in range(max(1, int(repeats))):
        start = time.perf_counter()
        out = fn()
        seconds = time.perf_counter() - start
        if seconds < best:
            best, result = seconds, out
    return result, best


def run(*, quick=False, frames=None, width=None, height=None, samples=None, depth=None,
        mesh="camel-19k", repeats=1, command=PROG) -> dict:
    """The three timings; returns the JSON document."""
    from jrt import batch, wavefront, whitted

    q = int(bool(quick))
    frames = FRAMES[q] if frames is None else int(frames)
    width = SIZES[q][0] if width is None else int(width)
    height = SIZES[q][1] if height is None else int(height)
    samples = SAMPLES[q] if samples is None else int(samples)
    depth = DEPTHS[q] if depth is None else int(depth)
    start = time.perf_counter()
    setup = whitted.prepare(glass_camel(mesh), samples=samples)
    prepare_seconds = time.perf_counter() - start
    cameras = batch.turntable(setup, frames, width=width, height=height)

    # Batched: a warm-up pass (compile, capacities), then the timed runs.
    _, warm = batch.render_batch(setup, cameras=cameras, max_depth=depth)
    (images, stats), seconds = _timed(
        lambda: batch.render_batch(setup, cameras=cameras, max_depth=depth), repeats)
    batched = {"seconds": seconds, "images_per_second": frames / seconds,
               "compile_seconds": warm.compile_seconds + stats.compile_seconds,
               "rays": stats.total_rays, "items_per_call": stats.items_per_call,
               "capacities": list(stats.capacities), "calls": stats.calls,
               "devices": stats.devices, "memory_budget": stats.memory_budget,
               "call_bytes": stats.call_bytes}

    def loop(capacities):
        render, params = wavefront.renderer(setup, width=width, height=height,
                                            max_depth=depth, capacities=capacities)
        frame_params = [{**params, "camera": batch.camera_parameters(c)} for c in cameras]

        def all_frames():
            return [(np.asarray(render(p), np.float64), render.last_stats)
                    for p in frame_params]

        warmup = all_frames()
        out, secs = _timed(all_frames, repeats)
        record = {"seconds": secs, "images_per_second": frames / secs,
                  "compile_seconds": sum(st.compile_seconds for _, st in warmup + out),
                  "rays": sum(st.total_rays for _, st in out),
                  "capacities": list(render.capacities)}
        return np.stack([r for r, _ in out]), record

    loop_images, looped = loop(None)
    same_images, same = loop(stats.capacities)
    best = max(looped["images_per_second"], same["images_per_second"])
    return {
        "kind": "turntable",
        "machine": machine_record(),
        "parameters": {"scene": SCENE, "mesh": mesh, "frames": frames, "width": width,
                       "height": height, "samples": samples, "max_depth": depth,
                       "quick": bool(quick), "repeats": int(repeats),
                       "triangles": int(setup.geometry.faces.shape[0]),
                       "prepare_seconds": prepare_seconds, "command": command,
                       "timing": "wall time of the whole turntable (radiance, no encoding) "
                                 "after a warm-up pass over the same frames; best of "
                                 "repeats"},
        "batched": batched,
        "loop": looped,
        "loop_same_capacities": same,
        "ratio": batched["images_per_second"] / best,
        "max_abs_difference": {
            "loop": float(np.abs(images - loop_images).max()),
            "loop_same_capacities": float(np.abs(images - same_images).max()),
            "peak_radiance": float(np.abs(loop_images).max())},
        "notes": [
            "ratio: batched images/s over the faster of the two loops.",
            "loop: one jrt.wavefront renderer at its own capacities; loop_same_capacities: a "
            "renderer at the batch's level capacities, each frame the program the batch "
            "vmaps.",
            "A nonzero difference is float32 rounding: XLA compiles the vmapped program "
            "differently (see jrt.batch's tests).",
        ],
    }


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    command = command_line(PROG, argv)
    start = time.perf_counter()
    doc = run(quick=args.quick, frames=args.frames, width=args.width, height=args.height,
              samples=args.samples, depth=args.depth, mesh=args.mesh, repeats=args.repeats,
              command=command)
    doc["parameters"]["total_seconds"] = time.perf_counter() - start
    out = write_record(doc, args.output)
    p = doc["parameters"]
    print(f"{p['frames']} frames {p['width']}x{p['height']}, {p['samples']} samples, depth "
          f"{p['max_depth']}, {p['triangles']:,} triangles")
    for name in ("batched", "loop", "loop_same_capacities"):
        r = doc[name]
        print(f"{name:16s} {r['seconds']:8.2f} s  {r['images_per_second']:7.3f} images/s  "
              f"(capacities {r['capacities']}, compile {r['compile_seconds']:.2f} s)")
    print(f"ratio {doc['ratio']:.2f}x; max |batched - loop| "
          f"{doc['max_abs_difference']['loop_same_capacities']:.3g} (same capacities), "
          f"{doc['max_abs_difference']['loop']:.3g} (own capacities) -> {out} "
          f"({p['total_seconds']:.1f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
