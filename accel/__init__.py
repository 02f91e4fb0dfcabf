"""accel: acceleration structures built in NumPy and flattened to arrays.

``accel.build(name, vertices, faces, **params)`` is the one entry point. The record it
returns (:class:`accel.structure.Structure`) is what ``jrt.closest_hit`` and
``jrt.occluded`` traverse. This package never imports JAX.
"""

from __future__ import annotations

import importlib

import numpy as np

from accel.structure import Structure

#: The structures, each a module ``accel.<name>`` with ``build(vertices, faces, **params)``
#: (and, for the traversal engine, ``jrt.<name>`` with ``traversal(structure)``).
NAMES: tuple[str, ...] = ("brute", "bvh", "kdtree", "octree", "bsp", "grid")

#: What each kind's record holds: the names of its arrays and the keys of its layout.
#: ``jrt`` checks a structure against them before tracing it, so that a record relabelled
#: as another kind (or missing an array) is an error, never a silent wrong answer.
SIGNATURES: dict[str, tuple[frozenset, frozenset]] = {
    "brute": (frozenset({"triangles", "triangle_ids"}), frozenset()),
    "bvh": (frozenset({"nodes", "triangles", "triangle_ids", "frame"}),
            frozenset({"leaf_bits", "width"})),
    "kdtree": (frozenset({"nodes", "bounds", "references", "triangles", "triangle_ids",
                          "frame"}), frozenset({"leaf_bits"})),
    "octree": (frozenset({"nodes", "references", "triangles", "triangle_ids", "frame"}),
               frozenset({"leaf_bits"})),
    "bsp": (frozenset({"nodes", "bounds", "references", "triangles", "triangle_ids",
                       "frame"}), frozenset({"leaf_bits"})),
    "grid": (frozenset({"cell_start", "grid", "references", "skip", "triangles",
                        "triangle_ids", "frame"}), frozenset()),
}


def build(name: str, vertices: np.ndarray, faces: np.ndarray, **params) -> Structure:
    """Build the structure ``name`` over a triangle mesh.

    Args:
        name: one of :data:`NAMES`.
        vertices: float [V, 3] positions (stored as float32), all finite (a NaN or
            infinite coordinate is a ValueError naming the vertex).
        faces: int [F, 3] vertex indices.
        **params: the builder's own parameters.
    """
    if name not in NAMES:
        raise ValueError(f"unknown acceleration structure {name!r}; allowed: {', '.join(NAMES)}")
    vertices = np.asarray(vertices)
    faces = np.asarray(faces)
    if vertices.ndim != 2 or vertices.shape[1] != 3:
        raise ValueError(f"vertices must have shape [V, 3], got {vertices.shape}")
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"faces must have shape [F, 3], got {faces.shape}")
    bad = ~np.isfinite(vertices).all(axis=1) if vertices.size else np.zeros(0, bool)
    if bad.any():
        first = int(np.flatnonzero(bad)[0])
        raise ValueError(f"vertex {first} is {vertices[first].tolist()} ({int(bad.sum())} "
                         "non-finite vertices); allowed: finite coordinates")
    return importlib.import_module(f"accel.{name}").build(vertices, faces, **params)


__all__ = ["NAMES", "SIGNATURES", "Structure", "build"]
