"""Scenes: TOML files (or built-in names) into a validated, frozen description, and from it
the static features that decide what the renderer compiles.

NumPy side only: nothing here is traced by JAX. The way in is :func:`load_scene`; the
way to arrays is :func:`assemble`; ``scene.features()`` is a hashable record meant as a
static argument to ``jax.jit``.

The schema (every table and field optional unless marked *required*; y is up)::

    name = "my-scene"                     # default: the built-in name or the file's stem

    [camera]
    eye = "auto"                          # or [x, y, z]; "auto": jrt.camera.frame_mesh
    target = "auto"                       # or [x, y, z]; "auto" exactly when eye is
    up = [0.0, 1.0, 0.0]                  # must be +y with automatic framing
    vfov = 30.0                           # degrees, (0, 180)
    azimuth = 50.0                        # automatic framing only: degrees around +y
    elevation = 20.0                      # automatic framing only: degrees above horizon
    margin = 1.05                         # automatic framing only: (0, 10]; the bounding
                                          #   sphere, its radius times margin, fits the view
    width = 640                           # pixels, 1..16384
    height = 480

    [settings]
    max_depth = 5                         # 1..16: levels of the Whitted tree
    samples = 16                          # 1..256 wavelength samples (with dispersion)
    threshold = 1e-3                      # [0, 1): prune rays whose weight falls below
    kernel = "watertight"                 # one of jrt.KERNELS
    accel = "bvh"                         # one of accel.NAMES
    background = "black"                  # "black" or "sky"
    fresnel = "exact"                     # "exact" (full equations) or "schlick" (ablation)
    ambient = 0.1                         # [0, 1]: share of a diffuse albedo always seen

    [materials.NAME]                      # one table per material, any name
    kind = "diffuse"                      # required: "diffuse", "mirror" or "dielectric"
    albedo = [0.8, 0.8, 0.8]              # diffuse: RGB in [0, 1]
    # reflectance = [0.9, 0.9, 0.9]       # mirror: RGB in [0, 1]
    # index = 1.5                         # dielectric, exactly one of: a constant in (1, 5],
    # glass = "BK7"                       #   a name in jrt.optics.GLASSES (Cauchy A, B),
    # cauchy = [1.5046, 0.0042]           #   or n(λ) = A + B/λ², A in (1, 5], B in [0, 1] µm²

    [[lamps]]                             # zero or more point lamps
    position = "auto"                     # or [x, y, z]; "auto": jrt.render.default_lamp
    intensity = 1.0                       # > 0, a scale on the lamp's contribution
    spectrum = "D65"                      # an illuminant: D65, D50, A, E, or another
                                          #   name of colour.SDS_ILLUMINANTS

    [[objects]]                           # required: at least one
    mesh = "camel"                        # required: a shipped mesh's name or a mesh file
    material = "NAME"                     # required: a name under [materials]
    scale = 1.0                           # > 0
    rotate = [0.0, 0.0, 0.0]              # degrees about x, then y, then z (fixed axes)
    translate = [0.0, 0.0, 0.0]
    crease_angle = 30.0                   # degrees, [0, 180]: sharper edges shade sharp
                                          #   (jrt.normals; 0 flat, 180 all smooth)

    [floor]                               # absent: no floor
    material = "NAME"                     # required
    enabled = true
    extent = 3.0                          # half-width, times the objects' largest half-size
    gap = 1e-3                            # below the lowest point, times the diagonal

A mesh file path is relative to the scene file's folder. Every error is a
:class:`SceneError` naming the file (or ``built-in scene NAME``), the field path (e.g.
``materials.glass.index``), the value and what is allowed.
"""

from __future__ import annotations

import dataclasses
import difflib
import json
import math
import tomllib
from collections.abc import Mapping
from pathlib import Path
from typing import Any, NoReturn

import numpy as np

import accel
from jrt.camera import FRAME_MARGIN, Camera, frame_mesh
from jrt.data import MESHES, camel_path
from jrt.kernels import DEFAULT_KERNEL, KERNELS
from jrt.mesh import SUFFIXES, Mesh, MeshError, load_mesh, mesh_from_arrays, mesh_suffix
from jrt.normals import DEFAULT_CREASE_ANGLE, corner_normals

Vec3 = tuple[float, float, float]

KINDS = ("diffuse", "mirror", "dielectric")
#: The Fresnel coefficients of a dielectric: jrt.optics.fresnel or jrt.optics.schlick.
FRESNEL_MODELS = ("exact", "schlick")
BACKGROUNDS = ("black", "sky")
#: Common illuminant names for a lamp's ``spectrum``; any other name of colour-science's
#: ``colour.SDS_ILLUMINANTS`` is accepted too (checked lazily, importing colour).
ILLUMINANTS = ("D65", "D50", "A", "E")
INDEX_RANGE = (1.0, 5.0)  # a constant index or Cauchy's A: (1, 5]
CAUCHY_B_RANGE = (0.0, 1.0)  # µm², [0, 1]
MAX_DEPTH = 16
MAX_SAMPLES = 256
MAX_PIXELS = 16384


class SceneError(ValueError):
    """A scene that cannot be rendered: names the file, the field, the value and the rule."""


