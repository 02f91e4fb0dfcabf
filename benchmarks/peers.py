"""The other engines the benchmarks measure jrt against, and their records.

* Intel Embree (through ``embreex``), :class:`EmbreePeer`: the reference for hits and the
  peer every rate is compared with. embreex's ``run`` uses one thread per call;
  :meth:`EmbreePeer.closest_hit` splits a batch over ``threads`` Python threads (embreex
  releases the GIL while Embree traces), from a pool kept for the peer's life.
* trimesh's rtree intersector, Open3D's ``RaycastingScene`` and Mitsuba 3 (``llvm_ad_rgb``):
  :func:`trimesh_rows`, :func:`open3d_rows`, :func:`mitsuba_rows`, one ``"peer"`` record
  (``benchmarks.schema``) per ray set, or one saying why the peer did not run.

A ray set is the suite's ``benchmarks.suite.RaySet``: ``name``, ``query`` (``"closest"`` or
``"occluded"``), float32 ``origins`` and ``directions`` [N, 3], ``tmax``, ``rays`` and the
number of ``distinct`` rays it starts with.
"""

from __future__ import annotations

import importlib.util
import os
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from benchmarks.common import rates, summary, time_calls


class EmbreePeer:
    """Embree scene over a triangle mesh (float32 vertices [V,3], faces [F,3])."""

    def __init__(self, vertices, faces, robust: bool = True):
        from embreex import rtcore_scene
        from embreex.mesh_construction import TriangleMesh

        self.scene = rtcore_scene.EmbreeScene(robust=robust)
        corners = np.ascontiguousarray(np.asarray(vertices, np.float32)[np.asarray(faces)])
        self._mesh = TriangleMesh(self.scene, corners)
        self._pools: dict[int, ThreadPoolExecutor] = {}

    def _split(self, fn, n, threads):
        if threads <= 1 or n < 2 * threads:
            return [fn(0, n)]
        bounds = np.linspace(0, n, threads + 1).astype(int)
        # One pool a thread count, kept: an application tracing batch after batch keeps its
        # threads (as Embree's own task scheduler does) instead of starting new ones.
        if threads not in self._pools:
            self._pools[threads] = ThreadPoolExecutor(threads)
        return list(self._pools[threads].map(lambda i: fn(bounds[i], bounds[i + 1]),
                                             range(threads)))

    def _query(self, origins, directions, tmax, threads, **query):
        """embreex ``run`` over slices of the batch, one slice per thread."""
        o = np.ascontiguousarray(origins, np.float32)
        d = np.ascontiguousarray(directions, np.float32)
        dists = None if tmax is None else np.ascontiguousarray(
            np.broadcast_to(np.asarray(tmax, np.float32), (len(o),)))

        def run(a, b):
            kwargs = {} if dists is None else {"dists": dists[a:b].copy()}
            return self.scene.run(o[a:b], d[a:b], **query, **kwargs)

        return self._split(run, len(o), threads)

    def closest_hit(self, origins, directions, tmax=None, threads: int = 1) -> dict:
        """t (inf for a miss), triangle (-1), u, v: the same record as ``jrt.closest_hit``."""
        parts = self._query(origins, directions, tmax, threads, output=1)
        tri = np.concatenate([p["primID"] for p in parts]).astype(np.int32)
        hit = tri >= 0
        return {
            "t": np.where(hit, np.concatenate([p["tfar"] for p in parts]), np.inf).astype(
                np.float32),
            "triangle": np.where(hit, tri, -1).astype(np.int32),
            "u": np.where(hit, np.concatenate([p["u"] for p in parts]), 0).astype(np.float32),
            "v": np.where(hit, np.concatenate([p["v"] for p in parts]), 0).astype(np.float32),
        }

    def occluded(self, origins, directions, tmax=None, threads: int = 1) -> np.ndarray:
        """bool [N]: any hit before tmax."""
        parts = self._query(origins, directions, tmax, threads, query="OCCLUDED")
        return np.concatenate(parts) >= 0

    def query_call(self, ray_set, threads: int):
        """A call of the set's query on all its rays (``closest_hit`` or ``occluded``), to
        time."""
        if ray_set.query == "occluded":
            return lambda: self.occluded(ray_set.origins, ray_set.directions, ray_set.tmax,
                                         threads=threads)
        return lambda: self.closest_hit(ray_set.origins, ray_set.directions, threads=threads)


