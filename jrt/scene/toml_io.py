"""Scene files: TOML text (or a built-in scene's name) into a validated :class:`Scene`,
and a scene back to TOML.

The way in is :func:`load_scene` (a built-in name or a file) or :func:`parse_scene` (text);
the way out is :func:`dump_scene` (``Scene.to_toml``), which :func:`parse_scene` reads back
to an equal scene.

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
    position = "auto"                     # or [x, y, z]; "auto": above the camera
                                          #   (jrt.scene.assembly.default_lamp)
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

import accel
from jrt.camera import FRAME_MARGIN
from jrt.data import MESHES
from jrt.kernels import DEFAULT_KERNEL, KERNELS
from jrt.mesh import SUFFIXES, mesh_suffix
from jrt.normals import DEFAULT_CREASE_ANGLE
from jrt.scene.builtin_scenes import BUILTIN_SCENES
from jrt.scene.model import (
    BACKGROUNDS,
    CAUCHY_B_RANGE,
    FRESNEL_MODELS,
    ILLUMINANTS,
    INDEX_RANGE,
    KINDS,
    MAX_DEPTH,
    MAX_PIXELS,
    MAX_SAMPLES,
    CameraSpec,
    Floor,
    Lamp,
    Material,
    Object,
    Scene,
    SceneError,
    Settings,
)

# --------------------------------------------------------------------------- reading


def load_scene(spec: str | Path) -> Scene:
    """A built-in scene's name (:data:`jrt.scene.BUILTIN_SCENES`) or the path of a ``.toml``
    file."""
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


def dump_scene(scene: Scene) -> str:
    """The scene as TOML text (``Scene.to_toml``): each field that applies, defaults too,
    ``"auto"`` for an automatic camera or lamp; :func:`parse_scene` reads it back to an
    equal scene."""
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


__all__ = ["dump_scene", "glass_catalogue", "illuminant_names", "load_scene", "parse_scene"]