# --------------------------------------------------------------------------- data model


@dataclasses.dataclass(frozen=True)
class Material:
    """A surface's optics.

    Attributes:
        name: the key under ``[materials]``.
        kind: ``"diffuse"`` (Lambert), ``"mirror"`` or ``"dielectric"`` (Fresnel glass).
        albedo: diffuse only: RGB in [0, 1].
        reflectance: mirror only: RGB in [0, 1].
        index: dielectric with a constant refractive index.
        glass: dielectric from the catalogue ``jrt.optics.GLASSES`` (its canonical name).
        cauchy: dielectric with n(λ) = A + B / λ², λ in µm, B in µm² (Cauchy's law, seed
            §3); filled from the catalogue when ``glass`` is given.
    """

    name: str
    kind: str
    albedo: Vec3 | None = None
    reflectance: Vec3 | None = None
    index: float | None = None
    glass: str | None = None
    cauchy: tuple[float, float] | None = None

    @property
    def dispersion(self) -> bool:
        """True when the refractive index depends on the wavelength (Cauchy B != 0)."""
        return self.kind == "dielectric" and self.cauchy is not None and self.cauchy[1] != 0.0

    def index_at(self, wavelength_nm):
        """Refractive index at ``wavelength_nm`` (nm, scalar or array): A + B / λ², λ in µm."""
        if self.kind != "dielectric":
            raise ValueError(f"material {self.name!r} is {self.kind}, not a dielectric")
        lam = np.asarray(wavelength_nm, np.float64)
        if self.cauchy is None:
            return np.full_like(lam, self.index) if lam.ndim else float(self.index)
        a, b = self.cauchy
        n = a + b / (lam / 1000.0) ** 2
        return n if lam.ndim else float(n)


@dataclasses.dataclass(frozen=True)
class Lamp:
    """A point lamp. ``position`` None means "auto" until :func:`assemble` resolves it."""

    position: Vec3 | None = None
    intensity: float = 1.0
    spectrum: str = "D65"


@dataclasses.dataclass(frozen=True)
class Object:
    """A mesh placed in the scene: scaled, then rotated, then translated.

    Attributes:
        mesh: a shipped mesh's name (``jrt.data.MESHES``, found by :func:`jrt.mesh_path`)
            or an absolute path to a mesh file (``.gz`` too).
        material: a material name.
        scale: uniform scale, > 0.
        rotate: degrees about the fixed x, y and z axes, applied in that order.
        translate: scene units.
        crease_angle: degrees in [0, 180]; edges whose faces meet at a larger angle shade
            sharp, the others smooth (:func:`jrt.normals.corner_normals`).
    """

    mesh: str
    material: str
    scale: float = 1.0
    rotate: Vec3 = (0.0, 0.0, 0.0)
    translate: Vec3 = (0.0, 0.0, 0.0)
    crease_angle: float = DEFAULT_CREASE_ANGLE

    def rotation(self) -> np.ndarray:
        """float64 [3, 3]: R = Rz @ Ry @ Rx (x first, fixed axes, right-handed)."""
        cx, cy, cz = np.cos(np.radians(self.rotate))
        sx, sy, sz = np.sin(np.radians(self.rotate))
        rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
        ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
        rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
        return rz @ ry @ rx

    def transform(self, points) -> np.ndarray:
        """float64 [N, 3]: ``R @ (scale * p) + translate`` for each point p [N, 3]."""
        p = np.asarray(points, np.float64)
        return (self.scale * p) @ self.rotation().T + np.asarray(self.translate)


@dataclasses.dataclass(frozen=True)
class Floor:
    """Two triangles (normal +y) under the objects' bounds.

    The square is centred under the bounds' centre, with half-width ``extent`` times the
    objects' larger horizontal half-size, ``gap`` times the objects' diagonal below their
    lowest point.
    """

    material: str
    extent: float = 3.0
    gap: float = 1e-3


@dataclasses.dataclass(frozen=True)
class CameraSpec:
    """The camera as written: explicit (``eye``, ``target``) or automatic (both None)."""

    eye: Vec3 | None = None
    target: Vec3 | None = None
    up: Vec3 = (0.0, 1.0, 0.0)
    vfov: float = 30.0
    azimuth: float = 50.0
    elevation: float = 20.0
    margin: float = FRAME_MARGIN
    width: int = 640
    height: int = 480

    @property
    def auto(self) -> bool:
        return self.eye is None

    def resolve(self, vertices) -> Camera:
        """The :class:`jrt.Camera`; automatic framing fits ``vertices`` [V, 3]."""
        if self.auto:
            return frame_mesh(vertices, width=self.width, height=self.height, vfov=self.vfov,
                              azimuth=self.azimuth, elevation=self.elevation,
                              margin=self.margin, up=self.up)
        return Camera(eye=self.eye, target=self.target, up=self.up, vfov=self.vfov,
                      width=self.width, height=self.height)


@dataclasses.dataclass(frozen=True)
class Settings:
    """Render settings (see the module doc for ranges)."""

    max_depth: int = 5
    samples: int = 16
    threshold: float = 1e-3
    kernel: str = DEFAULT_KERNEL
    accel: str = "bvh"
    background: str = "black"
    ambient: float = 0.1
    fresnel: str = "exact"


