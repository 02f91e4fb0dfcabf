"""Triangle meshes: loading through trimesh, validation at the boundary.

A :class:`Mesh` holds float32 vertices [V, 3] and int32 faces [F, 3] that passed
validation: not empty, finite coordinates, triangles only, indices in range. Degenerate
(zero-area) triangles are kept in the face list, so indices stay those of the file, but
they are counted, reported (a :class:`MeshWarning`), and left out of every acceleration
structure: never hit. Arrays must hold triangles already; a file's polygons are split into
triangles when it is loaded, with a :class:`MeshWarning` that says how many.
"""

from __future__ import annotations

import dataclasses
import gzip
import io
import re
import warnings
import zlib
from pathlib import Path

import numpy as np
import trimesh

from accel.geometry import degenerate_mask

SUFFIXES = (".off", ".obj", ".ply", ".stl")


def mesh_suffix(path: str | Path) -> str:
    """The format suffix of a mesh file: ``.off`` for ``camel.off`` and ``camel.off.gz``."""
    path = Path(path)
    return Path(path.stem).suffix if path.suffix.lower() == ".gz" else path.suffix


class MeshError(ValueError):
    """A mesh that cannot be traced: the message names the mesh, the problem and the rule."""


class MeshWarning(UserWarning):
    """A mesh that can be traced, with something its user should know: degenerate
    triangles (kept, never hit), or a file's polygons split into triangles. The ``jrt``
    command prints these as notes."""


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
            f"{name}: {len(degenerate)} degenerate (zero-area) "
            f"triangle{'s' if len(degenerate) > 1 else ''} kept but never hit "
            f"(first: face {int(degenerate[0])})",
            MeshWarning,
            stacklevel=2,
        )
    return Mesh(np.ascontiguousarray(v32), np.ascontiguousarray(f32), degenerate, name)


def _file_faces(data: bytes, fmt: str) -> tuple[int, np.ndarray | None] | None:
    """The faces a mesh file lists, as (count, corners of each face), read from the text
    the way trimesh's loaders read it: OFF (a corner count opens each face line) and OBJ
    (``f`` lines); PLY gives only its header's count (corners ``None``). ``None`` where the
    file cannot be read so (STL holds triangles only)."""
    try:
        if fmt == "obj":
            rows = re.findall(rb"^[ \t]*f[ \t]+([^\r\n#]*)", data, re.M)
            return len(rows), np.array([len(row.split()) for row in rows], np.int64)
        if fmt == "ply":
            found = re.search(rb"^element[ \t]+face[ \t]+(\d+)",
                              data[: data.find(b"end_header")], re.M)
            return (int(found.group(1)), None) if found else None
        if fmt == "off":
            text = re.sub(r"#[^\n]*", "", data.decode("utf-8", "replace"))
            lines = [s for s in (t.strip() for t in
                                 re.split("(?:COFF|OFF)", text, maxsplit=1)[1].splitlines()) if s]
            n_vertices, n_faces = (int(x) for x in lines[0].split()[:2])
            rows = lines[1 + n_vertices: 1 + n_vertices + n_faces]
            return n_faces, np.array([int(row.split()[0]) for row in rows], np.int64)
    except (IndexError, ValueError):
        return None
    return None


def _note_polygons(path: Path, data: bytes, fmt: str, triangles: int) -> None:
    """A :class:`MeshWarning` when the file's polygons (faces of more than three corners)
    came back from trimesh's loaders split into triangles (fans from a corner, the
    polygon's orientation kept): face indices then count those triangles."""
    listed = _file_faces(data, fmt)
    if listed is None or triangles <= listed[0]:
        return
    count, corners = listed

    def many(n: int, word: str) -> str:
        return f"{n:,} {word}{'' if n == 1 else 's'}"

    whole = (f"{many(count, 'face')} in the file, {many(triangles, 'triangle')}: face "
             "indices count the triangles")
    if corners is not None and len(corners) == count and (corners >= 3).all() \
            and int((corners - 2).sum()) == triangles:
        polygons = corners[corners > 3]
        larger = polygons[polygons > 4]
        parts = [many(int((polygons == 4).sum()), "quad")] if (polygons == 4).any() else []
        if len(larger):
            low, high = int(larger.min()), int(larger.max())
            parts.append(f"{many(len(larger), 'polygon')} of {low}"
                         + (f" to {high}" if high > low else "") + " corners")
        text = (f"split {' and '.join(parts)} into "
                f"{many(int((polygons - 2).sum()), 'triangle')} ({whole})")
    else:
        text = f"split its faces of more than three corners into triangles ({whole})"
    warnings.warn(f"{path}: {text}", MeshWarning, stacklevel=3)


def load_mesh(path) -> Mesh:
    """Load an OFF, OBJ, PLY or STL file through trimesh and validate it.

    The file is read as it is (``process=False``: no merging, no reordering), so face
    indices are the file's. Faces of more than three corners are split into triangles by
    trimesh's loaders (fans, the polygon's orientation kept), with a :class:`MeshWarning`
    that counts them: face indices then count the triangles. A directory, or a file with
    no vertices and no faces (e.g. a text file named ``.obj``), is a :class:`MeshError`.
    A gzip-compressed file (``camel.off.gz``, as the meshes ship) is decompressed in memory
    and read in the format named by the suffix before ``.gz``.
    """
    path = Path(path)
    if path.is_dir():
        raise MeshError(f"{path}: is a directory, not a mesh file")
    gz = path.suffix.lower() == ".gz"
    suffix = mesh_suffix(path)
    if suffix.lower() not in SUFFIXES:
        shown = (suffix + path.suffix if gz else suffix) or "(none)"
        raise MeshError(
            f"{path}: unsupported mesh format {shown!r}; "
            f"allowed: {', '.join(SUFFIXES)}, each also gzip-compressed (.gz)"
        )
    if not path.is_file():
        raise MeshError(f"{path}: no such mesh file")
    source = path
    if gz:
        try:
            source = io.BytesIO(gzip.decompress(path.read_bytes()))
        except (OSError, EOFError, zlib.error) as exc:
            raise MeshError(f"{path}: not a readable gzip file: {exc}") from exc
    try:
        loaded = trimesh.load(source, file_type=suffix.lower()[1:], process=False,
                              force="mesh")
    except Exception as exc:  # trimesh raises many kinds; name the file in one
        raise MeshError(f"{path}: trimesh could not read it: {exc}") from exc
    faces = np.asarray(getattr(loaded, "faces", np.zeros((0, 3))))
    if faces.size == 0:
        faces = faces.reshape(0, 3)
    vertices = np.asarray(getattr(loaded, "vertices", np.zeros((0, 3))))
    if len(vertices) == 0 and len(faces) == 0:
        found = ("vertex ('v x y z') or face ('f i j k') lines" if suffix.lower() == ".obj"
                 else "vertices or faces")
        raise MeshError(f"{path}: not a mesh: no {found} found in it")
    if len(faces):
        data = source.getvalue() if isinstance(source, io.BytesIO) else path.read_bytes()
        _note_polygons(path, data, suffix.lower()[1:], len(faces))
    return mesh_from_arrays(vertices, faces, name=str(path))
