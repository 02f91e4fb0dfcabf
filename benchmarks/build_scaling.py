"""Build time against triangle count: the camel and its 4x and 16x subdivisions.

    python -m benchmarks.build_scaling [--structures bvh,kdtree,octree,bsp,grid]
        [--levels 2] [--builds 3] [--json out/build_scaling.json]

libigl's ``upsample`` splits every triangle in four (midpoint subdivision), so the meshes
have N, 4N and 16N triangles. Reported: the median build time of each, the time per
N log2 N (flat for O(N log N) growth) and the fitted exponent of time against N.
The helpers here are shared with the suite (``benchmarks.suite``).
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
from benchmarks.structures import ENGINE_STRUCTURES, structure_names


def subdivide(vertices, faces, levels: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """The mesh and its ``levels`` successive midpoint subdivisions (libigl ``upsample``).

    Returns ``levels + 1`` pairs of float64 vertices and int64 faces: N, 4N, 16N, ...
    triangles.
    """
    vertices, faces = np.asarray(vertices, np.float64), np.asarray(faces, np.int64)
    meshes = [(vertices, faces)]
    for _ in range(levels):
        vertices, faces = igl.upsample(vertices, faces, 1)
        meshes.append((vertices, faces))
    return meshes


def build_times(name: str, vertices, faces, builds: int) -> tuple[list[float], object]:
    """The build time (s) of each of ``builds`` builds, and the last structure built."""
    times, structure = [], None
    for _ in range(builds):
        structure = accel.build(name, vertices, faces)
        times.append(structure.stats["build_seconds"])
    return times, structure


def ns_per_n_log2_n(seconds: float, n: int) -> float:
    """Time per N log2 N, in ns: flat when the time grows as N log N."""
    return seconds / (n * math.log2(n)) * 1e9 if n > 1 else float("nan")


#: Distinct sizes a power law is fitted through: two points always lie on a line, so a
#: slope through two says nothing of the law (a quick run's two sizes gave N^1.61 and N^1.03).
MIN_FIT_SIZES = 3


def fit_exponent(counts, values) -> float:
    """k of ``value ~ count^k``: the slope of log(value) against log(count), least squares.

    NaN (written as null) with fewer than :data:`MIN_FIT_SIZES` distinct counts.
    """
    counts, values = np.asarray(counts, float), np.asarray(values, float)
    if len(np.unique(counts)) < MIN_FIT_SIZES:
        return float("nan")
    return float(np.polyfit(np.log(counts), np.log(values), 1)[0])


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--levels", type=int, default=2, help="subdivision levels (default 2)")
    parser.add_argument("--builds", type=int, default=3)
    parser.add_argument("--structures", type=structure_names, default=list(ENGINE_STRUCTURES),
                        help=f"comma-separated, from {','.join(ENGINE_STRUCTURES)}")
    parser.add_argument("--json", default="out/build_scaling.json")
    args = parser.parse_args(argv)

    mesh = jrt.load_mesh(jrt.camel_path())
    meshes = subdivide(mesh.vertices, mesh.faces, args.levels)
    record = {"structures": {}}
    for name in args.structures:
        rows = []
        for vertices, faces in meshes:
            times, _ = build_times(name, vertices, faces, args.builds)
            n = len(faces)
            seconds = statistics.median(times)
            rows.append({"triangles": n, "seconds_median": seconds, "seconds": times,
                         "ns_per_n_log2_n": ns_per_n_log2_n(seconds, n)})
            print(f"{name:<7} {n:>10,} triangles: {seconds:7.3f} s, "
                  f"{rows[-1]['ns_per_n_log2_n']:.2f} ns per N log2 N", flush=True)
        exponent = fit_exponent([r["triangles"] for r in rows],
                                [r["seconds_median"] for r in rows])
        print(f"{name:<7} fitted exponent: " + (f"time ~ N^{exponent:.2f}" if exponent == exponent
              else f"not fitted ({len(rows)} sizes; {MIN_FIT_SIZES} needed)"), flush=True)
        record["structures"][name] = {"rows": rows, "exponent": exponent}
    write_record(record, args.json)
    return record


if __name__ == "__main__":
    main()