@dataclasses.dataclass(frozen=True)
class Features:
    """What the scene needs compiled: hashable, for ``jax.jit(static_argnames=...)``.

    ``max_depth`` is 1 (camera rays only) when no mirror or dielectric is used, whatever
    the settings say; ``shadows`` is true when a lamp lights a diffuse surface.
    """

    diffuse: bool
    mirror: bool
    dielectric: bool
    dispersion: bool
    lamps: int
    shadows: bool
    max_depth: int
    counters: bool = False


@dataclasses.dataclass(frozen=True)
class Scene:
    """A validated scene. ``source`` (the file, or ``built-in scene NAME``) is not compared."""

    name: str
    materials: tuple[Material, ...]
    lamps: tuple[Lamp, ...]
    objects: tuple[Object, ...]
    floor: Floor | None
    camera: CameraSpec
    settings: Settings
    source: str = dataclasses.field(default="<scene>", compare=False)

    def material(self, name: str) -> Material:
        return self.materials[self.material_index(name)]

    def material_index(self, name: str) -> int:
        """Index of ``name`` in :attr:`materials` (the order of definition)."""
        for i, m in enumerate(self.materials):
            if m.name == name:
                return i
        raise KeyError(name)

    def used_materials(self) -> tuple[Material, ...]:
        """The materials some object or the floor refers to, in index order."""
        names = {o.material for o in self.objects}
        if self.floor is not None:
            names.add(self.floor.material)
        return tuple(m for m in self.materials if m.name in names)

    def features(self, counters: bool = False) -> Features:
        used = self.used_materials()
        kinds = {m.kind for m in used}
        specular = bool(kinds & {"mirror", "dielectric"})
        return Features(
            diffuse="diffuse" in kinds,
            mirror="mirror" in kinds,
            dielectric="dielectric" in kinds,
            dispersion=any(m.dispersion for m in used),
            lamps=len(self.lamps),
            shadows=bool(self.lamps) and "diffuse" in kinds,
            max_depth=self.settings.max_depth if specular else 1,
            counters=bool(counters),
        )

    def to_toml(self) -> str:
        """The scene as TOML that :func:`parse_scene` reads back to an equal scene."""
        return _dump(self)


# --------------------------------------------------------------------------- built-ins

_CAMERA_AND_LAMP = """\
[camera]
eye = "auto"              # framed by jrt.camera.frame_mesh: a 3/4 view from above
target = "auto"
vfov = 30.0
azimuth = 50.0
elevation = 20.0
width = 640
height = 480

[[lamps]]
position = "auto"         # above the camera's left shoulder (jrt.render.default_lamp)
intensity = 1.0
spectrum = "D65"

[floor]
material = "floor"
extent = 3.0              # half-width: 3 x the camel's larger horizontal half-size
gap = 1e-3                # below the lowest hoof, times the camel's diagonal

[materials.floor]
kind = "diffuse"
albedo = [0.55, 0.55, 0.55]
"""

#: The built-in scenes, as TOML: copy one to start a scene of your own.
BUILTIN_SCENES: dict[str, str] = {
    "camel": f"""\
# The diffuse camel: Lambert shading, one point lamp with shadows, a grey floor.
name = "camel"

[settings]
max_depth = 1             # nothing reflects or refracts: camera rays and shadow rays
kernel = "watertight"
accel = "bvh"
background = "sky"
ambient = 0.15

[[objects]]
mesh = "camel"
material = "sand"

[materials.sand]
kind = "diffuse"
albedo = [0.86, 0.68, 0.46]

{_CAMERA_AND_LAMP}""",
    "glass-camel": f"""\
# A BK7 glass camel: Fresnel reflection and refraction, Cauchy dispersion
# n(lambda) = A + B / lambda^2 sampled at 16 wavelengths.
name = "glass-camel"

[settings]
max_depth = 8
samples = 16
threshold = 1e-3
kernel = "watertight"
accel = "bvh"
background = "sky"
ambient = 0.15

[[objects]]
mesh = "camel"
material = "glass"

[materials.glass]
kind = "dielectric"
glass = "BK7"             # Cauchy A, B from jrt.optics.GLASSES; or index = 1.5 (no dispersion)

{_CAMERA_AND_LAMP}""",
    "mirror-camel": f"""\
# A mirror camel over a diffuse floor.
name = "mirror-camel"

[settings]
max_depth = 5
kernel = "watertight"
accel = "bvh"
background = "sky"
ambient = 0.15

[[objects]]
mesh = "camel"
material = "mirror"

[materials.mirror]
kind = "mirror"
reflectance = [0.9, 0.9, 0.9]

{_CAMERA_AND_LAMP}""",
}


def builtin_toml(name: str) -> str:
    """The TOML text of the built-in scene ``name``."""
    if name not in BUILTIN_SCENES:
        raise SceneError(
            f"unknown built-in scene {name!r}; built-in scenes: {', '.join(BUILTIN_SCENES)}"
        )
    return BUILTIN_SCENES[name]


