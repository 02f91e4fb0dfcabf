"""What a new ray count costs: the first call, then calls on counts never seen before.

    python -m benchmarks.compile_reuse [--mesh camel-19k] [--structure bvh]
                                       [--counts 1000,1001,1500,3000] [--moves 2]
                                       [--json PATH]

``jrt.closest_hit`` pads the rays to a size bucket (``jrt.trace.bucket_size``: 1024, then
2^k and 3 x 2^(k-1)), so a count in a bucket already compiled reuses its program; a small
structure's arrays are padded to buckets too (``jrt.trace.padded_structure``), so a mesh
moved and built again (``--moves``: turned by 10 degrees about the vertical axis each
time, whose structure has other array lengths) reuses it as well. Each
mode runs in a fresh process (the compiled programs, and JAX's on-disk cache, are not
shared): "buckets" as jrt runs by default, "no buckets" with ``JRT_SIZE_BUCKETS=0``, where
every new count compiles. A call's time is compile (if any) and trace together, as a user
sees it; the count of compiled traversal programs says which calls compiled.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

from benchmarks.common import write_record

MODES = {"no buckets": "0", "buckets": "1"}


def _child(mesh_name: str, structure_name: str, counts: list[int], moves: int) -> dict:
    """One process's calls (jrt imported here: the parent never starts JAX)."""
    import jax
    import numpy as np

    import accel
    import jrt
    from jrt import engine
    from jrt.raysets import incoherent_set

    mesh = jrt.load_mesh(jrt.mesh_path(mesh_name))
    structure = accel.build(structure_name, mesh)
    origins, directions = incoherent_set(mesh.vertices, max(counts), seed=0)
    programs = (jrt.brute.compiled_programs if structure_name == "brute"
                else engine.compiled_programs)
    calls = []
    for n in counts:
        start = time.perf_counter()
        hits = jax.block_until_ready(jrt.closest_hit(structure, origins[:n], directions[:n]))
        seconds = time.perf_counter() - start
        calls.append({"rays": n, "seconds": seconds, "programs": programs(),
                      "hits": int(np.sum(np.asarray(hits.triangle) >= 0))})
    centre = mesh.vertices.mean(axis=0)
    for move in range(1, moves + 1):
        angle = np.radians(10.0 * move)
        turn = np.array([[np.cos(angle), 0, np.sin(angle)], [0, 1, 0],
                         [-np.sin(angle), 0, np.cos(angle)]])
        vertices = ((mesh.vertices - centre) @ turn.T + centre).astype(np.float32)
        moved = accel.build(structure_name, vertices, mesh.faces)
        n = counts[0]
        start = time.perf_counter()
        hits = jax.block_until_ready(jrt.closest_hit(moved, origins[:n], directions[:n]))
        seconds = time.perf_counter() - start
        calls.append({"rays": n, "moved": move, "seconds": seconds, "programs": programs(),
                      "hits": int(np.sum(np.asarray(hits.triangle) >= 0)),
                      "rows": {k: int(np.shape(a)[0]) for k, a in moved.arrays.items()}})
    return {"mesh": mesh.summary(), "structure": structure_name, "calls": calls}


def _run_mode(mode: str, args) -> dict:
    env = dict(os.environ, JRT_SIZE_BUCKETS=MODES[mode])
    env.pop("JAX_COMPILATION_CACHE_DIR", None)  # measure compiles, not cache hits
    done = subprocess.run(
        [sys.executable, "-m", "benchmarks.compile_reuse", "--child", "--mesh", args.mesh,
         "--structure", args.structure, "--counts", args.counts, "--moves", str(args.moves)],
        capture_output=True, text=True, env=env, check=False)
    if done.returncode != 0:
        raise RuntimeError(f"the {mode!r} run failed:\n{done.stderr[-3000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def main(argv=None, prog=None) -> dict:
    parser = argparse.ArgumentParser(prog=prog, description=__doc__.split("\n\n")[0])
    parser.add_argument("--mesh", default="camel-19k", help="a shipped mesh (camel-19k)")
    parser.add_argument("--structure", default="bvh", help="an accel structure (bvh)")
    parser.add_argument("--counts", default="1000,1001,1500,3000",
                        help="ray counts, called in this order (the first compiles)")
    parser.add_argument("--moves", type=int, default=2,
                        help="then this many calls on the mesh turned by 10 degrees more "
                        "each time and built again (default 2)")
    parser.add_argument("--json", default=None, help="also write the record here")
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    try:
        counts = [int(c) for c in args.counts.split(",")]
    except ValueError:
        counts = []
    if not counts or any(c < 1 for c in counts):
        parser.error(f"--counts must be positive integers separated by commas, got "
                     f"{args.counts!r}")
    if args.moves < 0:
        parser.error(f"--moves must be 0 or more, got {args.moves}")
    if args.child:
        record = _child(args.mesh, args.structure, counts, args.moves)
        print(json.dumps(record))
        return record

    record = {"counts": counts, "modes": {}}
    for mode in MODES:
        result = _run_mode(mode, args)
        record["modes"][mode] = result
        record["mesh"], record["structure"] = result["mesh"], result["structure"]
    print(f"{record['mesh']}; {record['structure']}; closest_hit, compile included "
          "(programs: traversal programs compiled so far)")
    print(f"{'rays':>15} " + " ".join(f"{m + ' s (programs)':>24}" for m in MODES))
    for i, first in enumerate(record["modes"]["buckets"]["calls"]):
        cells = []
        for mode in MODES:
            call = record["modes"][mode]["calls"][i]
            cells.append(f"{call['seconds']:>16.3f} ({call['programs']})".rjust(24))
        label = f"{first['rays']}" + (f" moved {first['moved']}" if "moved" in first else "")
        print(f"{label:>15} " + " ".join(cells))
    if args.json:
        write_record(record, args.json)
    return record


if __name__ == "__main__":
    main()
