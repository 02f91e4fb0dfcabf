"""BVH build time against triangle count: the camel and its 4x and 16x subdivisions.

    python -m benchmarks.bvh_scaling [--levels 2] [--builds 3] [--json out/bvh_scaling.json]

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


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--levels", type=int, default=2, help="subdivision levels (default 2)")
    parser.add_argument("--builds", type=int, default=3)
    parser.add_argument("--method", default="sah", choices=("sah", "median"))
    parser.add_argument("--json", default="out/bvh_scaling.json")
    args = parser.parse_args(argv)

    mesh = jrt.load_mesh(jrt.camel_path())
    vertices, faces = mesh.vertices.astype(np.float64), mesh.faces.astype(np.int64)
    rows = []
    for level in range(args.levels + 1):
        if level:
            vertices, faces = igl.upsample(vertices, faces, 1)
        times = [accel.build("bvh", vertices, faces, method=args.method).stats["build_seconds"]
                 for _ in range(args.builds)]
        n = len(faces)
        seconds = statistics.median(times)
        rows.append({"triangles": n, "seconds_median": seconds, "seconds": times,
                     "ns_per_n_log2_n": seconds / (n * math.log2(n)) * 1e9})
        print(f"{n:>10,} triangles: {seconds:7.3f} s, "
              f"{rows[-1]['ns_per_n_log2_n']:.2f} ns per N log2 N", flush=True)
    n = np.log([r["triangles"] for r in rows])
    t = np.log([r["seconds_median"] for r in rows])
    exponent = float(np.polyfit(n, t, 1)[0]) if len(rows) > 1 else float("nan")
    print(f"fitted exponent: time ~ N^{exponent:.2f}")
    record = {"method": args.method, "rows": rows, "exponent": exponent}
    write_record(record, args.json)
    return record


if __name__ == "__main__":
    main()