def load_scene(spec: str | Path) -> Scene:
    """A built-in scene's name (:data:`BUILTIN_SCENES`) or the path of a ``.toml`` file."""
    if isinstance(spec, str) and spec in BUILTIN_SCENES:
        return parse_scene(BUILTIN_SCENES[spec], source=f"built-in scene {spec}",
                           default_name=spec)
    path = Path(spec)
    builtins = f"built-in scenes: {', '.join(BUILTIN_SCENES)}"
    if not path.is_file():
        raise SceneError(
            f"{spec}: no built-in scene of that name and no such file; {builtins}, "
            "or the path of a .toml scene file"
        )
    if path.suffix.lower() != ".toml":
        raise SceneError(f"{path}: a scene file must end in .toml; {builtins}")
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise SceneError(f"{path}: cannot read the scene file: {exc}") from exc
    return parse_scene(text, source=str(path), base_dir=path.parent, default_name=path.stem)


def parse_scene(text: str, source: str = "<string>", base_dir: str | Path | None = None,
                default_name: str = "scene") -> Scene:
    """Validate TOML ``text``; ``source`` names it in errors, ``base_dir`` (default: the
    working directory) anchors relative mesh paths."""
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise SceneError(f"{source}: not valid TOML: {exc}") from exc
    return _Reader(source, Path(base_dir) if base_dir is not None else Path.cwd()).scene(
        data, default_name)


# --------------------------------------------------------------------------- validation

_REQUIRED = object()
_MISSING = object()


def _show(value: Any) -> str:
    text = ("true" if value else "false") if isinstance(value, bool) else repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _interval(lo: float, hi: float, lo_open: bool, hi_open: bool) -> str:
    if hi == math.inf:
        return f"a number {'>' if lo_open else '>='} {lo:g}"
    return f"a number in {'(' if lo_open else '['}{lo:g}, {hi:g}{')' if hi_open else ']'}"


def glass_catalogue() -> Mapping[str, tuple[float, float]]:
    """``jrt.optics.GLASSES``: {name: (A, B in µm²)}; ImportError when jrt.optics is absent."""
    from jrt.optics import GLASSES  # lazy: optics is a layer above the scene description

    return GLASSES


def illuminant_names() -> tuple[str, ...]:
    """Every illuminant name colour-science knows (imports colour: slow, so lazily)."""
    import colour

    return tuple(colour.SDS_ILLUMINANTS)


def _norm(name: str) -> str:
    return "".join(ch for ch in name.lower() if ch.isalnum())


