"""Build time against triangle count: the camel and its 4x and 16x subdivisions.

    python -m benchmarks.build_scaling [--structures bvh,kdtree,octree,bsp,grid]
        [--levels 2] [--builds 3] [--json out/build_scaling.json]

libigl's ``upsample`` splits every triangle in four (midpoint subdivision), so the meshes
have N, 4N and 16N triangles. Reported: the median build time of each, the time per
N log2 N (flat for O(N log N) growth) and the fitted exponent of time against N.
"""

from __future__ import annotations

import argparse
import math
import statistics

import igl
import numpy as np

import accel
import jrt
from benchmarks.common import write_record
from benchmarks.structures import ENGINE_STRUCTURES, _structures


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--levels", type=int, default=2, help="subdivision levels (default 2)")
    parser.add_argument("--builds", type=int, default=3)
    parser.add_argument("--structures", type=_structures, default=list(ENGINE_STRUCTURES),
                        help=f"comma-separated, from {','.join(ENGINE_STRUCTURES)}")
    parser.add_argument("--json", default="out/build_scaling.json")
    args = parser.parse_args(argv)

    mesh = jrt.load_mesh(jrt.camel_path())
    vertices, faces = mesh.vertices.astype(np.float64), mesh.faces.astype(np.int64)
    meshes = [(vertices, faces)]
    for _ in range(args.levels):
        vertices, faces = igl.upsample(vertices, faces, 1)
        meshes.append((vertices, faces))
    record = {"structures": {}}
    for name in args.structures:
        rows = []
        for vertices, faces in meshes:
            times = [accel.build(name, vertices, faces).stats["build_seconds"]
                     for _ in range(args.builds)]
            n = len(faces)
            seconds = statistics.median(times)
            rows.append({"triangles": n, "seconds_median": seconds, "seconds": times,
                         "ns_per_n_log2_n": seconds / (n * math.log2(n)) * 1e9})
            print(f"{name:<7} {n:>10,} triangles: {seconds:7.3f} s, "
                  f"{rows[-1]['ns_per_n_log2_n']:.2f} ns per N log2 N", flush=True)
        n = np.log([r["triangles"] for r in rows])
        t = np.log([r["seconds_median"] for r in rows])
        exponent = float(np.polyfit(n, t, 1)[0]) if len(rows) > 1 else float("nan")
        print(f"{name:<7} fitted exponent: time ~ N^{exponent:.2f}", flush=True)
        record["structures"][name] = {"rows": rows, "exponent": exponent}
    write_record(record, args.json)
    return record


if __name__ == "__main__":
    main()
