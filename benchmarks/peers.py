"""Intel Embree (through ``embreex``) as a reference for hits and as the peer in benchmarks.

embreex's ``run`` uses one thread per call; :meth:`EmbreePeer.closest_hit` splits a batch
over ``threads`` Python threads (embreex releases the GIL while Embree traces), from a pool
kept for the peer's life.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np


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
