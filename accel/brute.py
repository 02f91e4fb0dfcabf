"""Brute force: no structure at all, every ray tests every triangle.

The baseline and the oracle every acceleration structure is checked against.
"""

from __future__ import annotations

import time

import numpy as np

from accel.geometry import degenerate_mask, triangle_vertices
from accel.registry import StructureKind
from accel.structure import Structure


def build(vertices: np.ndarray, faces: np.ndarray) -> Structure:
    """Store the non-degenerate triangles as a flat [T, 3, 3] float32 array."""
    start = time.perf_counter()
    keep = ~degenerate_mask(vertices, faces)
    ids = np.flatnonzero(keep).astype(np.int32)
    triangles = triangle_vertices(vertices, np.asarray(faces)[ids])
    arrays = {"triangles": triangles, "triangle_ids": ids}
    stats = {
        "build_seconds": time.perf_counter() - start,
        "triangles": int(ids.shape[0]),
        "degenerate_skipped": int((~keep).sum()),
        "bytes": int(triangles.nbytes + ids.nbytes),
    }
    return Structure(kind="brute", arrays=arrays, layout=(), stats=stats)


KIND = StructureKind(
    name="brute", build=build, arrays=frozenset({"triangles", "triangle_ids"}),
    traversal=None, planes=None, refit="jrt.refitting:refit_brute",
    summary="every ray against every triangle: the baseline the other structures must equal")
