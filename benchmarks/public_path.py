"""The public call against the benchmark's: ``jrt.closest_hit`` on NumPy arrays with the
library's defaults, and on device arrays, beside Embree, in one process.

    python -m benchmarks.public_path [--set camera|incoherent] [--rays 1048576]
        [--repeats 7] [--tune-malloc]

The camel's BVH (watertight kernel); ``camera``: a 1024 x 1024 camera framing the camel
(``--rays`` is then the camera's pixel count, rounded to a square), ``incoherent``:
``jrt.raysets.incoherent_set``. Three calls in turn for ``--repeats`` rounds
(``benchmarks.common.interleaved_times``): Embree on every core (``EmbreePeer``, one
thread a core), ``jrt.closest_hit`` on the NumPy arrays (what a user's program passes), and
on ``jnp.asarray`` copies of them (device arrays, as the benchmark suite passes). With
``--tune-malloc`` the process applies ``jrt.tune_malloc()`` first (the benchmarks do).
Printed: each one's best call and the ratios.
"""

from __future__ import annotations

import argparse
import math
import os

import jax
import jax.numpy as jnp
import numpy as np

import accel
import jrt
from benchmarks.common import interleaved_times
from benchmarks.peers import EmbreePeer
from jrt.camera import camera_rays, frame_mesh
from jrt.data import mesh_path
from jrt.mesh import load_mesh
from jrt.raysets import incoherent_set


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.public_path",
                                     description=__doc__.split("\n\n")[0])
    parser.add_argument("--set", choices=("camera", "incoherent"), default="incoherent")
    parser.add_argument("--rays", type=int, default=1 << 20)
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--tune-malloc", action="store_true")
    args = parser.parse_args(argv)
    if args.rays < 1 or args.repeats < 1:
        parser.error("--rays and --repeats must be at least 1")
    if args.tune_malloc:
        jrt.tune_malloc()
    mesh = load_mesh(mesh_path("camel"))
    structure = accel.build("bvh", mesh)
    if args.set == "camera":
        side = max(1, math.isqrt(args.rays))
        origins, directions = (np.asarray(a, np.float32).reshape(-1, 3) for a in
                               camera_rays(frame_mesh(mesh.vertices, width=side, height=side)))
    else:
        origins, directions = incoherent_set(mesh.vertices, args.rays, seed=0)
    embree = EmbreePeer(mesh.vertices, mesh.faces)
    on_device = jnp.asarray(origins), jnp.asarray(directions)
    calls = {
        "embree": lambda: embree.closest_hit(origins, directions, threads=os.cpu_count()),
        "numpy": lambda: np.asarray(jrt.closest_hit(structure, origins, directions).t),
        "device": lambda: jax.block_until_ready(jrt.closest_hit(structure, *on_device).t),
    }
    for call in calls.values():  # compiles, and warms every path
        call()
    best = {label: min(times) for label, times in
            interleaved_times(calls, args.repeats).items()}
    ratios = {"numpy_x_embree": best["embree"] / best["numpy"],
              "device_x_embree": best["embree"] / best["device"],
              "numpy_over_device_time": best["numpy"] / best["device"]}
    print(f"{args.set}, {len(origins):,} rays, best of {args.repeats}: "
          + ", ".join(f"{k} {v * 1e3:.1f} ms" for k, v in best.items()))
    print(", ".join(f"{k} {v:.3f}" for k, v in ratios.items()))
    return {"set": args.set, "rays": len(origins), "best_seconds": best, **ratios}


if __name__ == "__main__":
    main()