def peer_row(peer, ray_set, seconds, embree_rate, rays=None, threads=None, note="") -> dict:
    """A ``"peer"`` record (``benchmarks.schema``): ``peer``'s times on ``ray_set`` (all its
    rays, or ``rays`` of them) and its rate's ratio to Embree's median ``embree_rate``."""
    rays = ray_set.rays if rays is None else rays
    rate = rates(rays, seconds)
    return {"kind": "peer", "peer": peer, "set": ray_set.name, "query": ray_set.query,
            "status": "ok", "note": note, "rays": rays, "threads": threads,
            "repeats": seconds, "seconds": summary(seconds), "mrays_per_s": rate,
            "ratio_to_embree": rate["median"] / embree_rate if embree_rate else None}


def absent_peer(peer, status, note) -> dict:
    """A ``"peer"`` record of a peer that did not run: ``status`` (not installed, skipped,
    failed) and ``note`` (how to install it, or the error)."""
    return {"kind": "peer", "peer": peer, "set": None, "query": None, "status": status,
            "note": note, "rays": None, "threads": None, "repeats": [], "seconds": None,
            "mrays_per_s": None, "ratio_to_embree": None}


def ray_subset(ray_set, count: int, seed: int, pad: bool = False) -> np.ndarray:
    """Sorted indices of ``count`` distinct rays of a set (drawn from its distinct rows).

    With ``pad``, a set with fewer distinct rays gives all of them, repeated up to
    ``count`` (so that every set's subset has one shape, and one compiled query).
    """
    rng = np.random.default_rng(seed)
    pool = ray_set.distinct
    idx = np.sort(rng.choice(pool, min(count, pool), replace=False))
    return np.resize(idx, count) if pad and len(idx) < count else idx


def trimesh_rows(mesh, sets, embree_rates, count: int, seed: int, log) -> list[dict]:
    """trimesh's rtree intersector (one thread, one call) on ``count`` rays of each set."""
    if count == 0:
        return [absent_peer("trimesh", "skipped", "--trimesh-rays 0")]
    if importlib.util.find_spec("rtree") is None:  # trimesh's intersector needs it
        log("trimesh: not installed (its ray intersector needs rtree: pip install rtree)")
        return [absent_peer("trimesh", "not installed",
                            "pip install rtree (trimesh's ray intersector needs it)")]
    try:
        import trimesh
        from trimesh.ray.ray_triangle import RayMeshIntersector

        tm = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
        intersector = RayMeshIntersector(tm)
        tm.triangles_tree  # noqa: B018  (builds the rtree now, outside the timing)
    except Exception as exc:  # noqa: BLE001  (any failure: recorded, the suite goes on)
        log(f"trimesh: skipped ({type(exc).__name__}: {exc})")
        return [absent_peer("trimesh", "failed", f"{type(exc).__name__}: {exc}")]
    rows = []
    for ray_set in sets.values():
        idx = ray_subset(ray_set, count, seed)
        o = ray_set.origins[idx].astype(np.float64)
        d = ray_set.directions[idx].astype(np.float64)
        if ray_set.query == "occluded":
            fn = lambda o=o, d=d: intersector.intersects_any(o, d)  # noqa: E731
            note = ("intersects_any on infinite rays (the lamp lies outside the mesh's box, "
                    "so nothing lies beyond it); one call, one thread")
        else:
            fn = lambda o=o, d=d: intersector.intersects_first(o, d)  # noqa: E731
            note = "intersects_first; one call, one thread"
        rows.append(peer_row("trimesh", ray_set, time_calls(fn, 1),
                             embree_rates[ray_set.name], rays=len(idx), threads=1, note=note))
    return rows


