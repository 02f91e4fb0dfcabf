"""The Whitted renderer's speed against the engine's, in one process.

    python -m benchmarks.render [--scene glass-camel] [--width 640 --height 480]
                                [--samples 16] [--depth 8] [--repeats 3] [--json PATH]

Renders a scene warm with the host-stepped tree (``jrt.whitted.render_radiance``: one host
round trip per level and per 32k-ray chunk) and with the device tree
(``jrt.wavefront.render_radiance``: every level in one compiled program), and times a warm
``jrt.closest_hit`` on 1M incoherent rays of the same mesh with the same structure and
kernel. Reported: warm seconds (best of ``--repeats``, interleaved), the ratio of each
render to the closest-hit call, Mrays/s of each (camera, secondary and shadow rays) against
the engine's, the compile time, and the largest difference between the two images relative
to their peak.
"""

from __future__ import annotations

import argparse
import sys
import time

from benchmarks.common import command_line, interleaved_times, write_record


def build_parser(prog: str = "python -m benchmarks.render") -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=prog, description=__doc__.split("\n\n")[0])
    p.add_argument("--scene", default="glass-camel", help="built-in scene or TOML path")
    p.add_argument("--width", type=int, default=640)
    p.add_argument("--height", type=int, default=480)
    p.add_argument("--samples", type=int, default=16, help="wavelength samples (spectral)")
    p.add_argument("--depth", type=int, default=8, help="tree levels")
    p.add_argument("--rays", type=int, default=1 << 20, help="incoherent rays of the engine")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--json", default=None, help="write the record here")
    return p


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    import jax
    import numpy as np

    import jrt
    from jrt import wavefront, whitted
    from jrt.raysets import incoherent_set

    setup = whitted.prepare(args.scene, samples=args.samples)
    size = dict(width=args.width, height=args.height, max_depth=args.depth)
    kernel = setup.scene.settings.kernel

    start = time.perf_counter()
    host_image, host_stats = whitted.render_radiance(setup, **size)
    host_first = time.perf_counter() - start
    start = time.perf_counter()
    device_image, device_stats, capacities = wavefront.render_radiance(setup, **size)
    device_first = time.perf_counter() - start

    mesh = setup.geometry.mesh  # the objects' incoherent rays (the floor's last two faces out)
    objects = np.asarray(mesh.vertices)[np.asarray(mesh.faces)[:-2].ravel()]
    origins, directions = incoherent_set(objects, args.rays, seed=0)
    origins, directions = jax.device_put(origins), jax.device_put(directions)

    def engine():
        return jax.block_until_ready(jrt.closest_hit(setup.device_structure, origins,
                                                     directions, kernel=kernel))

    engine()
    times = interleaved_times({
        "host tree": lambda: whitted.render_radiance(setup, **size),
        "device tree": lambda: wavefront.render_radiance(setup, **size, capacities=capacities),
        "closest_hit": engine,
    }, args.repeats)
    best = {name: min(values) for name, values in times.items()}
    rays = host_stats.total_rays
    peak = float(np.abs(host_image).max())
    record = {
        "benchmark": "render",
        "command": command_line("python -m benchmarks.render", argv),
        "scene": args.scene, "width": args.width, "height": args.height,
        "channels": setup.channels, "max_depth": args.depth, "kernel": kernel,
        "rays_per_level": list(host_stats.rays_per_level),
        "shadow_rays": host_stats.shadow_rays, "total_rays": rays,
        "capacities": list(capacities),
        "seconds": times, "best_seconds": best,
        "first_call_seconds": {"host tree": host_first, "device tree": device_first},
        "compile_seconds": {"host tree": host_stats.compile_seconds,
                            "device tree": device_stats.compile_seconds},
        "ratio_to_closest_hit": {name: best[name] / best["closest_hit"]
                                 for name in ("host tree", "device tree")},
        "mrays_per_second": {"host tree": rays / best["host tree"] / 1e6,
                             "device tree": rays / best["device tree"] / 1e6,
                             "closest_hit": args.rays / best["closest_hit"] / 1e6},
        "max_difference_of_peak": float(np.abs(device_image - host_image).max()) / peak,
        "same_rays_per_level": device_stats.rays_per_level == host_stats.rays_per_level,
    }
    print(f"{args.scene} {args.width}x{args.height}, {setup.channels} channels, depth "
          f"{args.depth}: {rays:,} rays; capacities {list(capacities)}")
    for name in ("host tree", "device tree"):
        print(f"  {name:12s} {best[name]:8.3f} s warm, x{record['ratio_to_closest_hit'][name]:.1f}"
              f" closest_hit, {record['mrays_per_second'][name]:.2f} Mrays/s, compile "
              f"{record['compile_seconds'][name]:.2f} s")
    print(f"  closest_hit  {best['closest_hit']:8.3f} s warm on {args.rays:,} incoherent rays, "
          f"{record['mrays_per_second']['closest_hit']:.2f} Mrays/s")
    print(f"  images differ by at most {record['max_difference_of_peak']:.2e} of the peak")
    if args.json:
        write_record(record, args.json)
    return 0


if __name__ == "__main__":
    sys.exit(main())
