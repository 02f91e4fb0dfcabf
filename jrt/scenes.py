"""The study's scene suite: meshes of different character, one name each, for comparing the
acceleration structures beyond one closed object in empty space.

    mesh = scene_mesh("stadium")                 # a jrt.Mesh (float32 vertices, int32 faces)
    mesh = scene_mesh("herd", size="small")      # the smaller variant (tests, --quick)

(Render scenes, with materials, lamps and a camera, are :mod:`jrt.scene`; these are the
geometry the benchmark suite traces, ``jrt bench --scene NAME``, each framed by the suite's
camera and ray sets like any mesh.)

The classic comparisons used several scenes because each structure has its known strength
and weakness (Havran 2000, Wald & Havran 2006, Aila & Laine 2009, Vinkler et al. 2016):

- ``camel``: the 69k-triangle camel, closed and evenly tessellated (small: the 19k camel);
- ``bunny``: the Stanford bunny scan, 69k triangles, with holes;
- ``teapot``: Newell's teapot, 6.3k triangles, open patches;
- ``fandisk``: a CAD part, 13k triangles, sharp creases and long thin triangles;
- ``stadium``: the camel at the centre of a stadium 1000 times its size (a ground, a ring
  of tilted stands, four big screens): the "teapot in a stadium", where a uniform grid's
  cells are either too large for the object or too many for the scene;
- ``herd``: 16 camels at random positions, turns and scales in a field, 1.1M triangles
  (small: 4 of the 19k camel), some of their boxes overlapping, empty space between;
- ``room``: the camel inside a closed box room five times its size, whose walls are two
  long triangles each: every ray from inside hits something;
- ``slivers``: a "hairball" of long thin needles (two corners close together, the third far
  away) crossing at random through a sphere: every structure's assumptions hurt.

Every generator is deterministic (fixed seeds) and NumPy only.
"""

from __future__ import annotations

import numpy as np

from jrt.data import mesh_path
from jrt.mesh import Mesh, load_mesh, mesh_from_arrays

#: The suite's scenes, in the study's order.
SCENES = ("camel", "bunny", "teapot", "fandisk", "stadium", "herd", "room", "slivers")
#: Sizes of a scene: ``full`` (the study) and ``small`` (tests and quick runs).
SIZES = ("full", "small")

#: What each scene is, in a few words (the report's cross-scene section quotes them).
DESCRIPTIONS = {
    "camel": "closed and evenly tessellated",
    "bunny": "a scan with holes",
    "teapot": "open patches, a small mesh",
    "fandisk": "a CAD part: sharp creases, long thin triangles",
    "stadium": "the camel in a stadium 1000 times its size",
    "herd": "camels scattered in a field, some overlapping",
    "room": "the camel in a closed room of long wall triangles",
    "slivers": "a hairball of long thin needles",
}
#: Camels in the herd (full, small).
HERD = {"full": 16, "small": 4}
#: Needles in the slivers hairball (full, small).
NEEDLES = {"full": 50_000, "small": 1_000}


def _camel(size: str) -> Mesh:
    return load_mesh(mesh_path("camel" if size == "full" else "camel-19k"))


def _joined(parts, name: str) -> Mesh:
    """One mesh of several ``(vertices, faces)``, the faces renumbered."""
    vertices, faces, count = [], [], 0
    for v, f in parts:
        vertices.append(np.asarray(v, np.float64))
        faces.append(np.asarray(f, np.int64) + count)
        count += len(v)
    return mesh_from_arrays(np.concatenate(vertices).astype(np.float32),
                            np.concatenate(faces).astype(np.int32), name=name)


def _quad(a, b, c, d):
    """Two triangles (a, b, c), (a, c, d) of the quad a-b-c-d."""
    return np.array([a, b, c, d], np.float64), np.array([[0, 1, 2], [0, 2, 3]])


def _box(lo, hi):
    """The 12 triangles of an axis-aligned box, outward winding."""
    x0, y0, z0 = lo
    x1, y1, z1 = hi
    v = np.array([[x0, y0, z0], [x1, y0, z0], [x1, y1, z0], [x0, y1, z0],
                  [x0, y0, z1], [x1, y0, z1], [x1, y1, z1], [x0, y1, z1]], np.float64)
    f = np.array([[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4],
                  [2, 3, 7], [2, 7, 6], [1, 2, 6], [1, 6, 5], [0, 4, 7], [0, 7, 3]])
    return v, f


def _centred(mesh: Mesh) -> tuple[np.ndarray, float, float]:
    """The mesh's vertices (float64) moved so that its box's centre is at x = z = 0 and its
    lowest point at y = 0 (the meshes are y-up), and its box diagonal and height."""
    v = np.asarray(mesh.vertices, np.float64)
    lo, hi = v.min(axis=0), v.max(axis=0)
    v = v - np.array([(lo[0] + hi[0]) / 2, lo[1], (lo[2] + hi[2]) / 2])
    return v, float(np.linalg.norm(hi - lo)), float(hi[1] - lo[1])


