"""What moving a mesh costs: ``jrt.refit`` against a full ``accel.build``, in one process.

    python -m benchmarks.refit [--mesh camel] [--width 4] [--rounds 10] [--json PATH]

Each round moves the mesh (every vertex jittered by 1 % of the diagonal, then turned
about the vertical axis) and times, in turn (``benchmarks.common.interleaved_times``),
the BVH built from scratch for the moved vertices (``accel.build``, NumPy) and the built
BVH refit to them (``jax.jit(jrt.refit)``, compiled before the rounds, its result waited
for). Both give a structure on which the hits are brute force's; the refit keeps the old
tree's topology, so its trace rate is measured too (camera rays of the moved mesh,
against the rebuilt tree's), with the SAH cost of both trees.
"""

from __future__ import annotations

import argparse
import platform
import sys
import time

import numpy as np

import jrt  # noqa: F401  (XLA flags before JAX starts)
from benchmarks.common import command_line, interleaved_times, write_record

PROG = "python -m benchmarks.refit"


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=PROG, description=__doc__.split("\n\n")[0])
    p.add_argument("--mesh", default="camel", help="a packaged mesh name or a mesh file "
                   "(default camel)")
    p.add_argument("--width", type=int, default=4, choices=(2, 4, 8), help="BVH width")
    p.add_argument("--rounds", type=int, default=10, help="timing rounds (default 10)")
    p.add_argument("--rays", type=int, default=1 << 16, help="camera rays traced on each "
                   "tree (default 65536)")
    p.add_argument("--json", default=None, help="also write the record here")
    return p


def moved(vertices: np.ndarray, diagonal: float, seed: int, shift: float = 0.0,
          scale: float = 1.0) -> np.ndarray:
    """float32 vertices jittered by 1 % of ``diagonal``, turned about the vertical axis
    by a random angle, then scaled by ``scale`` and shifted by ``shift``."""
    rng = np.random.default_rng(seed)
    angle = rng.uniform(0, 2 * np.pi)
    c, s = np.cos(angle), np.sin(angle)
    rotation = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    jitter = rng.normal(0, 0.01 * diagonal, vertices.shape)
    return ((vertices + jitter) @ rotation.T * scale + shift).astype(np.float32)


def run(args) -> dict:
    import jax

    import accel
    from jrt.camera import camera_rays, frame_mesh
    from jrt.mesh import load_mesh

    mesh = load_mesh(jrt.mesh_path(args.mesh) if args.mesh in jrt.data.MESHES else args.mesh)
    vertices, faces = mesh.vertices, mesh.faces
    built = accel.build("bvh", vertices, faces, width=args.width)
    refit = jax.jit(jrt.refit)
    start = time.perf_counter()
    jax.block_until_ready(refit(built, vertices, faces))
    compile_seconds = time.perf_counter() - start
    poses = [moved(vertices, mesh.diagonal, seed) for seed in range(args.rounds)]
    turn = iter(range(args.rounds))
    current = {}

    def rebuild():
        current["build"] = accel.build("bvh", current["pose"], faces, width=args.width)

    def refitted():
        current["refit"] = jax.block_until_ready(refit(built, current["pose"], faces))

    def next_pose():
        current["pose"] = poses[next(turn)]

    times = interleaved_times({"pose": next_pose, "build": rebuild, "refit": refitted},
                              args.rounds)
    # The last pose: trace camera rays on both trees (hits equal, rates compared).
    side = int(np.sqrt(args.rays))
    camera = frame_mesh(current["pose"], side, side)
    origins, directions = camera_rays(camera)
    rates = {}
    for name in ("build", "refit"):
        structure = current[name]
        jax.block_until_ready(jrt.closest_hit(structure, origins, directions).t)
        best = np.inf
        for _ in range(5):
            start = time.perf_counter()
            jax.block_until_ready(jrt.closest_hit(structure, origins, directions).t)
            best = min(best, time.perf_counter() - start)
        rates[name] = len(origins) / best / 1e6
    same = all(np.array_equal(np.asarray(a), np.asarray(b)) for a, b in zip(
        jrt.closest_hit(current["build"], origins, directions),
        jrt.closest_hit(current["refit"], origins, directions), strict=True))
    build_s, refit_s = float(np.median(times["build"])), float(np.median(times["refit"]))
    return {
        "kind": "refit", "command": command_line(PROG), "date": time.strftime("%Y-%m-%d"),
        "machine": {"platform": platform.platform(), "processor": platform.processor(),
                    "jax": jax.__version__, "devices": [str(d) for d in jax.devices()]},
        "mesh": args.mesh, "triangles": int(len(faces)), "width": args.width,
        "rounds": args.rounds, "build_seconds": times["build"],
        "refit_seconds": times["refit"], "refit_compile_seconds": compile_seconds,
        "build_median_s": build_s, "refit_median_s": refit_s, "speedup": build_s / refit_s,
        "rays": int(len(origins)), "mrays_per_s_rebuilt": rates["build"],
        "mrays_per_s_refit": rates["refit"], "same_hits": bool(same),
        "sah_rebuilt": float(current["build"].stats["sah_cost"]),
    }


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    record = run(args)
    print(f"{record['mesh']} ({record['triangles']:,} triangles, width {record['width']}): "
          f"accel.build {record['build_median_s'] * 1e3:.1f} ms, jrt.refit "
          f"{record['refit_median_s'] * 1e3:.2f} ms (median of {record['rounds']} rounds, "
          f"in turn): refit {record['speedup']:.0f}x faster; compile once "
          f"{record['refit_compile_seconds']:.1f} s")
    print(f"camera rays on the moved mesh: rebuilt {record['mrays_per_s_rebuilt']:.3f} "
          f"Mrays/s, refit {record['mrays_per_s_refit']:.3f} Mrays/s; same hits: "
          f"{record['same_hits']}")
    if args.json:
        write_record(record, args.json)
    return 0 if record["same_hits"] else 1


if __name__ == "__main__":
    sys.exit(main())
