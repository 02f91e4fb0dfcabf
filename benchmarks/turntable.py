"""Images per second of a turntable of the glass camel: one batched render (jrt.batch)
against a Python loop of single renders (jrt.whitted).

    python -m benchmarks.turntable [-o turntable.json] [--quick] [--frames N]
                                   [--width W --height H] [--samples S] [--depth D]
                                   [--mesh camel|camel-19k] [--repeats R]

The scene is the built-in ``glass-camel`` (its mesh swapped to ``--mesh``, by default the
19k-triangle camel) with ``--samples`` wavelength samples; the turntable is
:func:`jrt.batch.turntable` (N frames, 360/N degrees apart about +y, around the scene's
automatic framing, :func:`jrt.camera.frame_mesh`, which fits the camel's bounding sphere:
every frame shows the whole camel). Three ways to render the same N frames, each timed
after a warm-up of the same shapes at depth 1 (compiling left out and recorded apart), best
of ``--repeats``:

* ``batched``: :func:`jrt.batch.render_batch` over the N cameras (its own memory plan);
* ``loop``: N calls of :func:`jrt.whitted.render_radiance`, the library's default chunk
  (:data:`jrt.whitted.CHUNK` rays a call, padded);
* ``loop_same_chunk``: the same loop with the batch's chunk (less padding for small
  images: the fairer baseline when the default chunk is much larger than a level).

``ratio`` is the batch's images/s over the faster loop's. The batch's images are checked
against the loop's (``max_abs_difference``, radiance; 0 expected with the same chunk).
Output: ``{"kind": "turntable", "machine", "parameters", "batched", "loop",
"loop_same_chunk", "ratio", "max_abs_difference", "notes"}``, each timing with
``seconds``, ``images_per_second``, ``compile_seconds``, ``rays``.
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
    from jrt import batch, whitted

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
    singles = [batch.with_camera(setup, c) for c in cameras]

    # Batched: warm-up (compile) at depth 1, then the timed runs.
    _, warm = batch.render_batch(setup, cameras=cameras, max_depth=1)
    (images, stats), seconds = _timed(
        lambda: batch.render_batch(setup, cameras=cameras, max_depth=depth), repeats)
    batched = {"seconds": seconds, "images_per_second": frames / seconds,
               "compile_seconds": warm.compile_seconds + stats.compile_seconds,
               "rays": stats.total_rays, "items_per_call": stats.items_per_call,
               "chunk": stats.chunk, "calls": stats.calls, "devices": stats.devices,
               "memory_budget": stats.memory_budget, "call_bytes": stats.call_bytes}

    def loop(chunk):
        _, w = whitted.render_radiance(singles[0], max_depth=1, chunk=chunk)

        def all_frames():
            return [whitted.render_radiance(s, max_depth=depth, chunk=chunk) for s in singles]

        out, secs = _timed(all_frames, repeats)
        record = {"seconds": secs, "images_per_second": frames / secs,
                  "compile_seconds": w.compile_seconds + sum(st.compile_seconds
                                                             for _, st in out),
                  "rays": sum(st.total_rays for _, st in out), "chunk": chunk}
        return np.stack([r for r, _ in out]), record

    loop_images, looped = loop(whitted.CHUNK)
    same_images, same = loop(stats.chunk)
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
                                 "after a depth-1 warm-up of the same shapes; best of "
                                 "repeats"},
        "batched": batched,
        "loop": looped,
        "loop_same_chunk": same,
        "ratio": batched["images_per_second"] / best,
        "max_abs_difference": {
            "loop": float(np.abs(images - loop_images).max()),
            "loop_same_chunk": float(np.abs(images - same_images).max()),
            "peak_radiance": float(np.abs(loop_images).max())},
        "notes": [
            "ratio: batched images/s over the faster of the two loops.",
            "The loop with the default chunk pads every level to jrt.whitted.CHUNK rays; "
            "loop_same_chunk uses the batch's chunk, sized to a level-0 image.",
            "A nonzero difference against the default-chunk loop is float32 rounding: XLA "
            "compiles the level function for another shape (see jrt.batch's tests).",
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
    for name in ("batched", "loop", "loop_same_chunk"):
        r = doc[name]
        print(f"{name:16s} {r['seconds']:8.2f} s  {r['images_per_second']:7.3f} images/s  "
              f"(chunk {r['chunk']:,}, compile {r['compile_seconds']:.2f} s)")
    print(f"ratio {doc['ratio']:.2f}x; max |batched - loop| "
          f"{doc['max_abs_difference']['loop_same_chunk']:.3g} (same chunk), "
          f"{doc['max_abs_difference']['loop']:.3g} (default chunk) -> {out} "
          f"({p['total_seconds']:.1f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
