"""The Whitted renderer's speed against the engine's, in one process.

    python -m benchmarks.render [--scene glass-camel] [--width 640 --height 480]
                                [--samples 16] [--depth 8] [--spp 1] [--host]
                                [--repeats 3] [--json PATH]

Renders a scene warm with the renderer (``jrt.wavefront.renderer``: every level in one
compiled program, spectral camera rays as bundles) and, with ``--host``, with the
host-stepped reference tree (``jrt.whitted.host_radiance``: one host round trip per level
and per 32k-ray chunk), and times a warm ``jrt.closest_hit`` on 1M incoherent rays of the
same mesh with the same structure and kernel. Reported: warm seconds (best of
``--repeats``, interleaved), the ratio of each render to the closest-hit call, Mrays/s of
each (camera, secondary and shadow rays) against the engine's, the compile time, the render
program's memory (XLA's account; the device's peak where it reports one) and, with
``--host``, the largest difference between the two images relative to their peak.
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
    p.add_argument("--spp", type=int, default=1, help="camera rays per pixel (stratified)")
    p.add_argument("--host", action="store_true",
                   help="also time the host-stepped tree and compare the images")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--json", default=None, help="write the record here")
    return p


def _program_bytes(render) -> dict:
    """XLA's own account of the render program's memory (arguments, outputs, scratch)."""
    analysis = render.program.memory_analysis()
    if analysis is None:
        return {}
    return {"argument_bytes": int(analysis.argument_size_in_bytes),
            "output_bytes": int(analysis.output_size_in_bytes),
            "temp_bytes": int(analysis.temp_size_in_bytes)}


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
    render, params = wavefront.renderer(setup, **size, spp=args.spp)
    device_image = np.asarray(render(params), np.float64)
    device_first = time.perf_counter() - start
    device_stats = render.last_stats
    params = jax.device_put(params)

    mesh = setup.geometry.mesh  # the objects' incoherent rays (the floor's last two faces out)
    objects = np.asarray(mesh.vertices)[np.asarray(mesh.faces)[:-2].ravel()]
    origins, directions = incoherent_set(objects, args.rays, seed=0)
    origins, directions = jax.device_put(origins), jax.device_put(directions)

    def engine():
        return jax.block_until_ready(jrt.closest_hit(setup.device_structure, origins,
                                                     directions, kernel=kernel))

    engine()
    runs = {"device tree": lambda: jax.block_until_ready(render(params)),
            "closest_hit": engine}
    host_image = host_stats = None
    if args.host:
        start = time.perf_counter()
        host_image, host_stats = whitted.host_radiance(setup, **size)
        host_first = time.perf_counter() - start
        runs["host tree"] = lambda: whitted.host_radiance(setup, **size)
    times = interleaved_times(runs, args.repeats)
    best = {name: min(values) for name, values in times.items()}
    trees = [name for name in ("host tree", "device tree") if name in best]
    stats = {"device tree": device_stats, "host tree": host_stats}
    device = jax.devices()[0]
    record = {
        "benchmark": "render",
        "command": command_line("python -m benchmarks.render", argv),
        "device": f"{device.platform} {device.device_kind}", "devices": jax.device_count(),
        "scene": args.scene, "width": args.width, "height": args.height, "spp": args.spp,
        "channels": setup.channels, "max_depth": args.depth, "kernel": kernel,
        "rays_per_level": {name: list(stats[name].rays_per_level) for name in trees},
        "shadow_rays": {name: stats[name].shadow_rays for name in trees},
        "total_rays": {name: stats[name].total_rays for name in trees},
        "capacities": list(render.capacities),
        "seconds": times, "best_seconds": best,
        "first_call_seconds": {"device tree": device_first},
        "compile_seconds": {name: stats[name].compile_seconds for name in trees},
        "ratio_to_closest_hit": {name: best[name] / best["closest_hit"] for name in trees},
        "mrays_per_second": {name: stats[name].total_rays / best[name] / 1e6 for name in trees}
        | {"closest_hit": args.rays / best["closest_hit"] / 1e6},
        "program_memory": _program_bytes(render),
    }
    memory = device.memory_stats() if hasattr(device, "memory_stats") else None
    if memory and "peak_bytes_in_use" in memory:
        record["device_peak_bytes"] = int(memory["peak_bytes_in_use"])
    if host_image is not None:
        record["first_call_seconds"]["host tree"] = host_first
        peak = float(np.abs(host_image).max())
        record["max_difference_of_peak"] = float(np.abs(device_image - host_image).max()) / peak
    print(f"{args.scene} {args.width}x{args.height}, {setup.channels} channels, spp "
          f"{args.spp}, depth {args.depth} on {record['device']}; capacities "
          f"{list(render.capacities)}")
    for name in trees:
        print(f"  {name:12s} {best[name]:8.3f} s warm, x{record['ratio_to_closest_hit'][name]:.1f}"
              f" closest_hit, {stats[name].total_rays:,} rays "
              f"({list(stats[name].rays_per_level)} + {stats[name].shadow_rays:,} shadow), "
              f"{record['mrays_per_second'][name]:.2f} Mrays/s, compile "
              f"{record['compile_seconds'][name]:.2f} s")
    print(f"  closest_hit  {best['closest_hit']:8.3f} s warm on {args.rays:,} incoherent rays, "
          f"{record['mrays_per_second']['closest_hit']:.2f} Mrays/s")
    print(f"  render program memory {record['program_memory']}"
          + (f", device peak {record['device_peak_bytes'] / 2**20:.0f} MiB"
             if "device_peak_bytes" in record else ""))
    if host_image is not None:
        print(f"  images differ by at most {record['max_difference_of_peak']:.2e} of the peak")
    if args.json:
        write_record(record, args.json)
    return 0


if __name__ == "__main__":
    sys.exit(main())
