"""Triangle meshes: loading through trimesh, validation at the boundary.

A :class:`Mesh` holds float32 vertices [V, 3] and int32 faces [F, 3] that passed
validation: not empty, finite coordinates, triangles only, indices in range. Degenerate
(zero-area) triangles are kept in the face list, so indices stay those of the file, but
they are counted, reported (a :class:`MeshWarning`), and left out of every acceleration
structure: never hit. Arrays must hold triangles already; a file's polygons are split into
triangles when it is loaded, with a :class:`MeshWarning` that says how many. A PLY file of
triangle strips (a ``tristrips`` element, as some range scans ship) is read here, since
trimesh keeps no faces of it: :func:`strip_triangles`.
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
#: PLY property types (the PLY names and their sized aliases) as NumPy type codes.
PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2",
             "int16": "i2", "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4",
             "uint": "u4", "uint32": "u4", "float": "f4", "float32": "f4", "double": "f8",
             "float64": "f8"}
PLY_FORMATS = ("ascii", "binary_little_endian", "binary_big_endian")


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


def strip_triangles(strips) -> tuple[np.ndarray, int]:
    """The triangles of triangle strips, as PLY's ``tristrips`` element lists them.

    Each strip is a sequence of vertex indices in which -1 restarts the strip (and each
    strip of the list starts afresh). Triangle j of a (re)started strip is
    ``(v[j], v[j+1], v[j+2])`` for even j and ``(v[j+1], v[j], v[j+2])`` for odd j, so that
    all keep the strip's orientation (OpenGL's ``GL_TRIANGLE_STRIP`` rule, as MeshLab's
    reader). Triangles with a repeated vertex index, which strips use to turn or to join
    (zero area by construction), are left out.

    Returns:
        (faces, skipped): int64 [F, 3] in strip order, and how many were left out.
    """
    parts = [np.append(np.asarray(strip, np.int64).ravel(), -1) for strip in strips]
    index = np.concatenate(parts) if parts else np.zeros(0, np.int64)
    if index.size < 3:
        return np.zeros((0, 3), np.int64), 0
    restart = index == -1
    position = np.arange(index.size)
    # Where the strip that holds each position started (just after the last -1).
    start = np.maximum.accumulate(np.where(restart, position + 1, 0))
    a, b, c = index[:-2], index[1:-1], index[2:]
    whole = ~(restart[:-2] | restart[1:-1] | restart[2:])
    odd = (position[:-2] - start[:-2]) % 2 == 1
    faces = np.stack([np.where(odd, b, a), np.where(odd, a, b), c], axis=1)[whole]
    repeated = ((faces[:, 0] == faces[:, 1]) | (faces[:, 1] == faces[:, 2])
                | (faces[:, 0] == faces[:, 2]))
    return faces[~repeated], int(repeated.sum())


def _ply_header(data: bytes):
    """(format, elements, offset of the body) of a PLY file, each element (name, count,
    properties), a property (name, type) or (name, (count type, item type)) for a list;
    ``None`` where the header cannot be read so (trimesh then reports the file)."""
    end = re.search(rb"^end_header[ \t]*\r?\n", data, re.M)
    if not data.startswith(b"ply") or end is None:
        return None
    fmt, elements = None, []
    for line in data[:end.start()].decode("ascii", "replace").splitlines()[1:]:
        words = line.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "format" and len(words) == 3:
            fmt = words[1]
        elif words[0] == "element" and len(words) == 3 and words[2].isdigit():
            elements.append((words[1], int(words[2]), []))
        elif words[0] == "property" and elements and len(words) == 5 and words[1] == "list":
            elements[-1][2].append((words[4], (words[2], words[3])))
        elif words[0] == "property" and elements and len(words) == 3:
            elements[-1][2].append((words[2], words[1]))
        else:
            return None
    return (fmt, elements, end.end()) if fmt in PLY_FORMATS else None


def _ply_columns(data: bytes, header, wanted: set[str]) -> dict[str, dict]:
    """The properties of the PLY elements ``wanted`` (read in file order, up to the last of
    them): a scalar property as an array over the element's rows, a list property as a
    list of arrays, one per row (ASCII values as byte strings). A ValueError (KeyError for
    an unknown property type) where the file does not match its header."""
    fmt, elements, offset = header
    columns: dict[str, dict] = {}
    tokens = data[offset:].split() if fmt == "ascii" else None
    order = "<" if fmt == "binary_little_endian" else ">"

    def take(item: np.dtype | str, n: int, element: str) -> np.ndarray:  # n binary values
        nonlocal offset
        item = np.dtype(order + PLY_TYPES[item]) if isinstance(item, str) else item
        if n < 0 or offset + n * item.itemsize > len(data):
            raise ValueError(f"the file ends inside element {element!r}")
        offset += n * item.itemsize
        return np.frombuffer(data, item, n, offset - n * item.itemsize)

    for name, count, properties in elements:
        if wanted <= columns.keys():
            break
        scalar = all(isinstance(kind, str) for _, kind in properties)
        if tokens is not None and scalar:
            width = len(properties)
            block = tokens[:count * width]
            if len(block) < count * width:
                raise ValueError(f"the file ends inside element {name!r}")
            table = np.array(block, dtype=bytes).reshape(count, width)
            columns[name] = {p: table[:, j] for j, (p, _) in enumerate(properties)}
            tokens = tokens[count * width:]
        elif scalar:
            rows = take(np.dtype([(p, order + PLY_TYPES[kind]) for p, kind in properties]),
                        count, name)
            columns[name] = {p: rows[p] for p, _ in properties}
        else:  # a list property: row by row (strips: one or a few rows)
            values = {p: [] for p, _ in properties}
            at = 0
            for _ in range(count):
                for p, kind in properties:
                    if tokens is not None:
                        if at >= len(tokens):
                            raise ValueError(f"the file ends inside element {name!r}")
                        n = int(tokens[at]) if isinstance(kind, tuple) else 1
                        first = at + 1 if isinstance(kind, tuple) else at
                        if n < 0 or first + n > len(tokens):
                            raise ValueError(f"the file ends inside element {name!r}")
                        item = np.array(tokens[first:first + n], dtype=bytes)
                        at = first + n
                    elif isinstance(kind, tuple):
                        item = take(kind[1], int(take(kind[0], 1, name)[0]), name)
                    else:
                        item = take(kind, 1, name)
                    values[p].append(item if isinstance(kind, tuple) else item[0])
            if tokens is not None:
                tokens = tokens[at:]
            columns[name] = values
    return columns


def _ply_without_faces(elements) -> str:
    """The phrase "PLY with N vertices and no 'face' element" (or "an empty 'face'
    element"), for the errors about such a file."""
    counts = {name: count for name, count, _ in elements}
    face = "an empty 'face' element" if "face" in counts else "no 'face' element"
    return f"PLY with {counts.get('vertex', 0):,} vertices and {face}"


def _ply_strip_mesh(path: Path, data: bytes, header) -> Mesh:
    """The mesh of a PLY file whose triangles are triangle strips (``tristrips``)."""
    elements = header[1]
    what = f"{path}: {_ply_without_faces(elements)}; its triangle strips ('tristrips')"
    convert = ("; convert the strips to faces (e.g. open it in MeshLab and export it as "
               "PLY)")
    try:
        columns = _ply_columns(data, header, {"vertex", "tristrips"})
    except (ValueError, KeyError) as exc:
        problem = f"an unknown property type {exc}" if isinstance(exc, KeyError) else str(exc)
        raise MeshError(f"{what} could not be read: {problem}{convert}") from exc
    vertex, strips = columns.get("vertex", {}), columns["tristrips"]
    missing = [axis for axis in "xyz" if axis not in vertex]
    lists = [p for p, kind in next(e[2] for e in elements if e[0] == "tristrips")
             if isinstance(kind, tuple)]
    if missing or not lists:
        problem = (f"its 'vertex' element has no {', '.join(map(repr, missing))} property"
                   if missing else "its 'tristrips' element has no list property")
        raise MeshError(f"{what} could not be read: {problem}{convert}")
    indices = next((p for p in ("vertex_indices", "vertex_index") if p in lists), lists[0])
    try:  # (ASCII values come as text)
        vertices = np.stack([np.asarray(vertex[axis]).astype(np.float64) for axis in "xyz"],
                            axis=1)
        faces, skipped = strip_triangles(
            [np.asarray(strip).astype(np.int64) for strip in strips[indices]])
    except ValueError as exc:
        raise MeshError(f"{what} could not be read: {exc}{convert}") from exc

    def many(n: int, word: str) -> str:
        return f"{n:,} {word}{'' if n == 1 else 's'}"

    note = (f"{path}: read {many(len(strips[indices]), 'triangle strip')} ('tristrips') as "
            f"{many(len(faces), 'triangle')}; face indices count them in strip order")
    if skipped:
        note += (f" ({many(skipped, 'triangle')} with a repeated vertex, where the strips "
                 "turn or join, left out)")
    warnings.warn(note, MeshWarning, stacklevel=3)
    return mesh_from_arrays(vertices, faces, name=str(path))


def load_mesh(path) -> Mesh:
    """Load an OFF, OBJ, PLY or STL file through trimesh and validate it.

    The file is read as it is (``process=False``: no merging, no reordering), so face
    indices are the file's. Faces of more than three corners are split into triangles by
    trimesh's loaders (fans, the polygon's orientation kept), with a :class:`MeshWarning`
    that counts them: face indices then count the triangles. A PLY file without a ``face``
    element but with triangle strips (``tristrips``) is read as the strips' triangles
    (:func:`strip_triangles`), with a :class:`MeshWarning` that counts them. A directory, a
    file with no vertices and no faces (e.g. a text file named ``.obj``), or a PLY file
    with no faces and no strips is a :class:`MeshError`.
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
    source, data = path, None
    if gz:
        try:
            data = gzip.decompress(path.read_bytes())
        except (OSError, EOFError, zlib.error) as exc:
            raise MeshError(f"{path}: not a readable gzip file: {exc}") from exc
        source = io.BytesIO(data)
    header = None
    if suffix.lower() == ".ply":
        data = path.read_bytes() if data is None else data
        header = _ply_header(data)
        counts = {name: count for name, count, _ in header[1]} if header else {}
        if not counts.get("face") and counts.get("tristrips"):
            return _ply_strip_mesh(path, data, header)
    try:
        loaded = trimesh.load(source, file_type=suffix.lower()[1:], process=False,
                              force="mesh")
    except Exception as exc:  # trimesh raises many kinds; name the file in one
        raise MeshError(f"{path}: trimesh could not read it: {exc}") from exc
    faces = np.asarray(getattr(loaded, "faces", np.zeros((0, 3))))
    if faces.size == 0:
        faces = faces.reshape(0, 3)
    vertices = np.asarray(getattr(loaded, "vertices", np.zeros((0, 3))))
    if header is not None and len(faces) == 0:
        listed = ", ".join(f"{name} ({count:,})" for name, count, _ in header[1])
        raise MeshError(
            f"{path}: {_ply_without_faces(header[1])} (its elements: {listed or 'none'}): "
            "no triangles to trace; jrt reads triangles from a 'face' element, or triangle "
            "strips from a 'tristrips' element")
    if len(vertices) == 0 and len(faces) == 0:
        found = ("vertex ('v x y z') or face ('f i j k') lines" if suffix.lower() == ".obj"
                 else "vertices or faces")
        raise MeshError(f"{path}: not a mesh: no {found} found in it")
    if len(faces):
        data = path.read_bytes() if data is None else data
        _note_polygons(path, data, suffix.lower()[1:], len(faces))
    return mesh_from_arrays(vertices, faces, name=str(path))
