"""The scene model: frozen, validated dataclasses and the static features they imply.

A :class:`Scene` is what :func:`jrt.scene.load_scene` returns after checking every field
(:mod:`jrt.scene.toml_io` does the checking and names the offending field); the classes
here hold the values and the rules that follow from them (a material's refractive index,
an object's transform, which features the renderer must compile). NumPy only: nothing
here is traced by JAX. ``scene.features()`` is a hashable record meant as a static argument
to ``jax.jit``.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from jrt.camera import FRAME_MARGIN, Camera, frame_mesh
from jrt.kernels import DEFAULT_KERNEL
from jrt.normals import DEFAULT_CREASE_ANGLE

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
    """A point lamp. ``position`` None means "auto" until :func:`jrt.scene.assemble` resolves it."""

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
    """Render settings (ranges: the schema in :mod:`jrt.scene.toml_io`)."""

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
        """The scene as TOML that :func:`jrt.scene.parse_scene` reads back to an equal
        scene."""
        from jrt.scene.toml_io import dump_scene  # the writer imports this module

        return dump_scene(self)


__all__ = [
    "BACKGROUNDS",
    "CAUCHY_B_RANGE",
    "FRESNEL_MODELS",
    "ILLUMINANTS",
    "INDEX_RANGE",
    "KINDS",
    "MAX_DEPTH",
    "MAX_PIXELS",
    "MAX_SAMPLES",
    "CameraSpec",
    "Features",
    "Floor",
    "Lamp",
    "Material",
    "Object",
    "Scene",
    "SceneError",
    "Settings",
    "Vec3",
]