class _Reader:
    """Reads the parsed TOML tables, one field at a time, naming each field's path."""

    def __init__(self, source: str, base_dir: Path):
        self.source = source
        self.base_dir = base_dir

    def fail(self, path: str, problem: str, allowed: str, value: Any = _MISSING) -> NoReturn:
        shown = "" if value is _MISSING else f" = {_show(value)}"
        raise SceneError(f"{self.source}: {path}{shown}: {problem}; allowed: {allowed}")

    def keys(self, table: Mapping, prefix: str, allowed: tuple[str, ...]) -> None:
        for key in table:
            if key not in allowed:
                close = difflib.get_close_matches(key, allowed, n=1)
                hint = f" (did you mean {close[0]!r}?)" if close else ""
                self.fail(_join(prefix, key), f"unknown field{hint}", ", ".join(allowed))

    def table(self, data: Mapping, key: str, prefix: str, required: bool = False) -> dict:
        path = _join(prefix, key)
        if key not in data:
            if required:
                self.fail(path, "missing table", f"a table [{path}]")
            return {}
        value = data[key]
        if not isinstance(value, dict):
            self.fail(path, "not a table", f"a table [{path}]", value)
        return value

    def get(self, table: Mapping, key: str, prefix: str, default: Any, allowed: str) -> Any:
        if key in table:
            return table[key]
        if default is _REQUIRED:
            self.fail(_join(prefix, key), "missing (required)", allowed)
        return default

    def number(self, table: Mapping, key: str, prefix: str, default: Any,
               lo: float = -math.inf, hi: float = math.inf, lo_open: bool = False,
               hi_open: bool = False, integer: bool = False) -> Any:
        allowed = _interval(lo, hi, lo_open, hi_open)
        if integer:
            allowed = allowed.replace("a number", "an integer")
        elif lo == -math.inf and hi == math.inf:
            allowed = "a finite number"
        value = self.get(table, key, prefix, default, allowed)
        return self.check_number(value, _join(prefix, key), allowed, lo, hi, lo_open, hi_open,
                                 integer)

    def check_number(self, value: Any, path: str, allowed: str, lo: float = -math.inf,
                     hi: float = math.inf, lo_open: bool = False, hi_open: bool = False,
                     integer: bool = False) -> Any:
        kinds = (int,) if integer else (int, float)
        if isinstance(value, bool) or not isinstance(value, kinds):
            self.fail(path, "wrong type", allowed, value)
        if not math.isfinite(value):
            self.fail(path, "not finite", allowed, value)
        below = value <= lo if lo_open else value < lo
        above = value >= hi if hi_open else value > hi
        if below or above:
            self.fail(path, "out of range", allowed, value)
        return int(value) if integer else float(value)

    def vec3(self, table: Mapping, key: str, prefix: str, default: Any, auto: bool = False,
             lo: float = -math.inf, hi: float = math.inf) -> Any:
        path = _join(prefix, key)
        each = "finite numbers" if lo == -math.inf else f"numbers in [{lo:g}, {hi:g}]"
        allowed = f"3 {each}, [x, y, z]" if lo == -math.inf else f"3 {each}, [r, g, b]"
        if auto:
            allowed += ', or "auto"'
        value = self.get(table, key, prefix, default, allowed)
        if auto and value == "auto":
            return None
        if not isinstance(value, list | tuple) or len(value) != 3:
            self.fail(path, "not a list of 3 numbers", allowed, value)
        return tuple(self.check_number(x, f"{path}[{i}]", allowed, lo, hi)
                     for i, x in enumerate(value))

    def choice(self, table: Mapping, key: str, prefix: str, default: Any,
               choices: tuple[str, ...]) -> str:
        allowed = ", ".join(choices)
        value = self.get(table, key, prefix, default, allowed)
        if not isinstance(value, str) or value not in choices:
            close = difflib.get_close_matches(value, choices, n=1) if isinstance(
                value, str) else []
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            self.fail(_join(prefix, key), f"unknown value{hint}", allowed, value)
        return value

    def string(self, table: Mapping, key: str, prefix: str, default: Any, allowed: str) -> str:
        value = self.get(table, key, prefix, default, allowed)
        if not isinstance(value, str) or not value:
            self.fail(_join(prefix, key), "not a non-empty string", allowed, value)
        return value

    def boolean(self, table: Mapping, key: str, prefix: str, default: bool) -> bool:
        value = self.get(table, key, prefix, default, "true or false")
        if not isinstance(value, bool):
            self.fail(_join(prefix, key), "wrong type", "true or false", value)
        return value

    def array_of_tables(self, data: Mapping, key: str) -> list[dict]:
        value = data.get(key, [])
        if not isinstance(value, list) or not all(isinstance(x, dict) for x in value):
            self.fail(key, "not an array of tables", f"[[{key}]] tables", value)
        return value

    # ---- the scene, table by table

    def scene(self, data: Mapping, default_name: str) -> Scene:
        self.keys(data, "", ("name", "camera", "settings", "materials", "lamps", "objects",
                             "floor"))
        name = self.string(data, "name", "", default_name, "a non-empty string")
        materials = self.materials(self.table(data, "materials", ""))
        defined = tuple(m.name for m in materials)
        objects = tuple(self.object(o, f"objects[{i}]", defined)
                        for i, o in enumerate(self.array_of_tables(data, "objects")))
        if not objects:
            self.fail("objects", "no objects", "one or more [[objects]] tables, each with "
                      "mesh and material")
        lamps = tuple(self.lamp(t, f"lamps[{i}]")
                      for i, t in enumerate(self.array_of_tables(data, "lamps")))
        if sum(lamp.position is None for lamp in lamps) > 1:
            self.fail("lamps", 'more than one lamp with position = "auto"',
                      'at most one "auto" lamp; give the others [x, y, z]')
        return Scene(
            name=name, materials=materials, lamps=lamps, objects=objects,
            floor=self.floor(self.table(data, "floor", ""), defined) if "floor" in data
            else None,
            camera=self.camera(self.table(data, "camera", "")),
            settings=self.settings(self.table(data, "settings", "")),
            source=self.source,
        )

    def materials(self, table: Mapping) -> tuple[Material, ...]:
        out = []
        for name, body in table.items():
            path = f"materials.{name}"
            if not isinstance(body, dict):
                self.fail(path, "not a table", f"a table [{path}] with kind = "
                          + " | ".join(KINDS), body)
            out.append(self.material(name, body, path))
        return tuple(out)

    def material(self, name: str, body: Mapping, path: str) -> Material:
        kind = self.choice(body, "kind", path, _REQUIRED, KINDS)
        if kind == "diffuse":
            self.keys(body, path, ("kind", "albedo"))
            return Material(name, kind, albedo=self.vec3(body, "albedo", path, [0.8] * 3,
                                                         lo=0.0, hi=1.0))
        if kind == "mirror":
            self.keys(body, path, ("kind", "reflectance"))
            return Material(name, kind, reflectance=self.vec3(body, "reflectance", path,
                                                              [0.9] * 3, lo=0.0, hi=1.0))
        self.keys(body, path, ("kind", "index", "glass", "cauchy"))
        given = [k for k in ("index", "glass", "cauchy") if k in body]
        if len(given) != 1:
            self.fail(path, f"a dielectric needs exactly one of index, glass, cauchy "
                      f"(got {', '.join(given) or 'none'})",
                      "index = n in (1, 5], glass = a catalogue name, cauchy = [A, B]")
        a_lo, a_hi = INDEX_RANGE
        if given == ["index"]:
            return Material(name, kind, index=self.number(body, "index", path, _REQUIRED,
                                                          a_lo, a_hi, lo_open=True))
        if given == ["cauchy"]:
            value = body["cauchy"]
            cpath = f"{path}.cauchy"
            b_lo, b_hi = CAUCHY_B_RANGE
            allowed = (f"[A, B] with A {_interval(a_lo, a_hi, True, False)} and B (µm²) "
                       f"{_interval(b_lo, b_hi, False, False)}")
            if not isinstance(value, list) or len(value) != 2:
                self.fail(cpath, "wrong type", allowed, value)
            a = self.check_number(value[0], f"{cpath}[0]", allowed, a_lo, a_hi, lo_open=True)
            b = self.check_number(value[1], f"{cpath}[1]", allowed, b_lo, b_hi)
            return Material(name, kind, cauchy=(a, b))
        glass = body["glass"]
        gpath = f"{path}.glass"
        try:
            catalogue = glass_catalogue()
        except ModuleNotFoundError as exc:
            if exc.name not in ("jrt.optics", "jrt"):
                raise
            self.fail(gpath, "the glass catalogue jrt.optics.GLASSES is not available",
                      "index = n or cauchy = [A, B] instead", glass)
        names = {_norm(k): k for k in catalogue}
        if not isinstance(glass, str) or _norm(glass) not in names:
            self.fail(gpath, "unknown glass", ", ".join(catalogue), glass)
        canonical = names[_norm(glass)]
        a, b = catalogue[canonical]
        return Material(name, kind, glass=canonical, cauchy=(float(a), float(b)))

    def mesh(self, value: Any, path: str) -> str:
        allowed = (f"{', '.join(MESHES)}, or a mesh file ({', '.join(SUFFIXES)}, each also "
                   ".gz) relative to the scene file")
        if not isinstance(value, str) or not value:
            self.fail(path, "not a non-empty string", allowed, value)
        if value in MESHES:
            return value
        file = (self.base_dir / Path(value).expanduser()).resolve()
        if mesh_suffix(file).lower() not in SUFFIXES:
            self.fail(path, "unsupported mesh format", allowed, value)
        if not file.is_file():
            self.fail(path, f"no such file ({file})", allowed, value)
        return str(file)

    def object(self, body: Mapping, path: str, defined: tuple[str, ...]) -> Object:
        self.keys(body, path, ("mesh", "material", "scale", "rotate", "translate",
                               "crease_angle"))
        mesh_allowed = f"{', '.join(MESHES)}, or a mesh file"
        mesh = self.mesh(self.get(body, "mesh", path, _REQUIRED, mesh_allowed),
                         f"{path}.mesh")
        return Object(
            mesh=mesh,
            material=self.material_ref(body, path, defined),
            scale=self.number(body, "scale", path, 1.0, 0.0, lo_open=True),
            rotate=self.vec3(body, "rotate", path, [0.0] * 3),
            translate=self.vec3(body, "translate", path, [0.0] * 3),
            crease_angle=self.number(body, "crease_angle", path, DEFAULT_CREASE_ANGLE,
                                     0.0, 180.0),
        )

    def material_ref(self, body: Mapping, path: str, defined: tuple[str, ...]) -> str:
        allowed = ("a material defined under [materials]: " + ", ".join(defined)
                   if defined else "a name defined as [materials.NAME] (none defined)")
        name = self.string(body, "material", path, _REQUIRED, allowed)
        if name not in defined:
            close = difflib.get_close_matches(name, defined, n=1)
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            self.fail(f"{path}.material", f"material not defined{hint}", allowed, name)
        return name

    def lamp(self, body: Mapping, path: str) -> Lamp:
        self.keys(body, path, ("position", "intensity", "spectrum"))
        return Lamp(
            position=self.vec3(body, "position", path, "auto", auto=True),
            intensity=self.number(body, "intensity", path, 1.0, 0.0, lo_open=True),
            spectrum=self.illuminant(body, path),
        )

    def illuminant(self, body: Mapping, path: str) -> str:
        value = self.get(body, "spectrum", path, "D65", ", ".join(ILLUMINANTS))
        if isinstance(value, str) and value in ILLUMINANTS:
            return value
        names = illuminant_names()
        if not isinstance(value, str) or value not in names:
            close = difflib.get_close_matches(value, names, n=1) if isinstance(
                value, str) else []
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            self.fail(f"{path}.spectrum", f"unknown illuminant{hint}",
                      f"{', '.join(ILLUMINANTS)}, or another colour.SDS_ILLUMINANTS name",
                      value)
        return value

    def floor(self, body: Mapping, defined: tuple[str, ...]) -> Floor | None:
        self.keys(body, "floor", ("material", "enabled", "extent", "gap"))
        enabled = self.boolean(body, "enabled", "floor", True)
        floor = Floor(
            material=self.material_ref(body, "floor", defined),
            extent=self.number(body, "extent", "floor", 3.0, 1.0, 1000.0),
            gap=self.number(body, "gap", "floor", 1e-3, 0.0, 1.0),
        )
        return floor if enabled else None

    def camera(self, body: Mapping) -> CameraSpec:
        p = "camera"
        self.keys(body, p, tuple(f.name for f in dataclasses.fields(CameraSpec)))
        spec = CameraSpec(
            eye=self.vec3(body, "eye", p, "auto", auto=True),
            target=self.vec3(body, "target", p, "auto", auto=True),
            up=self.vec3(body, "up", p, [0.0, 1.0, 0.0]),
            vfov=self.number(body, "vfov", p, 30.0, 0.0, 180.0, lo_open=True, hi_open=True),
            azimuth=self.number(body, "azimuth", p, 50.0, -360.0, 360.0),
            elevation=self.number(body, "elevation", p, 20.0, -90.0, 90.0, True, True),
            margin=self.number(body, "margin", p, FRAME_MARGIN, 0.0, 10.0, lo_open=True),
            width=self.number(body, "width", p, 640, 1, MAX_PIXELS, integer=True),
            height=self.number(body, "height", p, 480, 1, MAX_PIXELS, integer=True),
        )
        if (spec.eye is None) != (spec.target is None):
            self.fail("camera.target" if spec.target is None else "camera.eye",
                      "eye and target must both be given or both be \"auto\"",
                      'both [x, y, z], or both "auto"',
                      body.get("target" if spec.target is None else "eye", "auto"))
        if spec.auto:
            if spec.up != (0.0, 1.0, 0.0):
                self.fail("camera.up", 'automatic framing is for a y-up scene',
                          '[0, 1, 0] with eye = "auto"; or give eye and target', list(spec.up))
        else:
            for key in ("azimuth", "elevation", "margin"):
                if key in body:
                    self.fail(f"camera.{key}", "used only by automatic framing",
                              'this field with eye = "auto" only', body[key])
            try:
                spec.resolve(None)
            except ValueError as exc:
                self.fail("camera", str(exc), "a non-degenerate view")
        return spec

    def settings(self, body: Mapping) -> Settings:
        p = "settings"
        self.keys(body, p, tuple(f.name for f in dataclasses.fields(Settings)))
        return Settings(
            max_depth=self.number(body, "max_depth", p, 5, 1, MAX_DEPTH, integer=True),
            samples=self.number(body, "samples", p, 16, 1, MAX_SAMPLES, integer=True),
            threshold=self.number(body, "threshold", p, 1e-3, 0.0, 1.0, hi_open=True),
            kernel=self.choice(body, "kernel", p, DEFAULT_KERNEL, tuple(KERNELS)),
            accel=self.choice(body, "accel", p, "bvh", tuple(accel.NAMES)),
            background=self.choice(body, "background", p, "black", BACKGROUNDS),
            ambient=self.number(body, "ambient", p, 0.1, 0.0, 1.0),
            fresnel=self.choice(body, "fresnel", p, "exact", FRESNEL_MODELS),
        )


