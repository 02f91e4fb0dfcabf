"""Every acceleration structure on the camel, side by side with Embree in one process.

    python -m benchmarks.structures [--structures bvh,kdtree,octree,bsp,grid]
        [--rays 1000000] [--repeats 3] [--builds 3] [--json out/structures.json]

- Build: median of ``--builds`` builds per structure, with its statistics.
- Trace: closest hit on camera rays and incoherent rays (``jrt.raysets``), every XLA CPU
  device (one per core, see ``jrt._xla``) against Embree (embreex, robust mode) with one
  Python thread per core, in this same process; the best of ``--repeats`` warm calls, the
  first call (compile and run) apart; the speed-up over brute force, estimated from
  ``--brute-rays`` rays; steps, triangle tests and leaves per ray (the engine's counters).
- Agreement: every structure's hits against the BVH's on the same rays (the BVH itself is
  checked against brute force by ``benchmarks.bvh_correctness``).

Ratios to Embree are the figures to quote: absolute times drift on a shared machine.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import time

import jax
import numpy as np

import accel
import jrt
from benchmarks.common import best_time, write_record
from benchmarks.peers import EmbreePeer
from jrt.raysets import camera_set, incoherent_set
from jrt.trace import as_numpy

ENGINE_STRUCTURES = tuple(n for n in accel.NAMES if n != "brute")


def structure_names(value: str) -> list[str]:
    """``--structures`` of the benchmarks: comma-separated names, each an engine structure."""
    names = [v.strip() for v in value.split(",") if v.strip()]
    bad = [n for n in names if n not in ENGINE_STRUCTURES]
    if bad or not names:
        raise argparse.ArgumentTypeError(
            f"unknown structure(s) {bad}; allowed: {', '.join(ENGINE_STRUCTURES)}")
    return names


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--structures", type=structure_names, default=list(ENGINE_STRUCTURES),
                        help=f"comma-separated, from {','.join(ENGINE_STRUCTURES)}")
    parser.add_argument("--rays", type=int, default=1_000_000, help="rays per set")
    parser.add_argument("--brute-rays", type=int, default=4096)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--builds", type=int, default=3)
    parser.add_argument("--kernel", default="watertight", choices=tuple(jrt.KERNELS))
    parser.add_argument("--json", default="out/structures.json")
    args = parser.parse_args(argv)

    mesh = jrt.load_mesh(jrt.camel_path())
    cores = os.cpu_count() or 1
    record = {
        "mesh": mesh.summary(), "rays": args.rays, "kernel": args.kernel,
        "machine": f"{platform.machine()} {platform.processor()}, {cores} cores",
        "devices": [str(d) for d in jax.devices()], "jax": jax.__version__,
        "builds": {}, "trace": [],
    }
    print(record["mesh"], "|", len(jax.devices()), "XLA devices |", cores, "cores", flush=True)

    names = list(dict.fromkeys(["bvh", *args.structures]))  # the BVH is the reference
    built = {}
    for name in names:
        times = []
        for _ in range(args.builds):
            s = accel.build(name, mesh.vertices, mesh.faces)
            times.append(s.stats["build_seconds"])
        built[name] = s
        record["builds"][name] = {"seconds_median": statistics.median(times), "seconds": times,
                                  **s.stats}
        print(f"build {name:<7} median {statistics.median(times):6.3f} s "
              f"(min {min(times):.3f}, max {max(times):.3f}); {s.nbytes / 2**20:6.1f} MiB; "
              + ", ".join(f"{k} {v:.4g}" if isinstance(v, float) else f"{k} {v}"
                          for k, v in s.stats.items() if k != "build_seconds"), flush=True)

    brute = accel.build("brute", mesh.vertices, mesh.faces)
    embree = EmbreePeer(mesh.vertices, mesh.faces)
    sets = {"camera": camera_set(mesh.vertices, args.rays),
            "incoherent": incoherent_set(mesh.vertices, args.rays, seed=0)}
    print(f"{'set':<11} {'method':<14} {'Mrays/s':>9} {'x Embree':>9} {'x brute':>8} "
          f"{'first s':>8} {'steps':>6} {'tests':>6} {'leaves':>6} {'vs bvh':>7}", flush=True)
    for set_name, (o, d) in sets.items():
        o, d = o[: args.rays], d[: args.rays]
        n = len(o)
        oj, dj = jax.device_put(o), jax.device_put(d)
        t_emb = best_time(lambda o=o, d=d: embree.closest_hit(o, d, threads=cores),
                          args.repeats)
        ob, db = oj[: args.brute_rays], dj[: args.brute_rays]
        brute_run = lambda ob=ob, db=db: jax.block_until_ready(  # noqa: E731
            jrt.closest_hit(brute, ob, db, kernel=args.kernel))
        brute_run()
        t_brute = best_time(brute_run, 1) * n / len(ob)
        print(f"{set_name:<11} {'embree':<14} {n / t_emb / 1e6:9.3f} {1:9.3f}", flush=True)
        reference = None
        for name in names:
            s = built[name]

            def run(s=s, oj=oj, dj=dj):
                return jax.block_until_ready(jrt.closest_hit(s, oj, dj, kernel=args.kernel))

            start = time.perf_counter()
            hits = as_numpy(run())
            first = time.perf_counter() - start
            seconds = best_time(run, args.repeats)
            _, counts = jrt.closest_hit(s, oj, dj, kernel=args.kernel, counters=True)
            counts = {k: float(np.asarray(v).mean()) for k, v in counts._asdict().items()}
            if reference is None:
                reference = hits
            differ = np.zeros(n, bool)
            for key in ("triangle", "t", "u", "v"):
                differ |= hits[key] != reference[key]
            row = {"set": set_name, "method": f"jrt {name}", "rays": n, "seconds": seconds,
                   "mrays_per_s": n / seconds / 1e6, "ratio_to_embree": t_emb / seconds,
                   "speedup_over_brute": t_brute / seconds, "first_call_seconds": first,
                   "counters": counts, "mismatches_vs_bvh": int(differ.sum())}
            record["trace"].append(row)
            print(f"{set_name:<11} {'jrt ' + name:<14} {row['mrays_per_s']:9.3f} "
                  f"{row['ratio_to_embree']:9.3f} {row['speedup_over_brute']:8.0f} "
                  f"{first:8.1f} {counts['steps']:6.1f} {counts['tests']:6.1f} "
                  f"{counts['leaves']:6.1f} {row['mismatches_vs_bvh']:7d}", flush=True)
        record["trace"].append({"set": set_name, "method": "embree", "rays": n,
                                "seconds": t_emb, "mrays_per_s": n / t_emb / 1e6,
                                "ratio_to_embree": 1.0})
        record["trace"].append({"set": set_name, "method": "jrt brute (est.)", "rays": n,
                                "seconds": t_brute, "mrays_per_s": n / t_brute / 1e6,
                                "ratio_to_embree": t_emb / t_brute,
                                "estimated_from_rays": int(len(ob))})
    write_record(record, args.json)
    return record


if __name__ == "__main__":
    main()
