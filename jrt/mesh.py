"""Triangle meshes: loading through trimesh, validation at the boundary.

A :class:`Mesh` holds float32 vertices [V, 3] and int32 faces [F, 3] that passed
validation: not empty, finite coordinates, triangles only, indices in range. Degenerate
(zero-area) triangles are kept in the face list, so indices stay those of the file, but
they are counted, reported, and left out of every acceleration structure: never hit.
"""

from __future__ import annotations

import dataclasses
import warnings
from pathlib import Path

import numpy as np
import trimesh

from accel.geometry import degenerate_mask

SUFFIXES = (".off", ".obj", ".ply", ".stl")


class MeshError(ValueError):
    """A mesh that cannot be traced: the message names the mesh, the problem and the rule."""


@dataclasses.dataclass(frozen=True, eq=False)
class Mesh:
    """A validated triangle mesh.

    Attributes:
        vertices: float32 [V, 3].
        faces: int32 [F, 3], indices into ``vertices``.
        degenerate: int32 [D], indices of zero-area faces (never hit).
        name: where it came from (a file path or a label).
    """

    vertices: np.ndarray
    faces: np.ndarray
    degenerate: np.ndarray
    name: str = "mesh"

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """(lower, upper) corners of the bounding box, float32 [3] each."""
        return self.vertices.min(axis=0), self.vertices.max(axis=0)

    @property
    def diagonal(self) -> float:
        """Length of the bounding box's diagonal: the scene size."""
        lo, hi = self.bounds
        return float(np.linalg.norm(hi.astype(np.float64) - lo))

    def summary(self) -> str:
        text = f"{self.name}: {len(self.vertices):,} vertices, {len(self.faces):,} triangles"
        if len(self.degenerate):
            text += f", {len(self.degenerate):,} degenerate (zero area, never hit)"
        return text


def mesh_from_arrays(vertices, faces, name: str = "mesh") -> Mesh:
    """Validate arrays into a :class:`Mesh`; :class:`MeshError` says what is wrong."""
    vertices = np.asarray(vertices)
    faces = np.asarray(faces)
    if vertices.ndim != 2 or vertices.shape[1] != 3:
        raise MeshError(f"{name}: vertices must have shape [V, 3], got {vertices.shape}")
    if not np.issubdtype(vertices.dtype, np.number) or np.iscomplexobj(vertices):
        raise MeshError(f"{name}: vertices must be real numbers, got dtype {vertices.dtype}")
    if faces.size == 0 or len(vertices) == 0:
        raise MeshError(
            f"{name}: empty mesh ({len(vertices)} vertices, {len(faces)} faces); "
            "at least one triangle is needed"
        )
    if faces.ndim != 2 or faces.shape[1] != 3:
        corners = faces.shape[1] if faces.ndim == 2 else "a ragged number of"
        raise MeshError(
            f"{name}: faces must be triangles, shape [F, 3]; got {corners} corners per face "
            f"(shape {faces.shape}). Triangulate first, e.g. with "
            "trimesh.geometry.triangulate_quads"
        )
    if not np.issubdtype(faces.dtype, np.integer):
        if np.issubdtype(faces.dtype, np.floating) and np.all(np.isfinite(faces)) and np.all(
            faces == np.round(faces)
        ):
            faces = faces.astype(np.int64)
        else:
            raise MeshError(f"{name}: face indices must be integers, got dtype {faces.dtype}")
    with np.errstate(over="ignore", invalid="ignore"):
        v32 = vertices.astype(np.float32)
    bad = ~np.isfinite(v32)
    if bad.any():
        row = int(np.flatnonzero(bad.any(axis=1))[0])
        raise MeshError(
            f"{name}: {int(bad.any(axis=1).sum())} vertices have NaN or infinite coordinates "
            f"(in float32), the first is vertex {row} = {vertices[row].tolist()}; "
            "all coordinates must be finite"
        )
    out = (faces < 0) | (faces >= len(vertices))
    if out.any():
        row = int(np.flatnonzero(out.any(axis=1))[0])
        raise MeshError(
            f"{name}: face {row} = {faces[row].tolist()} refers to a vertex out of range; "
            f"allowed indices are 0..{len(vertices) - 1}"
        )
    f32 = faces.astype(np.int32)
    degenerate = np.flatnonzero(degenerate_mask(v32, f32)).astype(np.int32)
    if len(degenerate) == len(f32):
        raise MeshError(
            f"{name}: all {len(f32)} triangles are degenerate (zero area); "
            "at least one triangle of non-zero area is needed"
        )
    if len(degenerate):
        warnings.warn(
            f"{name}: {len(degenerate)} degenerate (zero-area) triangles kept but never hit "
            f"(first: face {int(degenerate[0])})",
            stacklevel=2,
        )
    return Mesh(np.ascontiguousarray(v32), np.ascontiguousarray(f32), degenerate, name)


def load_mesh(path) -> Mesh:
    """Load an OFF, OBJ, PLY or STL file through trimesh and validate it.

    The file is read as it is (``process=False``: no merging, no reordering), so face
    indices are the file's. Polygon faces are fan-triangulated by trimesh's loaders.
    """
    path = Path(path)
    if path.suffix.lower() not in SUFFIXES:
        raise MeshError(
            f"{path}: unsupported mesh format {path.suffix or '(none)'!r}; "
            f"allowed: {', '.join(SUFFIXES)}"
        )
    if not path.is_file():
        raise MeshError(f"{path}: no such mesh file")
    try:
        loaded = trimesh.load(path, process=False, force="mesh")
    except Exception as exc:  # trimesh raises many kinds; name the file in one
        raise MeshError(f"{path}: trimesh could not read it: {exc}") from exc
    faces = np.asarray(getattr(loaded, "faces", np.zeros((0, 3))))
    if faces.size == 0:
        faces = faces.reshape(0, 3)
    return mesh_from_arrays(np.asarray(loaded.vertices), faces, name=str(path))