def _join(prefix: str, key: str) -> str:
    return f"{prefix}.{key}" if prefix else key


# --------------------------------------------------------------------------- TOML out


def _toml(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int | float):
        return repr(value)
    if isinstance(value, str):
        return json.dumps(value, ensure_ascii=False)
    return "[" + ", ".join(_toml(x) for x in value) + "]"


def _lines(fields: Mapping[str, Any]) -> list[str]:
    return [f"{k} = {_toml(v)}" for k, v in fields.items() if v is not None]


def _dump(scene: Scene) -> str:
    cam = scene.camera
    camera = dataclasses.asdict(cam)
    if cam.auto:
        camera.update(eye="auto", target="auto")
    else:
        for key in ("azimuth", "elevation", "margin"):
            camera.pop(key)
    out = [f"name = {_toml(scene.name)}", "", "[camera]", *_lines(camera), "",
           "[settings]", *_lines(dataclasses.asdict(scene.settings))]
    for m in scene.materials:
        fields = {"kind": m.kind, "albedo": m.albedo, "reflectance": m.reflectance,
                  "index": m.index}
        if m.glass is not None:
            fields["glass"] = m.glass
        elif m.cauchy is not None:
            fields["cauchy"] = m.cauchy
        out += ["", f"[materials.{_toml(m.name)}]", *_lines(fields)]
    for lamp in scene.lamps:
        fields = dataclasses.asdict(lamp)
        fields["position"] = "auto" if lamp.position is None else lamp.position
        out += ["", "[[lamps]]", *_lines(fields)]
    for obj in scene.objects:
        out += ["", "[[objects]]", *_lines(dataclasses.asdict(obj))]
    if scene.floor is not None:
        out += ["", "[floor]", *_lines(dataclasses.asdict(scene.floor))]
    return "\n".join(out) + "\n"


