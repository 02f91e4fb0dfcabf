"""BVH on the camel: build, then closest hit and occlusion beside Embree, all cores for both.

    python -m benchmarks.bvh [--rays 1000000] [--repeats 5] [--json out/bvh.json]

- Build: the binned-SAH and object-median BVHs, median of ``--builds`` builds, with the
  statistics of the structure (nodes of the default width, 4).
- Width: closest hits of the SAH tree flattened to each of ``--widths`` (2, 4 and 8
  children a node), with their steps and tests per ray.
- Trace: camera rays (``jrt.raysets.camera_set``) and incoherent rays (origins on a
  sphere, aimed at random points of the box). jrt's BVH on every XLA CPU device (one per
  core, see ``jrt._xla``) against Embree (embreex, robust mode) with one Python thread per
  core, in this same process; jrt's first call (compile and run) is reported apart. The
  timed calls come in ``--repeats`` rounds, each calling Embree and every jrt variant in
  turn (``benchmarks.common.interleaved_times``), so that all meet the same drift of the
  machine's speed: rates are the best call of each, ``x Embree`` the ratio of the bests,
  and ``paired`` the median over the rounds of Embree's time over jrt's in the same
  round. Brute force runs on a subset of ``--brute-rays`` rays for the speed-up over it.
- Occlusion: any-hit rays toward each ray's closest hit (half of them stopped short).

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
import accel.bvh as accel_bvh
import jrt
from benchmarks.common import best_time, interleaved_times, write_record
from benchmarks.peers import EmbreePeer
from jrt.raysets import camera_set, incoherent_set


def _ready(x):
    return jax.block_until_ready(x)


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rays", type=int, default=1_000_000, help="rays per set")
    parser.add_argument("--brute-rays", type=int, default=8192,
                        help="rays of each set traced by brute force (default 8192)")
    parser.add_argument("--repeats", type=int, default=5,
                        help="timed rounds; each round calls jrt and Embree in turn")
    parser.add_argument("--builds", type=int, default=5)
    parser.add_argument("--kernel", default="watertight", choices=tuple(jrt.KERNELS))
    parser.add_argument("--lanes", type=int, default=None,
                        help="persistent lanes per device (default: jrt.engine.default_lanes, "
                             "by backend)")
    parser.add_argument("--widths", default="2,4,8",
                        help="node widths whose closest hits are timed (default 2,4,8)")
    parser.add_argument("--json", default="out/bvh.json")
    args = parser.parse_args(argv)
    try:
        widths = [int(w) for w in args.widths.split(",")]
        if any(w not in accel_bvh.WIDTHS for w in widths):
            raise ValueError
    except ValueError:
        parser.error(f"--widths: a comma list of {', '.join(map(str, accel_bvh.WIDTHS))}, "
                     f"got {args.widths!r}")

    mesh = jrt.load_mesh(jrt.camel_path())
    cores = os.cpu_count() or 1
    record = {
        "mesh": mesh.summary(), "rays": args.rays, "kernel": args.kernel,
        "machine": f"{platform.machine()} {platform.processor()}, {cores} cores",
        "devices": [str(d) for d in jax.devices()], "jax": jax.__version__,
        "builds": {}, "trace": [],
    }
    print(record["mesh"], "|", len(jax.devices()), "XLA devices |", cores, "cores")

    structures = {}
    for method in ("sah", "median"):
        times = []
        for _ in range(args.builds):
            s = accel.build("bvh", mesh.vertices, mesh.faces, method=method)
            times.append(s.stats["build_seconds"])
        structures[method] = s
        record["builds"][method] = {"seconds_median": statistics.median(times),
                                    "seconds": times, **s.stats}
        st = s.stats
        print(f"build {method:<6} median {statistics.median(times):.3f} s "
              f"(min {min(times):.3f}, max {max(times):.3f}); nodes {st['nodes']:,}, "
              f"leaves {st['leaves']:,}, depth {st['depth']}, "
              f"tris/leaf {st['triangles_per_leaf_mean']:.2f} "
              f"(max {st['triangles_per_leaf_max']}), SAH {st['sah_cost']:.2f}, "
              f"{st['bytes'] / 2**20:.1f} MiB")

    bvh = structures["sah"]
    wide = {w: accel.build("bvh", mesh.vertices, mesh.faces, width=w) for w in widths
            if w != bvh.stats["width"]}
    brute = accel.build("brute", mesh.vertices, mesh.faces)
    embree = EmbreePeer(mesh.vertices, mesh.faces)
    sets = {"camera": camera_set(mesh.vertices, args.rays),
            "incoherent": incoherent_set(mesh.vertices, args.rays, seed=0)}
    print(f"{'set':<11} {'query':<9} {'method':<18} {'Mrays/s':>9} {'x Embree':>9} "
          f"{'paired':>9} notes")
    for name, (o, d) in sets.items():
        o, d = o[: args.rays], d[: args.rays]
        n = len(o)
        oj, dj = jax.device_put(o), jax.device_put(d)

        def jrt_closest(s=bvh, oj=oj, dj=dj):
            return _ready(jrt.closest_hit(s, oj, dj, kernel=args.kernel, lanes=args.lanes))

        start = time.perf_counter()
        hits = jrt_closest()
        first = time.perf_counter() - start
        embree_closest = lambda o=o, d=d: embree.closest_hit(o, d, threads=cores)  # noqa: E731
        for run in (embree_closest, *(lambda s=s: jrt_closest(s) for s in wide.values())):
            run()  # every peer warm (compiled, threads started) before the timed rounds
        default = f"jrt bvh width {bvh.stats['width']}"
        closest = interleaved_times({
            "embree": embree_closest,
            default: jrt_closest,
            **{f"jrt bvh width {w}": (lambda s=s: jrt_closest(s)) for w, s in wide.items()},
        }, args.repeats)
        t_jrt = min(closest[default])
        ob, db = oj[: args.brute_rays], dj[: args.brute_rays]
        brute_run = lambda ob=ob, db=db: _ready(  # noqa: E731
            jrt.closest_hit(brute, ob, db, kernel=args.kernel))
        brute_run()
        t_brute = best_time(brute_run, 1) * n / len(ob)
        _, counts = jrt.closest_hit(bvh, oj, dj, kernel=args.kernel, lanes=args.lanes,
                                    counters=True)
        counts = {k: float(np.asarray(v).mean()) for k, v in counts._asdict().items()}
        rows = [
            ("closest", "embree", closest["embree"], ""),
            ("closest", default, closest[default],
             f"first call {first:.1f} s; {t_brute / t_jrt:,.0f}x brute force; "
             f"steps {counts['steps']:.1f}, tests {counts['tests']:.1f}, "
             f"leaves {counts['leaves']:.1f} per ray"),
            ("closest", "jrt brute (est.)", [t_brute], f"from {len(ob):,} rays"),
        ]
        for w, s in wide.items():
            _, c = jrt.closest_hit(s, oj, dj, kernel=args.kernel, lanes=args.lanes,
                                   counters=True)
            rows.append(("closest", f"jrt bvh width {w}", closest[f"jrt bvh width {w}"],
                         f"steps {float(np.asarray(c.steps).mean()):.1f}, "
                         f"tests {float(np.asarray(c.tests).mean()):.1f} per ray"))
        # Occlusion toward the closest hit: half the rays stop short of it.
        t_hit = np.asarray(hits.t)
        rng = np.random.default_rng(1)
        tmax = np.where(np.isfinite(t_hit), t_hit * rng.choice([0.5, 1.5], n), 10.0)
        tmax = tmax.astype(np.float32)
        tj = jax.device_put(tmax)
        occ_run = lambda oj=oj, dj=dj, tj=tj: _ready(  # noqa: E731
            jrt.occluded(bvh, oj, dj, tmax=tj, kernel=args.kernel, lanes=args.lanes))
        embree_occluded = lambda o=o, d=d, tm=tmax: embree.occluded(  # noqa: E731
            o, d, tm, threads=cores)
        occ_run()
        embree_occluded()
        occluded = interleaved_times({"embree": embree_occluded, default: occ_run},
                                     args.repeats)
        rows += [("occluded", "embree", occluded["embree"], ""),
                 ("occluded", default, occluded[default], "")]
        rounds = {"closest": closest, "occluded": occluded}  # the interleaved calls
        for query, method, times, notes in rows:
            seconds = min(times)
            ref = rounds[query]["embree"]
            rate = n / seconds / 1e6
            # Round by round: Embree's time over this method's (brute force, timed apart
            # on a subset, has none).
            paired = (statistics.median(e / t for e, t in zip(ref, times, strict=True))
                      if method in rounds[query] else None)
            record["trace"].append({
                "set": name, "query": query, "method": method, "rays": n,
                "seconds": seconds, "seconds_all": list(times), "mrays_per_s": rate,
                "ratio_to_embree": min(ref) / seconds, "ratio_to_embree_paired_median": paired,
                "notes": notes, **({"counters": counts, "first_call_seconds": first}
                                   if method == default and query == "closest" else {})})
            paired_text = "" if paired is None else f"{paired:9.3f}"
            print(f"{name:<11} {query:<9} {method:<18} {rate:9.3f} {min(ref) / seconds:9.3f} "
                  f"{paired_text:>9} {notes}")
    write_record(record, args.json)
    return record


if __name__ == "__main__":
    main()
