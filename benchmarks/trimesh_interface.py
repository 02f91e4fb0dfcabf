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
    """label -> intersector: jrt's, Embree's (if embreex is installed), trimesh's own (if
    rtree is: its intersector needs it)."""
    from jrt.trimesh import RayMeshIntersector

    out = {"jrt": RayMeshIntersector(mesh)}
    if importlib.util.find_spec("embreex") is not None:
        from trimesh.ray import ray_pyembree

        out["embree"] = ray_pyembree.RayMeshIntersector(mesh)
    else:
        log("embree: embreex is not installed (pip install embreex); left out")
    if importlib.util.find_spec("rtree") is not None:
        from trimesh.ray import ray_triangle

        out["trimesh"] = ray_triangle.RayMeshIntersector(mesh)
        mesh.triangles_tree  # noqa: B018  (trimesh's rtree, built outside the timing)
    else:
        log("trimesh: its ray intersector needs rtree (pip install rtree); left out")
    return out


def counts(result, n):
    """Hits per ray from intersects_location's (locations, index_ray, index_tri)."""
    return np.bincount(result[1], minlength=n)


def interface_records(name, rays, points, trimesh_items, repeats, seed, log,
                      mesh=None) -> list[dict]:
    """The ``"trimesh_interface"`` records (``benchmarks.schema``) of one mesh: per query,
    one record per engine (items per second, the median of ``repeats`` interleaved calls;
    trimesh's own on ``trimesh_items`` of them, one call), the jrt record with the
    agreement counts. ``mesh``: a trimesh.Trimesh (default: :func:`load` of ``name``)."""
    from jrt.raysets import incoherent_set

    mesh = load(name) if mesh is None else mesh
    found = engines(mesh, log)
    origins, directions = incoherent_set(np.asarray(mesh.vertices, np.float32), rays,
                                         seed=seed)
    origins, directions = origins.astype(np.float64), directions.astype(np.float64)
    rng = np.random.default_rng(seed + 1)
    lo, hi = mesh.bounds
    cloud = rng.uniform(lo, hi, (points, 3))
    queries = {
        "intersects_location": (
            lambda e, s=slice(None): e.intersects_location(origins[s], directions[s]), rays),
        "contains_points": (lambda e, s=slice(None): e.contains_points(cloud[s]), points),
    }
    records = []
    for query, (call, total) in queries.items():
        few = slice(0, min(trimesh_items, total))
        # The first calls (jrt compiles here), and the answers compared.
        start = time.perf_counter()
        answers = {label: call(e) for label, e in found.items() if label != "trimesh"}
        first = time.perf_counter() - start
        reference = call(found["trimesh"], few) if "trimesh" in found else None
        mine = call(found["jrt"], few)
        if query == "intersects_location":
            def same(a, b, n):  # rays whose hit counts agree
                return int(np.sum(counts(a, n) == counts(b, n)))
            found_items = int(len(answers["jrt"][1]))
        else:
            def same(a, b, n):  # points whose answers agree
                return int(np.sum(a == b))
            found_items = int(answers["jrt"].sum())
        agree = None if reference is None else same(mine, reference, few.stop)
        embree = (same(answers["embree"], answers["jrt"], total) if "embree" in answers
                  else None)
        fns = {label: (lambda e=e, call=call: call(e)) for label, e in found.items()
               if label != "trimesh"}
        times = interleaved_times(fns, repeats)
        if "trimesh" in found:
            slow = found["trimesh"]
            times["trimesh"] = time_calls(lambda call=call, slow=slow, few=few: call(slow, few),
                                          1)
        rate = {label: (few.stop if label == "trimesh" else total)
                / summary(seconds)["median"] for label, seconds in times.items()}
        for label, seconds in times.items():
            record = {"kind": "trimesh_interface", "mesh": name,
                      "triangles": int(len(mesh.faces)), "query": query, "engine": label,
                      "items": few.stop if label == "trimesh" else total, "threads": None
                      if label == "jrt" else 1, "repeats": seconds,
                      "seconds": summary(seconds), "per_second": rate[label],
                      "jrt_speedup": rate["jrt"] / rate[label]}
            if label == "jrt":
                record.update(first_call_seconds=first, found=found_items,
                              trimesh_items=few.stop if agree is not None else None,
                              agree_with_trimesh=agree,
                              agree_with_embree=embree)
            records.append(record)
            log(f"{name:7} {query:20} {label:8} {rate[label]:12,.0f} /s "
                f"(jrt {record['jrt_speedup']:.2f}x)")
        for peer, n, of in (("trimesh", agree, few.stop), ("Embree", embree, total)):
            if n is not None:
                log(f"{name:7} {query:20} jrt agrees with {peer} on {n:,} of {of:,}")
    return records


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
    records = []
    for name in meshes:
        records += interface_records(name, args.rays, args.points, args.trimesh_rays,
                                     args.repeats, args.seed, print)
    record = {"command": command_line(PROG, argv), "date": time.strftime("%Y-%m-%d"),
              "host": platform.processor() or platform.machine(), "records": records}
    if args.json:
        write_record(record, args.json)
    return record


if __name__ == "__main__":
    main()