# --------------------------------------------------------------------------- assembly


@dataclasses.dataclass(frozen=True, eq=False)
class SceneGeometry:
    """A scene as arrays: every object transformed, the floor appended (last two faces).

    Attributes:
        mesh: the whole scene as one validated :class:`jrt.Mesh` (float32 vertices [V, 3],
            int32 faces [F, 3]); build the acceleration structure over it.
        material_of_face: int32 [F], index into ``materials`` of each face.
        normals: float32 [F, 3, 3], the shading normal of each face's corners
            (:func:`jrt.normals.corner_normals` of each object with its ``crease_angle``;
            the floor flat).
        materials: the scene's materials, in index order.
        lamps: the lamps, each with its position resolved.
        camera: the resolved :class:`jrt.Camera`.
        object_faces: ``(start, stop)`` face range of each object, then of the floor.
        features: ``scene.features()``.
    """

    mesh: Mesh
    material_of_face: np.ndarray
    normals: np.ndarray
    materials: tuple[Material, ...]
    lamps: tuple[Lamp, ...]
    camera: Camera
    object_faces: tuple[tuple[int, int], ...]
    features: Features

    @property
    def vertices(self) -> np.ndarray:
        return self.mesh.vertices

    @property
    def faces(self) -> np.ndarray:
        return self.mesh.faces

    @property
    def lamp_positions(self) -> np.ndarray:
        """float32 [L, 3]."""
        return np.asarray([lamp.position for lamp in self.lamps], np.float32).reshape(-1, 3)

    @property
    def lamp_intensities(self) -> np.ndarray:
        """float32 [L]."""
        return np.asarray([lamp.intensity for lamp in self.lamps], np.float32)


