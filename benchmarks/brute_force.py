"""Brute-force rays/s of each triangle kernel on the camel, beside Embree, in one run.

    python -m benchmarks.brute_force [--rays 8192] [--repeats 3] [--json out/brute.json]

Each kernel traces a fixed subset of camera rays and of incoherent rays (see
``jrt.raysets``) by brute force (every ray against all 69,092 triangles), after one
warm-up call that compiles. Embree (embreex, robust mode) traces the same rays with one
thread and with one thread per core. Reported: rays/s, triangle tests/s, and the ratio to
Embree measured in this same process (absolute times drift on a shared machine).
"""

from __future__ import annotations

import argparse
import os
import platform

import accel
import jrt
from benchmarks.common import best_time, write_record
from benchmarks.peers import EmbreePeer
from jrt.raysets import camera_set, incoherent_set


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rays", type=int, default=8192, help="rays per set (default 8192)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--json", default="out/brute_force.json")
    args = parser.parse_args(argv)

    mesh = jrt.load_mesh(jrt.camel_path())
    structure = accel.build("brute", mesh.vertices, mesh.faces)
    embree = EmbreePeer(mesh.vertices, mesh.faces)
    cores = os.cpu_count() or 1
    sets = {
        "camera": camera_set(mesh.vertices, args.rays),
        "incoherent": incoherent_set(mesh.vertices, args.rays, seed=0),
    }
    sets = {k: (o[: args.rays], d[: args.rays]) for k, (o, d) in sets.items()}
    record = {"mesh": mesh.summary(), "triangles": structure.num_triangles, "rays": args.rays,
              "machine": f"{platform.machine()}, {cores} cores", "results": []}
    print(record["mesh"])
    print(f"{'set':<11} {'method':<22} {'rays/s':>12} {'Mtests/s':>9} {'x Embree(1t)':>13}")
    for name, (o, d) in sets.items():
        emb1 = best_time(lambda o=o, d=d: embree.closest_hit(o, d, threads=1), args.repeats)
        embn = best_time(lambda o=o, d=d: embree.closest_hit(o, d, threads=cores), args.repeats)
        rows = [("embree 1 thread", emb1), (f"embree {cores} threads", embn)]
        for kernel in jrt.KERNELS:
            run = lambda o=o, d=d, k=kernel: jrt.closest_hit(structure, o, d, kernel=k).t \
                .block_until_ready()  # noqa: E731
            run()  # compile
            rows.append((f"brute {kernel}", best_time(run, args.repeats)))
        for method, seconds in rows:
            rate = len(o) / seconds
            tests = rate * structure.num_triangles / 1e6 if method.startswith("brute") else None
            ratio = emb1 / seconds
            record["results"].append({"set": name, "method": method, "seconds": seconds,
                                      "rays_per_s": rate, "mtests_per_s": tests,
                                      "ratio_to_embree_1t": ratio})
            tests_text = f"{tests:9.0f}" if tests else f"{'':9}"
            print(f"{name:<11} {method:<22} {rate:12,.0f} {tests_text} {ratio:13.5f}")
    write_record(record, args.json)
    return record


if __name__ == "__main__":
    main()
