"""trimesh's ray interface three ways: jrt's intersector, trimesh's own, trimesh's Embree one.

    python -m benchmarks.trimesh_interface [--meshes camel,sphere] [--rays 65536]
        [--points 65536] [--trimesh-rays 2000] [--repeats 5] [--json out/trimesh.json]

On each mesh (the camel, 69,092 triangles; ``sphere``, trimesh's icosphere subdivided 6
times, 81,920 triangles), the two calls trimesh's own code makes most:

* ``intersects_location(origins, directions)`` with every hit of each ray (trimesh's
  default, ``multiple_hits=True``) on ``--rays`` rays through the mesh's bounding sphere
  (``jrt.raysets.incoherent_set``);
* ``contains_points(points)`` on ``--points`` points drawn uniformly in the mesh's
  bounding box (two rays a point inside the box, forward and backward).

Engines: ``jrt`` (``jrt.trimesh.RayMeshIntersector``, the BVH and the watertight kernel,
every core; compiled before the timing), ``embree`` (``trimesh.ray.ray_pyembree``, embreex,
one thread: that is how trimesh calls it) and ``trimesh`` (``trimesh.ray.ray_triangle``,
float64 NumPy and an rtree; on ``--trimesh-rays`` of the rays or points only, it is slow).
Each engine's calls are interleaved with the others' (``--repeats`` rounds), in one
process; rates are rays (or points) per second, medians. Agreement is checked on the
trimesh subset: the fraction of rays whose hit count equals trimesh's (float64), and of
points whose answer does; Embree's on the whole set against jrt's.
"""

from __future__ import annotations

import argparse
import importlib.util
import platform
import time

import numpy as np

from benchmarks.common import (
    comma_names,
    command_line,
    interleaved_times,
    summary,
    time_calls,
    write_record,
)

MESHES = ("camel", "sphere")
PROG = "python -m benchmarks.trimesh_interface"


def load(name: str):
    """A trimesh.Trimesh of a benchmark mesh."""
    import trimesh

    if name == "sphere":
        return trimesh.creation.icosphere(subdivisions=6)
    from jrt.data import mesh_path
    from jrt.mesh import load_mesh

    mesh = load_mesh(mesh_path(name))
    return trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)


def engines(mesh, log):
    """label -> intersector: jrt's, Embree's (if embreex imports), trimesh's own."""
    from trimesh.ray import ray_triangle

    from jrt.trimesh import RayMeshIntersector

    out = {"jrt": RayMeshIntersector(mesh)}
    if importlib.util.find_spec("embreex") is not None:
        from trimesh.ray import ray_pyembree

        out["embree"] = ray_pyembree.RayMeshIntersector(mesh)
    else:
        log("embree: embreex is not installed (pip install embreex); left out")
    out["trimesh"] = ray_triangle.RayMeshIntersector(mesh)
    mesh.triangles_tree  # noqa: B018  (trimesh's rtree, built outside the timing)
    return out


def counts(result, n):
    """Hits per ray from intersects_location's (locations, index_ray, index_tri)."""
    return np.bincount(result[1], minlength=n)


def bench_mesh(name, args, log) -> list[dict]:
    from jrt.raysets import incoherent_set

    mesh = load(name)
    rows = []
    found = engines(mesh, log)
    origins, directions = incoherent_set(np.asarray(mesh.vertices, np.float32), args.rays,
                                         seed=args.seed)
    origins, directions = origins.astype(np.float64), directions.astype(np.float64)
    rng = np.random.default_rng(args.seed + 1)
    lo, hi = mesh.bounds
    points = rng.uniform(lo, hi, (args.points, 3))
    few = slice(0, min(args.trimesh_rays, args.rays, args.points))
    queries = {
        "intersects_location": (
            lambda e, s=slice(None): e.intersects_location(origins[s], directions[s]),
            args.rays),
        "contains_points": (lambda e, s=slice(None): e.contains_points(points[s]),
                            args.points),
    }
    for query, (call, total) in queries.items():
        # Warm-up (jrt compiles its programs here) and the answers compared.
        start = time.perf_counter()
        answers = {label: call(e) for label, e in found.items() if label != "trimesh"}
        log(f"{name} {query}: first calls {time.perf_counter() - start:.1f} s")
        reference = call(found["trimesh"], few)
        mine_few = call(found["jrt"], few)
        if query == "intersects_location":
            n_few = few.stop
            agree = float(np.mean(counts(mine_few, n_few) == counts(reference, n_few)))
            embree_agree = (float(np.mean(counts(answers["embree"], total)
                                          == counts(answers["jrt"], total)))
                            if "embree" in answers else None)
            hits = int(len(answers["jrt"][1]))
        else:
            agree = float(np.mean(mine_few == reference))
            embree_agree = (float(np.mean(answers["embree"] == answers["jrt"]))
                            if "embree" in answers else None)
            hits = int(answers["jrt"].sum())
        fns = {label: (lambda e=e, call=call: call(e)) for label, e in found.items()
               if label != "trimesh"}
        times = interleaved_times(fns, args.repeats)
        slow = found["trimesh"]
        times["trimesh"] = time_calls(lambda call=call, slow=slow: call(slow, few), 1)
        for label, seconds in times.items():
            n = few.stop if label == "trimesh" else total
            rate = n / summary(seconds)["median"]
            rows.append({"mesh": name, "triangles": int(len(mesh.faces)), "query": query,
                         "engine": label, "items": n, "repeats": seconds,
                         "per_second": rate})
        jrt_rate = next(r["per_second"] for r in rows
                        if r["mesh"] == name and r["query"] == query and r["engine"] == "jrt")
        for r in rows:
            if r["mesh"] == name and r["query"] == query:
                r["jrt_speedup"] = jrt_rate / r["per_second"]
        rows.append({"mesh": name, "query": query, "engine": "agreement",
                     "with_trimesh": agree, "trimesh_items": few.stop,
                     "embree_with_jrt": embree_agree, "jrt_hits_or_inside": hits})
        for r in rows[-len(times) - 1:-1]:
            log(f"{name:7} {query:20} {r['engine']:8} {r['per_second']:12,.0f} /s "
                f"(jrt {r['jrt_speedup']:.2f}x)")
        log(f"{name:7} {query:20} agreement with trimesh {agree:.4f} on {few.stop}, "
            f"Embree with jrt {embree_agree}")
    return rows


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(prog=PROG, description=__doc__.split("\n\n")[0])
    parser.add_argument("--meshes", default="camel,sphere",
                        help=f"comma-separated, from {', '.join(MESHES)}")
    parser.add_argument("--rays", type=int, default=65536)
    parser.add_argument("--points", type=int, default=65536)
    parser.add_argument("--trimesh-rays", type=int, default=2000,
                        help="rays (and points) trimesh's own intersector traces")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", default=None, metavar="PATH")
    args = parser.parse_args(argv)
    try:
        meshes = comma_names(args.meshes, MESHES)
    except ValueError as error:
        parser.error(f"--meshes: {error}")
    for option in ("rays", "points", "trimesh_rays", "repeats"):
        if getattr(args, option) < 1:
            parser.error(f"--{option.replace('_', '-')} must be at least 1")
    import jrt

    jrt.tune_malloc()
    rows = []
    for name in meshes:
        rows += bench_mesh(name, args, print)
    record = {"kind": "trimesh_interface", "command": command_line(PROG, argv),
              "date": time.strftime("%Y-%m-%d"), "host": platform.processor()
              or platform.machine(), "rows": rows}
    if args.json:
        write_record(record, args.json)
    return record


if __name__ == "__main__":
    main()
