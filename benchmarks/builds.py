"""Build times of every structure beside Embree's, on scenes of the scene suite.

    python -m benchmarks.builds [--scenes camel,herd] [--structures bvh,...] [--builds 5]
        [--json out/builds.json]

Per scene: Embree's build (the scene made and committed: its constructor, then a first
one-ray query, which commits the scene, less a warm one-ray query) and each structure's
build (``accel.build``, the builder's own ``build_seconds``), ``--builds`` times each, in
one process, interleaved (Embree, then every structure, then again), so that a host's
drift reaches all of them alike. Printed and written: the median and the minimum of each,
and each structure's median relative to Embree's.
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

import accel
from benchmarks.common import write_record
from benchmarks.peers import EmbreePeer
from benchmarks.structures import ENGINE_STRUCTURES, structure_names
from jrt.scenes import SCENES, scene_mesh


def embree_build_seconds(vertices, faces) -> float:
    """Seconds to build and commit an Embree scene of the mesh (see the module's doc)."""
    origin = np.zeros((1, 3), np.float32)
    direction = np.float32([[0, 0, 1]])
    start = time.perf_counter()
    peer = EmbreePeer(vertices, faces)
    peer.scene.run(origin, direction)  # commits the scene
    first = time.perf_counter() - start
    start = time.perf_counter()
    peer.scene.run(origin, direction)
    return max(first - (time.perf_counter() - start), 0.0)


def measure(name_of_scene: str, structures, builds: int, size: str = "full") -> dict:
    """{"scene", "triangles", "embree": [s...], "structures": {name: [s...]}, ...}."""
    mesh = scene_mesh(name_of_scene, size=size)
    times = {"embree": [], **{n: [] for n in structures}}
    sah = {}
    for _ in range(builds):
        times["embree"].append(embree_build_seconds(mesh.vertices, mesh.faces))
        for n in structures:
            s = accel.build(n, mesh.vertices, mesh.faces)
            times[n].append(s.stats["build_seconds"])
            sah[n] = s.stats.get("sah_cost")
    embree = statistics.median(times["embree"])
    return {"scene": name_of_scene, "size": size, "triangles": len(mesh.faces),
            "builds": builds, "seconds": times,
            "median": {k: statistics.median(v) for k, v in times.items()},
            "min": {k: min(v) for k, v in times.items()},
            "ratio_to_embree": {n: statistics.median(times[n]) / embree for n in structures},
            "sah_cost": sah}


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.builds", description=__doc__
                                     .split("\n\n")[0])
    parser.add_argument("--scenes", default="camel,herd",
                        help=f"comma-separated, from {', '.join(SCENES)} (default camel,herd)")
    parser.add_argument("--size", choices=("full", "small"), default="full")
    parser.add_argument("--structures", type=structure_names, default=list(ENGINE_STRUCTURES))
    parser.add_argument("--builds", type=int, default=5)
    parser.add_argument("--json", default=None, metavar="PATH")
    args = parser.parse_args(argv)
    names = [s.strip() for s in args.scenes.split(",") if s.strip()]
    unknown = [s for s in names if s not in SCENES]
    if unknown or args.builds < 1:
        parser.error(f"unknown scene(s) {unknown}; allowed: {', '.join(SCENES)}" if unknown
                     else f"--builds must be at least 1, got {args.builds}")
    results = []
    for scene in names:
        r = measure(scene, args.structures, args.builds, args.size)
        results.append(r)
        print(f"{scene} ({r['triangles']:,} triangles), median of {args.builds} builds: "
              f"embree {r['median']['embree']:.3f} s; " + ", ".join(
                  f"{n} {r['median'][n]:.3f} s ({r['ratio_to_embree'][n]:.1f}x)"
                  for n in args.structures), flush=True)
    record = {"kind": "builds", "results": results}
    if args.json:
        write_record(record, args.json)
    return record


if __name__ == "__main__":
    main()