def stadium(size: str = "full") -> Mesh:
    """The camel on the ground at the centre of a stadium 1000 times its size."""
    camel = _camel(size)
    v, diagonal, _ = _centred(camel)
    radius = 500.0 * diagonal  # the stadium's diameter: 1000 camels
    parts = [(v, camel.faces), _quad((-radius, 0, -radius), (-radius, 0, radius),
                                     (radius, 0, radius), (radius, 0, -radius))]
    segments, rise = 64, 0.08 * radius
    for k in range(segments):  # a ring of stands, tilted toward the centre
        a0, a1 = 2 * np.pi * k / segments, 2 * np.pi * (k + 1) / segments
        inner, outer = 0.8 * radius, radius
        p = [(r * np.cos(a), h, r * np.sin(a))
             for r, h, a in ((inner, 0.0, a0), (outer, rise, a0), (outer, rise, a1),
                             (inner, 0.0, a1))]
        parts.append(_quad(*p))
    for k in range(4):  # big screens above the stands
        a = np.pi / 4 + k * np.pi / 2
        c, s = np.cos(a), np.sin(a)
        w, r = 0.15 * radius, 0.95 * radius
        corners = [(r * c - w * s, rise, r * s + w * c), (r * c - w * s, 2 * rise, r * s + w * c),
                   (r * c + w * s, 2 * rise, r * s - w * c), (r * c + w * s, rise, r * s - w * c)]
        parts.append(_quad(*corners))
    return _joined(parts, f"stadium ({size})")


def herd(size: str = "full") -> Mesh:
    """Camels at random positions, turns about the vertical and scales (0.6 to 1.4) in a
    square field of side sqrt(count) camel diagonals; the second stands a third of a
    diagonal beside the first, so that at least two boxes overlap at every size."""
    camel = _camel(size)
    v, diagonal, _ = _centred(camel)
    count = HERD[size]
    rng = np.random.default_rng(16)
    side = diagonal * np.sqrt(count)
    parts, places = [], []
    for k in range(count):
        a = rng.uniform(0, 2 * np.pi)
        turn = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
        place = np.array([rng.uniform(-side, side) / 2, 0.0, rng.uniform(-side, side) / 2])
        if k == 1:
            place = places[0] + np.array([diagonal / 3, 0.0, 0.0])
        places.append(place)
        parts.append((v @ turn.T * rng.uniform(0.6, 1.4) + place, camel.faces))
    return _joined(parts, f"herd ({size})")


def room(size: str = "full") -> Mesh:
    """The camel inside a closed box room, five camels long, three wide and two high: each
    wall two long triangles, every ray from inside the room hits."""
    camel = _camel(size)
    v, diagonal, height = _centred(camel)
    lo, hi = np.array([-2.5, -0.01, -1.5]) * diagonal, np.array([2.5, 2.0, 1.5]) * diagonal
    lo[1] = -0.01 * height  # the floor just under the feet
    box_v, box_f = _box(lo, hi)
    return _joined([(v, camel.faces), (box_v, box_f[:, ::-1])], f"room ({size})")  # inward


def slivers(size: str = "full") -> Mesh:
    """Needles through a unit sphere: each a triangle whose two near corners are 1e-3 of
    its length apart, the third at the far end, in random directions and places."""
    count = NEEDLES[size]
    rng = np.random.default_rng(17)
    start = rng.normal(size=(count, 3))
    start /= np.linalg.norm(start, axis=1, keepdims=True)
    end = rng.normal(size=(count, 3))
    end /= np.linalg.norm(end, axis=1, keepdims=True)
    side = np.cross(end - start, rng.normal(size=(count, 3)))
    side *= 1e-3 * np.linalg.norm(end - start, axis=1, keepdims=True) / np.linalg.norm(
        side, axis=1, keepdims=True)
    vertices = np.stack([start, start + side, end], axis=1).reshape(-1, 3)
    return mesh_from_arrays(vertices.astype(np.float32),
                            np.arange(3 * count, dtype=np.int32).reshape(-1, 3),
                            name=f"slivers ({size})")


#: The generated scenes (each has a full and a small size).
GENERATED = {"stadium": stadium, "herd": herd, "room": room, "slivers": slivers}


def scene_mesh(name: str, *, size: str = "full") -> Mesh:
    """The mesh of scene ``name`` (:data:`SCENES`) at ``size`` (:data:`SIZES`): a shipped
    mesh (the camel's small size is the 19k camel; the others have one size) or a
    generated one.

    Raises:
        ValueError: an unknown scene or size, naming the allowed ones.
    """
    if name not in SCENES:
        raise ValueError(f"unknown scene {name!r}; the scenes are {', '.join(SCENES)}")
    if size not in SIZES:
        raise ValueError(f"unknown size {size!r} of scene {name!r}; sizes are "
                         f"{', '.join(SIZES)}")
    if name in GENERATED:
        return GENERATED[name](size)
    if name == "camel":
        return _camel(size)
    return load_mesh(mesh_path(name))


def scene_label(name: str, size: str = "full") -> str:
    """The short name of scene ``name`` at ``size``, as commands and results name it:
    ``NAME``, ``NAME-small`` for a generated scene's small size, ``camel-19k`` for the
    camel's (the other shipped meshes have one size)."""
    if size == "small" and name in GENERATED:
        return f"{name}-small"
    return "camel-19k" if (name, size) == ("camel", "small") else name


def parse_label(label: str) -> tuple[str, str] | None:
    """``(scene, size)`` of a short name from :func:`scene_label`; None for any other."""
    for name in SCENES:
        for size in SIZES:
            if scene_label(name, size) == label:
                return name, size
    return None


#: The short names of the generated scenes, full and small (``stadium``,
#: ``stadium-small``, ...): mesh names besides the shipped meshes'.
GENERATED_LABELS = tuple(scene_label(n, size) for n in GENERATED for size in SIZES)


__all__ = ["DESCRIPTIONS", "GENERATED", "GENERATED_LABELS", "SCENES", "SIZES", "herd",
           "parse_label", "room", "scene_label", "scene_mesh", "slivers", "stadium"]
