"""Every structure against the BVH on the full camel ray sets: every kernel, every ray.

    python -m benchmarks.structures_correctness [--structures kdtree,octree,bsp,grid]
        [--rays 1000000] [--json out/structures_correctness.json]

For each kernel and each set (camera, incoherent), each structure's closest hits must be
the BVH's (same triangle, same t bit for bit, same u, v), and ``occluded`` must agree
(tmax: half the rays stop short of their closest hit, half go past it). The BVH is the
reference because brute force takes minutes a set; ``benchmarks.bvh_correctness`` checks
the BVH against brute force on the same rays.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

import accel
import jrt
from benchmarks.common import write_record
from benchmarks.structures import ENGINE_STRUCTURES, structure_names
from jrt.raysets import camera_set, incoherent_set
from jrt.trace import as_numpy


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    others = [n for n in ENGINE_STRUCTURES if n != "bvh"]
    parser.add_argument("--structures", type=structure_names, default=others,
                        help=f"comma-separated, from {','.join(others)}")
    parser.add_argument("--rays", type=int, default=1_000_000)
    parser.add_argument("--json", default="out/structures_correctness.json")
    args = parser.parse_args(argv)

    mesh = jrt.load_mesh(jrt.camel_path())
    bvh = accel.build("bvh", mesh.vertices, mesh.faces)
    built = {name: accel.build(name, mesh.vertices, mesh.faces) for name in args.structures}
    sets = {"camera": camera_set(mesh.vertices, args.rays),
            "incoherent": incoherent_set(mesh.vertices, args.rays, seed=0)}
    record = {"mesh": mesh.summary(), "rays": args.rays, "reference": "bvh", "results": []}
    rng = np.random.default_rng(2)
    for set_name, (o, d) in sets.items():
        o, d = o[: args.rays], d[: args.rays]
        for kernel in jrt.KERNELS:
            ref = as_numpy(jrt.closest_hit(bvh, o, d, kernel=kernel))
            tmax = np.where(np.isfinite(ref["t"]), ref["t"] * rng.choice([0.5, 1.5], len(o)),
                            10.0).astype(np.float32)
            occ_ref = np.asarray(jrt.occluded(bvh, o, d, tmax=tmax, kernel=kernel))
            for name, s in built.items():
                start = time.perf_counter()
                got = as_numpy(jrt.closest_hit(s, o, d, kernel=kernel))
                differ = np.zeros(len(o), bool)
                for key in ("triangle", "t", "u", "v"):
                    differ |= ref[key] != got[key]
                occ = np.asarray(jrt.occluded(s, o, d, tmax=tmax, kernel=kernel))
                row = {"set": set_name, "kernel": kernel, "structure": name, "rays": len(o),
                       "hits": int((ref["triangle"] >= 0).sum()),
                       "closest_hit_mismatches": int(differ.sum()),
                       "occluded": int(occ_ref.sum()),
                       "occluded_mismatches": int((occ_ref != occ).sum()),
                       "seconds": time.perf_counter() - start}
                record["results"].append(row)
                print(f"{set_name:<11} {kernel:<18} {name:<7} {row['rays']:,} rays, "
                      f"{row['hits']:,} hits: {row['closest_hit_mismatches']} closest-hit "
                      f"mismatches; {row['occluded']:,} occluded: "
                      f"{row['occluded_mismatches']} mismatches ({row['seconds']:.0f} s)",
                      flush=True)
    write_record(record, args.json)
    return record


if __name__ == "__main__":
    main()