def open3d_rows(mesh, sets, embree_rates, repeats: int) -> list[dict]:
    """Open3D's ``RaycastingScene`` (all cores), when installed."""
    if importlib.util.find_spec("open3d") is None:
        return [absent_peer("open3d", "not installed", "pip install open3d (needs the "
                                                       "system library libusb-1.0)")]
    try:
        import open3d as o3d

        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(o3d.core.Tensor(mesh.vertices.astype(np.float32)),
                            o3d.core.Tensor(mesh.faces.astype(np.uint32)))
        rows = []
        for ray_set in sets.values():
            if ray_set.query == "occluded":
                # tfar is one number: scale each direction by its tmax and stop at t = 1.
                d = ray_set.directions * ray_set.tmax[:, None]
                rays = o3d.core.Tensor(np.hstack([ray_set.origins, d]).astype(np.float32))
                fn = lambda rays=rays: scene.test_occlusions(rays, tfar=1.0).numpy()  # noqa: E731
            else:
                rays = o3d.core.Tensor(
                    np.hstack([ray_set.origins, ray_set.directions]).astype(np.float32))
                fn = lambda rays=rays: scene.cast_rays(rays)["t_hit"].numpy()  # noqa: E731
            fn()
            rows.append(peer_row("open3d", ray_set, time_calls(fn, repeats),
                                 embree_rates[ray_set.name], threads=os.cpu_count(),
                                 note="RaycastingScene, all cores"))
        return rows
    except Exception as exc:  # noqa: BLE001
        return [absent_peer("open3d", "failed", f"{type(exc).__name__}: {exc}")]


def mitsuba_rows(mesh, sets, embree_rates, repeats: int) -> list[dict]:
    """Mitsuba 3's ``llvm_ad_rgb`` variant (ray_intersect_preliminary / ray_test)."""
    if importlib.util.find_spec("mitsuba") is None:
        return [absent_peer("mitsuba", "not installed", "pip install mitsuba")]
    try:
        import drjit as dr
        import mitsuba as mi

        mi.set_variant("llvm_ad_rgb")
        m = mi.Mesh("camel", vertex_count=len(mesh.vertices), face_count=len(mesh.faces),
                    has_vertex_normals=False, has_vertex_texcoords=False)
        params = mi.traverse(m)
        params["vertex_positions"] = mi.Float(mesh.vertices.astype(np.float32).ravel())
        params["faces"] = mi.UInt32(mesh.faces.astype(np.uint32).ravel())
        params.update()
        scene = mi.load_dict({"type": "scene", "camel": m})
        rows = []
        for ray_set in sets.values():
            o, d = ray_set.origins, ray_set.directions
            ray = mi.Ray3f(mi.Point3f(*(mi.Float(o[:, k]) for k in range(3))),
                           mi.Vector3f(*(mi.Float(d[:, k]) for k in range(3))))
            if ray_set.query == "occluded":
                ray.maxt = mi.Float(ray_set.tmax)

                def fn(ray=ray):
                    out = scene.ray_test(ray)
                    dr.eval(out)
                    dr.sync_thread()
            else:
                def fn(ray=ray):
                    out = scene.ray_intersect_preliminary(ray)
                    dr.eval(out.t)
                    dr.sync_thread()
            fn()
            rows.append(peer_row("mitsuba", ray_set, time_calls(fn, repeats),
                                 embree_rates[ray_set.name], threads=os.cpu_count(),
                                 note="llvm_ad_rgb variant"))
        return rows
    except Exception as exc:  # noqa: BLE001
        return [absent_peer("mitsuba", "failed", f"{type(exc).__name__}: {exc}")]


__all__ = ["EmbreePeer", "absent_peer", "mitsuba_rows", "open3d_rows", "peer_row", "ray_subset",
           "trimesh_rows"]