def _load_object_mesh(obj: Object) -> Mesh:
    return load_mesh(camel_path(obj.mesh) if obj.mesh in MESHES else obj.mesh)


def floor_quad(lo, hi, extent: float, gap: float) -> tuple[np.ndarray, np.ndarray]:
    """float64 [4, 3] corners and int [2, 3] faces (normal +y) of the floor under the box
    ``lo``..``hi`` (see :class:`Floor`)."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    centre = (lo + hi) / 2
    half = extent * max(float(hi[0] - lo[0]), float(hi[2] - lo[2]), 1e-12) / 2
    y = lo[1] - gap * float(np.linalg.norm(hi - lo))
    x0, x1, z0, z1 = centre[0] - half, centre[0] + half, centre[2] - half, centre[2] + half
    corners = np.array([[x0, y, z0], [x1, y, z0], [x1, y, z1], [x0, y, z1]])
    # (a, d, c) and (a, c, b): (d - a) x (c - a) = (0, dz dx, 0), pointing up.
    return corners, np.array([[0, 3, 2], [0, 2, 1]])


def assemble(scene: Scene) -> SceneGeometry:
    """Load, transform and concatenate the scene's meshes; resolve the camera and lamps.

    Raises :class:`SceneError` for a mesh that fails :func:`jrt.load_mesh`'s validation,
    FileNotFoundError when the camel data cannot be found.
    """
    from jrt.render import default_lamp

    vertices, faces, material, ranges, normals = [], [], [], [], []
    loaded: dict[str, Mesh] = {}
    count = 0  # vertices so far
    for i, obj in enumerate(scene.objects):
        try:
            if obj.mesh not in loaded:
                loaded[obj.mesh] = _load_object_mesh(obj)
        except MeshError as exc:
            raise SceneError(f"{scene.source}: objects[{i}].mesh: {exc}") from exc
        mesh = loaded[obj.mesh]
        start = sum(len(f) for f in faces)
        vertices.append(obj.transform(mesh.vertices))
        normals.append(corner_normals(vertices[-1], mesh.faces, obj.crease_angle))
        faces.append(mesh.faces.astype(np.int64) + count)
        material.append(np.full(len(mesh.faces), scene.material_index(obj.material)))
        ranges.append((start, start + len(mesh.faces)))
        count += len(mesh.vertices)
    try:
        objects = mesh_from_arrays(np.concatenate(vertices), np.concatenate(faces),
                                   name=f"{scene.name} (objects)")
    except MeshError as exc:  # e.g. a scale that underflows float32
        raise SceneError(f"{scene.source}: objects: {exc}") from exc
    camera = scene.camera.resolve(objects.vertices)
    lamps = tuple(
        lamp if lamp.position is not None else dataclasses.replace(
            lamp, position=tuple(float(x) for x in default_lamp(objects, camera)))
        for lamp in scene.lamps
    )
    if scene.floor is not None:
        lo, hi = objects.bounds
        corners, quad = floor_quad(lo, hi, scene.floor.extent, scene.floor.gap)
        start = len(objects.faces)
        vertices.append(corners)
        faces.append(quad + count)
        normals.append(corner_normals(corners, quad, 0.0))
        material.append(np.full(2, scene.material_index(scene.floor.material)))
        ranges.append((start, start + 2))
    whole = mesh_from_arrays(np.concatenate(vertices), np.concatenate(faces),
                             name=scene.name) if scene.floor is not None else objects
    return SceneGeometry(
        mesh=whole,
        material_of_face=np.concatenate(material).astype(np.int32),
        normals=np.concatenate(normals).astype(np.float32),
        materials=scene.materials,
        lamps=lamps,
        camera=camera,
        object_faces=tuple(ranges),
        features=scene.features(),
    )


__all__ = [
    "BACKGROUNDS",
    "BUILTIN_SCENES",
    "ILLUMINANTS",
    "KINDS",
    "CameraSpec",
    "Features",
    "Floor",
    "Lamp",
    "Material",
    "Object",
    "Scene",
    "SceneError",
    "SceneGeometry",
    "Settings",
    "assemble",
    "builtin_toml",
    "floor_quad",
    "glass_catalogue",
    "illuminant_names",
    "load_scene",
    "parse_scene",
]
