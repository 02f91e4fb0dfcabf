"""The BVH against brute force on the full camel ray sets: every kernel, every ray.

    python -m benchmarks.bvh_correctness [--rays 1000000] [--sets camera,incoherent]
        [--kernels plane_barycentric,moller_trumbore,watertight] [--json out/bvh_correctness.json]

For each kernel and each set (camera, incoherent), closest hits must be identical (same
triangle, same t bit for bit, same u, v) and ``occluded`` must agree (tmax: half the rays
stop short of their closest hit, half go past it). Brute force tests every triangle, so
this takes minutes (the incoherent set, whose rays nearly all reach the mesh, most of
them); the test suite checks 20k rays of each set. ``--sets`` and ``--kernels`` run a part.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

import accel
import jrt
from benchmarks.common import comma_names, write_record
from jrt.raysets import camera_set, incoherent_set
from jrt.trace import as_numpy

#: The ray sets, by name: (origins, directions) of a mesh's vertices and a ray count.
SETS = {"camera": camera_set,
        "incoherent": lambda vertices, n: incoherent_set(vertices, n, seed=0)}


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rays", type=int, default=1_000_000)
    parser.add_argument("--sets", default=",".join(SETS),
                        help=f"comma-separated ray sets, from {', '.join(SETS)} (default all)")
    parser.add_argument("--kernels", default=",".join(jrt.KERNELS),
                        help=f"comma-separated triangle kernels, from {', '.join(jrt.KERNELS)} "
                             "(default all)")
    parser.add_argument("--json", default="out/bvh_correctness.json")
    args = parser.parse_args(argv)
    def names(option, text, allowed):
        try:
            return comma_names(text, allowed)
        except ValueError as exc:
            parser.error(f"{option}: {exc}")

    chosen_sets = names("--sets", args.sets, SETS)
    kernels = names("--kernels", args.kernels, tuple(jrt.KERNELS))

    mesh = jrt.load_mesh(jrt.camel_path())
    bvh = accel.build("bvh", mesh.vertices, mesh.faces)
    brute = accel.build("brute", mesh.vertices, mesh.faces)
    sets = {name: SETS[name](mesh.vertices, args.rays) for name in chosen_sets}
    record = {"mesh": mesh.summary(), "rays": args.rays, "results": []}
    rng = np.random.default_rng(2)
    for name, (o, d) in sets.items():
        o, d = o[: args.rays], d[: args.rays]
        for kernel in kernels:
            start = time.perf_counter()
            ref = as_numpy(jrt.closest_hit(brute, o, d, kernel=kernel))
            got = as_numpy(jrt.closest_hit(bvh, o, d, kernel=kernel))
            differ = np.zeros(len(o), bool)
            for key in ("triangle", "t", "u", "v"):
                differ |= ref[key] != got[key]
            tmax = np.where(np.isfinite(ref["t"]), ref["t"] * rng.choice([0.5, 1.5], len(o)),
                            10.0).astype(np.float32)
            occ_ref = np.asarray(jrt.occluded(brute, o, d, tmax=tmax, kernel=kernel))
            occ_got = np.asarray(jrt.occluded(bvh, o, d, tmax=tmax, kernel=kernel))
            row = {"set": name, "kernel": kernel, "rays": len(o),
                   "hits": int((ref["triangle"] >= 0).sum()),
                   "closest_hit_mismatches": int(differ.sum()),
                   "occluded": int(occ_ref.sum()),
                   "occluded_mismatches": int((occ_ref != occ_got).sum()),
                   "seconds": time.perf_counter() - start}
            record["results"].append(row)
            print(f"{name:<11} {kernel:<18} {row['rays']:,} rays, {row['hits']:,} hits: "
                  f"{row['closest_hit_mismatches']} closest-hit mismatches; "
                  f"{row['occluded']:,} occluded: {row['occluded_mismatches']} mismatches "
                  f"({row['seconds']:.0f} s)", flush=True)
    write_record(record, args.json)
    return record


if __name__ == "__main__":
    main()
