"""accel: acceleration structures built in NumPy and flattened to arrays.

``accel.build(name, mesh, **params)`` (or ``accel.build(name, vertices, faces, **params)``)
is the one entry point; ``accel.names()`` lists the structures, each declared once as an
:class:`accel.StructureKind` (``accel.registry``; a new one joins with ``accel.register``).
The record it returns (:class:`accel.structure.Structure`) is what
``jrt.closest_hit`` and ``jrt.occluded`` traverse. This package never imports JAX.
"""

from __future__ import annotations

import difflib
import inspect

import numpy as np

from accel.geometry import mesh_arrays
from accel.registry import (
    StructureKind,
    kind,
    kinds,
    names,
    planes,
    register,
    unregister,
)
from accel.structure import Structure


def __getattr__(name: str):
    # NAMES and SIGNATURES are views of the registry, computed when read, so that a kind
    # registered later (accel.register) is in them.
    if name == "NAMES":
        return names()
    if name == "SIGNATURES":
        return {k.name: (k.arrays, k.layout) for k in kinds()}
    raise AttributeError(f"module 'accel' has no attribute {name!r}")


def _builder(name: str):
    """The registered kind ``name``'s builder (a ValueError listing the names if unknown)."""
    return kind(name).build


def parameters(name: str) -> dict[str, object]:
    """The parameters of the builder ``name`` and their defaults (``accel.<name>.build``'s
    keyword arguments), e.g. ``parameters("bvh")["width"] == 4``."""
    signature = inspect.signature(_builder(name))
    return {p.name: p.default for p in list(signature.parameters.values())[2:]
            if p.kind in (p.KEYWORD_ONLY, p.POSITIONAL_OR_KEYWORD)}


def _mesh_arrays(mesh, faces):
    """(vertices, faces) from ``build``'s mesh argument(s), or a TypeError saying what is
    accepted."""
    usage = ("pass a mesh with 'vertices' and 'faces' attributes (jrt.Mesh, "
             "trimesh.Trimesh), accel.build(name, mesh), or the two arrays, "
             "accel.build(name, vertices, faces)")
    has_arrays = hasattr(mesh, "vertices") and hasattr(mesh, "faces")
    if faces is None:
        if has_arrays:
            return mesh.vertices, mesh.faces
        raise TypeError(f"accel.build got a {type(mesh).__name__} and no faces: {usage}")
    if has_arrays:
        raise TypeError(f"accel.build got a mesh ({type(mesh).__name__}) and faces as well: "
                        f"{usage}, not both")
    return mesh, faces


def build(name: str, mesh, faces=None, /, **params) -> Structure:
    """Build the structure ``name`` over a triangle mesh.

        accel.build("bvh", mesh)                       # jrt.Mesh, trimesh.Trimesh, ...
        accel.build("bvh", vertices, faces, width=8)   # or the arrays

    Args:
        name: a registered structure (:func:`names`).
        mesh: an object with ``vertices`` [V, 3] and ``faces`` [F, 3] attributes, or the
            vertices themselves (then ``faces`` is the second argument): float positions
            (stored as float32), all finite (a NaN or infinite coordinate is a
            ValueError naming the vertex).
        faces: int [F, 3] vertex indices, when ``mesh`` is the vertices.
        **params: the builder's own parameters (:func:`parameters`; an unknown one is a
            TypeError listing them).
    """
    builder = _builder(name)
    allowed = parameters(name)
    unknown = [key for key in params if key not in allowed]
    if unknown:
        key = unknown[0]
        close = difflib.get_close_matches(key, allowed, n=1)
        hint = f" (did you mean {close[0]!r}?)" if close else ""
        listed = ", ".join(f"{k}={v!r}" for k, v in allowed.items()) or "none"
        raise TypeError(f"unknown parameter {key!r} for accel.build({name!r}, ...){hint}; "
                        f"its parameters (with defaults): {listed}")
    vertices, faces = _mesh_arrays(mesh, faces)
    vertices, faces = mesh_arrays(vertices, faces)
    bad = ~np.isfinite(vertices).all(axis=1) if vertices.size else np.zeros(0, bool)
    if bad.any():
        first = int(np.flatnonzero(bad)[0])
        raise ValueError(f"vertex {first} is {vertices[first].tolist()} ({int(bad.sum())} "
                         "non-finite vertices); allowed: finite coordinates")
    return builder(vertices, faces, **params)


__all__ = ["NAMES", "SIGNATURES", "Structure", "StructureKind", "build", "kind", "kinds",
           "names", "parameters", "planes", "register", "unregister"]
