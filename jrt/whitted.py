"""The Whitted renderer: the seed's tree of reflected and refracted rays, level by level.

    setup = prepare(load_scene("glass-camel"))            # NumPy side: arrays, structure
    image, stats = render_scene(setup, width=320, height=240)
    radiance, stats = render_radiance(setup, max_depth=4)  # linear, per channel
    render, params = renderer(setup, width=320, height=240)  # a pure function of params
    radiance = render(params)                              # jnp [H, W, C]

The tree (Whitted, "An improved illumination model for shaded display", CACM 23(6), 1980;
the seed's ``couleur = kR·lancer(réfléchi) + kT·lancer(réfracté)``). Rays leave the eye
(reverse light path, seed Théorème 2.2). At a surface a ray of weight ``w`` either ends or
spawns children:

* **miss**: adds ``w × background`` (``"black"``: 0; ``"sky"``: :func:`sky_rgb`, a vertical
  gradient over the ray's *direction*, zenith :data:`jrt.render.SKY_TOP` to nadir
  :data:`jrt.render.SKY_BOTTOM`, turned into the channels as a reflectance lit by the lamp
  illuminant: ``rgb_to_reflectance(sky) × illuminant``);
* **diffuse**: adds ``w × albedo × Σ_lamps lamp × (ambient + (1 - ambient) max(0, n·l) V)``,
  ``V`` the visibility of the lamp by a shadow ray (``jrt.occluded``, any hit before the
  lamp; every surface, glass included, casts a shadow), the look of :mod:`jrt.render`. With
  no lamp, a diffuse surface shows ``w × albedo × ambient × illuminant``. No children;
* **mirror**: one child, ``reflect(d, n)`` (seed eq. 2), weight ``w × reflectance``;
* **dielectric**: Fresnel's ``(R, T)`` (unpolarised, :func:`jrt.optics.fresnel`; Schlick's
  approximation, :func:`jrt.optics.schlick`, with ``settings.fresnel = "schlick"``) for the
  indices on either side (outside: 1; inside: Cauchy's ``n(λ) = A + B/λ²``); children the
  reflected ray (seed eq. 2) with ``w × R`` and the refracted one (seed eq. 1) with ``w × T``;
  under total internal reflection ``R = 1`` and the reflected child is the only one.

Entering and leaving are told apart by the sign of ``d · n_g``, ``n_g`` the geometric normal
of the face's winding (outward for a closed, consistently oriented mesh such as the camel).
Directions use the shading normal ``n_s`` (the hit face's corner normals interpolated at its
barycentrics, :func:`jrt.normals.corner_normals`); where it would send a child to the
wrong side of the geometric surface (or faces away from the ray), that hit uses ``n_g``.

**Channels.** A scene with dispersion (a Cauchy ``B != 0``) is rendered spectrally, over
``settings.samples`` wavelength samples; since ``n`` depends on ``λ`` (seed, dispersion) each
sample follows its own path through the glass. A camera ray, though, carries all of them as
a *bundle* (weights over the C samples) to its first surface: its hit, its shadow rays and
a diffuse or background contribution are the same for every wavelength, and only its
children part, one ray per sample (weights [1] and a wavelength index), wavelength-major,
in the order the host tree gives. Without dispersion one tree per pixel carries an RGB
weight (3 channels, :func:`jrt.spectral.rgb_tables`). One code path: a ray's weight has
``K`` channels, ``K = 1`` (one sample), ``C`` (a bundle) or ``3`` (RGB); the radiance per
pixel has ``C = S`` or ``3`` channels and goes to sRGB through :mod:`jrt.spectral` (its
radiance convention: lamp units, the illuminant multiplied in by the renderer; every lamp is
scaled to luminance Y = 1 at intensity 1).

**One compiled program.** :func:`render_radiance` and :func:`render_scene` run
:func:`renderer` (:mod:`jrt.wavefront`): every level of the tree inside one jitted program,
a pure function of the scene's parameters, with no host step between levels. Each level is
one batched closest hit over its live rays, shaded by :func:`_shade_chunk`, whose static
arguments are the scene's :class:`jrt.scene.Features` (with the depth taken out), the
kernel, the background and the mode: an opaque scene compiles no Fresnel or refraction
code, a scene without mirrors no mirror branch, a scene without lamps no shadow rays. A
child whose weight (largest channel) is below ``settings.threshold`` is pruned, exactly
(its weight is counted in ``stats.dropped_weight``). **Past the maximum depth** the children
left are not traced: they contribute black (their weight is ``stats.truncated_weight``).
:func:`host_radiance` is the same tree stepped from the host, one level and one
:data:`CHUNK` of rays per device call, NumPy compaction between levels and every camera ray
per wavelength sample: slower, and an independent route the tests compare the renderer
with (and it can return the image at every depth, ``by_depth=True``: a render at depth
``d`` is exactly the sum of levels ``0..d-1`` of any deeper render).

**Rays per pixel.** Per camera ray and wavelength sample, level ``d`` holds at
most ``2^d`` rays with glass (each dielectric hit doubles, total internal reflection and
misses and diffuse hits end branches), at most 1 with mirrors only; up to depth ``D`` at most
``2^D - 1`` rays in all, plus one shadow ray per lamp per diffuse hit. Pruning by weight
cuts the exponential growth: along a path the weight is a product of Fresnel R, T, so
branches of many reflections die out (R ≈ 0.04 for glass at normal incidence). Measured
numbers are in ``stats.rays_per_pixel_by_depth`` (rays at level d per camera ray).

**Sampled variant** (``mode="sampled"``): at a dielectric a path follows *one* branch,
reflected with probability ``R``, refracted otherwise, with its weight unchanged (the
estimator ``R × L_r / p = L_r``, pbrt-v4 §13.1.2 / §9.5 on sampling Fresnel); every level has
at most as many rays as the one before. ``spp`` such paths per pixel (and wavelength), all
through the pixel centre, are averaged: the expectation is the tree's image (at ``spp =
1``), so the two can be compared error against time. In the tree, ``spp`` is anti-aliasing:
camera rays through stratified positions of the pixel (:func:`jrt.camera.subpixel_offsets`).

**Leaving a surface.** Secondary and shadow rays start at the barycentric hit point moved
off the surface by pbrt-v4's error bound (Pharr, Jakob & Humphreys, *Physically Based
Rendering*, 4th ed., §6.8.5 "Bounding intersection point error" and §6.8.6 "Robust spawned
ray origins", ``OffsetRayOrigin``): ``p_err = γ7 (|b0 v0| + |b1 v1| + |b2 v2|)`` per
component, the origin moves by ``Σ|n_i| p_err_i`` along the geometric normal to the side the
new ray goes to, each coordinate then rounded away with ``nextafter``. The offset scales with
the coordinates, not with a scene size.
"""

from __future__ import annotations

import dataclasses
import functools
import time
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

import accel
from accel.structure import Structure
from jrt import optics
from jrt import structure as _structure  # noqa: F401  (registers Structure as a pytree)
from jrt.camera import Camera, camera_rays
from jrt.kernels import _gamma, cross, dot
from jrt.render import SKY_BOTTOM, SKY_TOP
from jrt.scene import Features, Scene, SceneGeometry, assemble, load_scene
from jrt.spectral import (
    SpectralTables,
    encode_srgb,
    rgb_tables,
    rgb_to_reflectance,
    spectral_tables,
    spectrum_to_srgb,
)
from jrt.trace import query_status, raise_on_status

#: Rays per call of the compiled level function (padded up to it).
CHUNK = 1 << 15
#: Material kind codes in :attr:`SceneArrays.kind`.
KIND_CODES = {"diffuse": 0, "mirror": 1, "dielectric": 2}
MODES = ("tree", "sampled")
MISS = -1


# --------------------------------------------------------------------------------------------
# Records
# --------------------------------------------------------------------------------------------


class SceneArrays(NamedTuple):
    """Everything the level function reads besides the structure (a JAX pytree).

    ``C`` is the number of channels: the wavelength samples (spectral mode) or 3 (RGB).
    """

    vertices: Float[Array, "v 3"]
    faces: Int[Array, "f 3"]
    normals: Float[Array, "f 3 3"]  # corner normals (jrt.normals.corner_normals)
    material: Int[Array, " f"]  # material index of each face
    kind: Int[Array, " m"]  # KIND_CODES
    albedo: Float[Array, "m c"]  # diffuse reflectance over the channels
    reflectance: Float[Array, "m c"]  # mirror reflectance over the channels
    cauchy: Float[Array, "m 2"]  # dielectric (A, B µm²); a constant index is (n, 0)
    lamp_positions: Float[Array, "l 3"]
    lamp_radiance: Float[Array, "l c"]  # intensity × spectrum, luminance Y = intensity
    sky: Float[Array, "2 c"]  # zenith and nadir radiance over the channels
    wavelengths: Float[Array, " c"]  # nm (RGB mode: nominal labels, unused)
    illuminant: Float[Array, " c"]  # the tables' lamp spectrum (ambient without lamps)
    ambient: Float[Array, ""]


class Rays(NamedTuple):
    """A level's rays, NumPy arrays (host side, between levels).

    Attributes:
        origins, directions: float32 [N, 3], unit directions.
        weights: float32 [N, K], the product of the coefficients along the path.
        pixels: int32 [N], row-major pixel index.
        channels: int32 [N], wavelength sample index (spectral mode); 0 in RGB mode.
        sources: int32 [N], the triangle the ray leaves (-1 for camera rays).
    """

    origins: np.ndarray
    directions: np.ndarray
    weights: np.ndarray
    pixels: np.ndarray
    channels: np.ndarray
    sources: np.ndarray

    def __len__(self) -> int:
        return int(self.pixels.shape[0])

    def take(self, index) -> Rays:
        return Rays(*(a[index] for a in self))


class Level(NamedTuple):
    """What one level did to its rays (NumPy).

    Attributes:
        contributions: float32 [N, K], radiance each ray adds to its pixel and channel.
        kinds: int32 [N], the kind code hit (:data:`KIND_CODES`), ``MISS`` (-1) for none.
        tir: bool [N], total internal reflection at a dielectric hit.
        triangles: int32 [N], the hit triangle (-1: a miss).
        t: float32 [N], the hit distance (inf: a miss).
        children: the spawned rays with nonzero weight (not yet pruned by the threshold).
        parents: int32 [M], index of each child's parent in this level.
        shadow_rays: number of shadow rays traced.
    """

    contributions: np.ndarray
    kinds: np.ndarray
    tir: np.ndarray
    triangles: np.ndarray
    t: np.ndarray
    children: Rays
    parents: np.ndarray
    shadow_rays: int


@dataclasses.dataclass(frozen=True, eq=False)
class RenderSetup:
    """A scene ready to render: geometry, structure, channel tables, material arrays.

    Attributes:
        scene: the validated scene.
        geometry: :func:`jrt.scene.assemble`'s arrays.
        structure: the acceleration structure (host record, with its build stats).
        features: what gets compiled (:meth:`jrt.scene.Scene.features`, or a forced one).
        tables: the channel tables: ``spectral_tables(samples, lamp)`` with dispersion,
            ``rgb_tables(lamp)`` without.
        arrays: :class:`SceneArrays` on the device.
        device_structure: ``structure`` with its arrays on the device.
        bounds: float64 [2, 3], the objects' bounding box (for re-framing the camera).
    """

    scene: Scene
    geometry: SceneGeometry
    structure: Structure
    features: Features
    tables: SpectralTables
    arrays: SceneArrays
    device_structure: Structure
    bounds: np.ndarray

    @property
    def spectral(self) -> bool:
        return bool(self.features.dispersion)

    @property
    def channels(self) -> int:
        """C: wavelength samples in spectral mode, 3 in RGB mode."""
        return int(self.tables.wavelengths.shape[0])

    @property
    def ray_channels(self) -> int:
        """K: the channels of one ray's weight (1 spectral, 3 RGB)."""
        return 1 if self.spectral else 3

    def camera(self, width: int | None = None, height: int | None = None) -> Camera:
        """The scene's camera at another image size (automatic framing refits the box)."""
        spec = self.scene.camera
        w = spec.width if width is None else int(width)
        h = spec.height if height is None else int(height)
        if (w, h) == (spec.width, spec.height):
            return self.geometry.camera
        return dataclasses.replace(spec, width=w, height=h).resolve(self.bounds)


@dataclasses.dataclass(frozen=True)
class RenderStats:
    """What a render did.

    ``rays_per_level[d]``: live rays traced at level d (0: camera rays, one per pixel,
    wavelength sample and sample per pixel). ``rays_per_pixel_by_depth[d]``: the same per
    camera ray, i.e. per pixel and wavelength (and spp), at most 2^d. ``shadow_rays``: the
    shadow rays actually cast (diffuse hits facing a lamp). Weights are in camera-ray units
    (a camera ray starts at 1 in every channel; a ray's weight is summed over its K channels
    and divided by K): ``dropped_weight`` went to pruning, ``truncated_weight`` to the
    depth limit; divided by ``rays_per_level[0]`` they are shares of the light the camera
    rays could bring back. ``seconds`` is the whole render, compile included;
    ``compile_seconds`` the part spent compiling (0 when the shapes were compiled before).
    """

    width: int
    height: int
    mode: str
    channels: int
    spp: int
    max_depth: int
    rays_per_level: tuple[int, ...]
    shadow_rays: int
    seconds: float
    compile_seconds: float
    dropped_weight: float
    truncated_weight: float
    rays_per_pixel_by_depth: tuple[float, ...]

    @property
    def total_rays(self) -> int:
        return int(sum(self.rays_per_level)) + self.shadow_rays

    @property
    def mrays_per_second(self) -> float:
        """Rays traced per second, compile time left out."""
        busy = self.seconds - self.compile_seconds
        return self.total_rays / busy / 1e6 if busy > 0 else float("nan")

    def summary(self) -> str:
        return (
            f"{self.width}x{self.height} {self.mode} ({self.channels} channels"
            f"{f', {self.spp} spp' if self.spp > 1 else ''}), depth {self.max_depth}: "
            f"rays per level {list(self.rays_per_level)} + {self.shadow_rays:,} shadow rays = "
            f"{self.total_rays:,} rays in {self.seconds:.2f} s (compile "
            f"{self.compile_seconds:.2f} s), {self.mrays_per_second:.3f} Mrays/s"
        )


# --------------------------------------------------------------------------------------------
# Preparing a scene (NumPy side)
# --------------------------------------------------------------------------------------------


def sky_rgb(directions: Float[Array, "*batch 3"]) -> Float[Array, "*batch 3"]:
    """Linear sRGB of the ``"sky"`` background seen along unit ``directions``.

    ``w = (1 - d_y) / 2`` mixes :data:`jrt.render.SKY_TOP` (zenith, w = 0) into
    :data:`jrt.render.SKY_BOTTOM` (nadir, w = 1): the vertical gradient of :mod:`jrt.render`,
    over directions rather than image rows, so that reflected and refracted rays see it too.
    """
    d = jnp.asarray(directions, jnp.float32)
    w = jnp.clip((1 - d[..., 1]) / 2, 0, 1)[..., None]
    return jnp.asarray(SKY_TOP, jnp.float32) * (1 - w) + jnp.asarray(SKY_BOTTOM, jnp.float32) * w


def _lamp_channels(spectrum: str, tables: SpectralTables, spectral: bool) -> np.ndarray:
    """A lamp's spectrum over the channels, scaled to luminance Y = 1 (tables' k, CMFs)."""
    if not spectral:
        return np.asarray(rgb_tables(spectrum).illuminant, np.float64)
    spd = np.asarray(spectral_tables(tables.samples, spectrum,
                                     float(tables.wavelengths[0] - tables.weights[0] / 2),
                                     float(tables.wavelengths[-1] + tables.weights[-1] / 2)
                                     ).illuminant, np.float64)
    y = float(tables.k) * float(np.sum(spd * np.asarray(tables.cmfs[:, 1] * tables.weights)))
    return spd / y


def _scene_arrays(scene: Scene, geometry: SceneGeometry, tables: SpectralTables,
                  spectral: bool) -> SceneArrays:
    m = len(geometry.materials)
    c = int(tables.wavelengths.shape[0])
    kind = np.zeros(m, np.int32)
    albedo_rgb = np.zeros((m, 3), np.float32)
    reflectance_rgb = np.zeros((m, 3), np.float32)
    cauchy = np.zeros((m, 2), np.float32)
    for i, mat in enumerate(geometry.materials):
        kind[i] = KIND_CODES[mat.kind]
        if mat.kind == "diffuse":
            albedo_rgb[i] = mat.albedo
        elif mat.kind == "mirror":
            reflectance_rgb[i] = mat.reflectance
        else:
            cauchy[i] = mat.cauchy if mat.cauchy is not None else (mat.index, 0.0)
    # Spectral mode: reflectance spectra by Mallett & Yuksel's basis at the samples
    # (jrt.spectral.rgb_to_reflectance); RGB mode: the RGB values themselves.
    albedo = np.asarray(rgb_to_reflectance(albedo_rgb, tables), np.float32).reshape(m, c)
    reflectance = np.asarray(rgb_to_reflectance(reflectance_rgb, tables),
                             np.float32).reshape(m, c)
    illuminant = np.asarray(tables.illuminant, np.float64)
    lamps = [(_lamp_channels(lamp.spectrum, tables, spectral) * lamp.intensity)
             for lamp in geometry.lamps]
    lamp_radiance = np.asarray(lamps, np.float32).reshape(len(lamps), c)
    sky_rgb_ends = np.asarray([SKY_TOP, SKY_BOTTOM], np.float32)
    sky = np.asarray(rgb_to_reflectance(sky_rgb_ends, tables), np.float64) * illuminant
    if scene.settings.background == "black":
        sky = np.zeros_like(sky)
    f32 = lambda a: jnp.asarray(a, jnp.float32)  # noqa: E731
    i32 = lambda a: jnp.asarray(a, jnp.int32)  # noqa: E731
    return SceneArrays(
        vertices=f32(geometry.vertices), faces=i32(geometry.faces),
        normals=f32(geometry.normals), material=i32(geometry.material_of_face),
        kind=i32(kind), albedo=f32(albedo), reflectance=f32(reflectance), cauchy=f32(cauchy),
        lamp_positions=f32(geometry.lamp_positions.reshape(-1, 3)),
        lamp_radiance=f32(lamp_radiance), sky=f32(sky),
        wavelengths=f32(tables.wavelengths), illuminant=f32(illuminant),
        ambient=f32(scene.settings.ambient),
    )


def _tables(scene: Scene, features: Features, samples: int) -> SpectralTables:
    illuminant = scene.lamps[0].spectrum if scene.lamps else "D65"
    if features.dispersion:
        return spectral_tables(samples, illuminant)
    return rgb_tables(illuminant)


def prepare(
    scene: Scene | str | Path,
    *,
    structure: Structure | None = None,
    features: Features | None = None,
    samples: int | None = None,
) -> RenderSetup:
    """Assemble ``scene`` (a :class:`Scene`, a built-in name or a TOML path) for rendering.

    Args:
        structure: an ``accel`` structure over the assembled mesh; built with
            ``accel.build(scene.settings.accel, vertices, faces)`` when None.
        features: force what gets compiled (e.g. the general path for an opaque scene);
            default ``scene.features()``.
        samples: wavelength samples (spectral mode); default ``scene.settings.samples``.
    """
    if not isinstance(scene, Scene):
        scene = load_scene(scene)
    geometry = assemble(scene)
    features = geometry.features if features is None else features
    if not isinstance(features, Features):
        raise TypeError(f"features must be a jrt.scene.Features, got {type(features)}")
    if structure is None:
        structure = accel.build(scene.settings.accel, geometry.vertices, geometry.faces)
    samples = scene.settings.samples if samples is None else samples
    tables = _tables(scene, features, samples)
    n_objects = geometry.object_faces[len(scene.objects) - 1][1]
    corners = geometry.vertices[geometry.faces[:n_objects]].reshape(-1, 3).astype(np.float64)
    bounds = np.stack([corners.min(axis=0), corners.max(axis=0)])
    return RenderSetup(
        scene=scene, geometry=geometry, structure=structure, features=features, tables=tables,
        arrays=_scene_arrays(scene, geometry, tables, features.dispersion),
        device_structure=jax.tree.map(jnp.asarray, structure), bounds=bounds,
    )


def _with(setup: RenderSetup, samples: int | None, features: Features | None) -> RenderSetup:
    """The setup with another sample count or forced features (tables rebuilt if needed)."""
    features = setup.features if features is None else features
    samples = setup.tables.samples if samples is None else samples
    if features == setup.features and (not features.dispersion or
                                       samples == setup.tables.samples):
        return setup
    tables = _tables(setup.scene, features, samples)
    return dataclasses.replace(
        setup, features=features, tables=tables,
        arrays=_scene_arrays(setup.scene, setup.geometry, tables, features.dispersion))


# --------------------------------------------------------------------------------------------
# One chunk of one level (JAX)
# --------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class _Static:
    """The static arguments of :func:`_shade_chunk` (hashable)."""

    features: Features  # max_depth and counters taken out: depth is handled between levels
    kernel: str
    sky: bool
    sampled: bool
    schlick: bool  # Schlick's approximation instead of the full Fresnel equations
    # Spectral mode only: the rays are bundles carrying every wavelength sample (weights
    # [N, C]); their children are split, one ray per wavelength sample (weights [N, 1]).
    bundle: bool = False


def _normalise(v):
    return v / jnp.sqrt(jnp.maximum(dot(v, v), 1e-30))[..., None]


def offset_origin(point, error, n, direction):
    """pbrt-v4 §6.8.6, ``OffsetRayOrigin``: move ``point`` off the surface of unit normal
    ``n`` by ``d = Σ|n_i| error_i`` to the side ``direction`` goes to, then round each moved
    coordinate one float further away (``NextFloatUp/Down``)."""
    d = dot(jnp.abs(n), error)
    offset = d[..., None] * n
    offset = jnp.where((dot(direction, n) < 0)[..., None], -offset, offset)
    moved = point + offset
    away = jnp.where(offset > 0, jnp.inf, jnp.where(offset < 0, -jnp.inf, moved))
    return jnp.nextafter(moved, away)


def _pick(table, channels, per_ray: bool):
    """[N, C] per-ray rows -> [N, K]: the ray's own wavelength sample (a spectral ray
    carrying one sample) or all of them (RGB, or a spectral bundle)."""
    if per_ray:
        return jnp.take_along_axis(table, channels[:, None], axis=1)
    return table


class _ChunkOut(NamedTuple):
    """One chunk's results. B children slots: (reflected, refracted) for the tree with
    glass, else 1; a spectral bundle's children are split per wavelength sample, B = C x
    those slots, wavelength-major."""

    contributions: Float[Array, "n k"]
    kinds: Int[Array, " n"]  # KIND_CODES, MISS
    tir: Array  # bool [N] (a bundle: under any of its wavelength samples)
    triangles: Int[Array, " n"]  # hit triangle, -1
    t: Float[Array, " n"]  # hit distance, inf
    child_origins: Float[Array, "n b 3"]
    child_directions: Float[Array, "n b 3"]
    child_weights: Float[Array, "n b kc"]
    child_alive: Array  # bool [N, B]
    child_channels: Int[Array, "n b"]  # each child's wavelength sample index (0 in RGB)
    shadow_rays: Int[Array, ""]
    status: Int[Array, ""]  # the queries' jrt.engine.STATUS_* bits, ORed


@functools.partial(jax.jit, static_argnames=("static",))
def _shade_chunk(structure, scene: SceneArrays, origins, directions, weights, channels, valid,
                 key, *, static: _Static):
    """Closest hits of one chunk of rays and what they do there (see the module doc):
    a :class:`_ChunkOut`. ``valid`` [N] marks the real rays (the rest is padding)."""
    f = static.features
    spectral = f.dispersion
    per_ray = spectral and not static.bundle  # the ray carries one wavelength sample
    n = origins.shape[0]
    k = weights.shape[1]
    c = scene.sky.shape[1]
    tmax = jnp.where(valid, jnp.inf, 0.0).astype(jnp.float32)  # padding never hits
    hits, status = query_status(structure, origins, directions, tmax=tmax,
                                kernel=static.kernel, any_hit=False)
    hit = (hits.triangle >= 0) & valid
    tri = jnp.maximum(hits.triangle, 0)
    corners = scene.faces[tri]
    p = scene.vertices[corners]  # [N, 3, 3]
    b = jnp.stack([1 - hits.u - hits.v, hits.u, hits.v], axis=-1)[..., None]  # [N, 3, 1]
    # The hit point from the barycentrics, not o + t d, and its error bound
    # (pbrt-v4 §6.8.5, Triangle::InteractionFromIntersection: pError = γ7 Σ|b_i p_i|).
    point = (b * p).sum(axis=1)
    error = _gamma(7, jnp.float32) * jnp.abs(b * p).sum(axis=1)
    ng_out = _normalise(cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]))
    # Entering (from outside) when d · n_g < 0 with the winding's outward normal (seed,
    # Proposition 3.2; jrt.optics.orient).
    entering = dot(directions, ng_out) < 0
    ng = jnp.where(entering[:, None], ng_out, -ng_out)  # facing the ray
    ns_out = _normalise((b * scene.normals[tri]).sum(axis=1))  # corner normals at b
    ns = jnp.where(entering[:, None], ns_out, -ns_out)
    mat = scene.material[tri]
    kind = jnp.where(hit, scene.kind[mat], MISS)

    contrib = jnp.zeros((n, k), jnp.float32)
    shadow_count = jnp.zeros((), jnp.int32)
    if static.sky:
        w = jnp.clip((1 - directions[:, 1]) / 2, 0, 1)[:, None]  # as sky_rgb
        top = _pick(jnp.broadcast_to(scene.sky[0], (n, c)), channels, per_ray)
        bottom = _pick(jnp.broadcast_to(scene.sky[1], (n, c)), channels, per_ray)
        background = top * (1 - w) + bottom * w
        contrib = contrib + jnp.where((valid & ~hit)[:, None], weights * background, 0.0)

    if f.diffuse:
        is_diffuse = kind == KIND_CODES["diffuse"]
        albedo = _pick(scene.albedo[mat], channels, per_ray)
        ambient = scene.ambient
        if f.lamps:
            n_lamps = f.lamps
            # [N, L, 3]: from the hit point to each lamp.
            to_lamp = scene.lamp_positions[None, :, :] - point[:, None, :]
            l_dir = _normalise(to_lamp)
            ng_l = jnp.broadcast_to(ng[:, None, :], l_dir.shape)
            cos = jnp.maximum(dot(jnp.broadcast_to(ns[:, None, :], l_dir.shape), l_dir), 0.0)
            # Light from below the geometric surface never reaches it.
            need = is_diffuse[:, None] & (dot(ng_l, l_dir) > 0) & (cos > 0)
            start = offset_origin(jnp.broadcast_to(point[:, None, :], l_dir.shape),
                                   jnp.broadcast_to(error[:, None, :], l_dir.shape),
                                   ng_l, l_dir)
            seg = scene.lamp_positions[None, :, :] - start
            dist = jnp.sqrt(dot(seg, seg))
            s_dir = seg / jnp.maximum(dist, 1e-30)[..., None]
            s_tmax = jnp.where(need, dist, 0.0)
            blocked, shadow_status = query_status(
                structure, start.reshape(-1, 3), s_dir.reshape(-1, 3),
                tmax=s_tmax.reshape(-1), kernel=static.kernel, any_hit=True)
            status = status | shadow_status
            visible = need & ~blocked.reshape(n, n_lamps)
            shadow_count = need.sum(dtype=jnp.int32)
            shade = ambient + (1 - ambient) * cos * visible  # [N, L]
            if per_ray:
                lamp = scene.lamp_radiance.T[channels]  # [N, L]
                light = (lamp * shade).sum(axis=1, keepdims=True)  # [N, 1]
            else:  # Σ_l shade_l lamp_l, written out (no reduced-precision matmul)
                light = (shade[:, :, None] * scene.lamp_radiance[None, :, :]).sum(axis=1)
        else:
            light = ambient * _pick(jnp.broadcast_to(scene.illuminant, (n, c)), channels,
                                    per_ray)
        contrib = contrib + jnp.where(is_diffuse[:, None], weights * albedo * light, 0.0)

    if not (f.mirror or f.dielectric):
        zeros3 = jnp.zeros((n, 1, 3), jnp.float32)
        empty = jnp.zeros((n, 1), bool)
        return _ChunkOut(contrib, kind, jnp.zeros((n,), bool), hits.triangle, hits.t,
                         zeros3, zeros3, jnp.zeros((n, 1, 1 if spectral else k), jnp.float32),
                         empty, jnp.zeros((n, 1), jnp.int32), shadow_count, status)

    if static.bundle:
        # A bundle's wavelength samples part here: each goes on as its own ray (the
        # directions of a dispersive refraction and every Fresnel and mirror weight depend
        # on the wavelength). The children of its C samples are those of C rays of one
        # sample each at this same hit, wavelength-major: the host tree's order.
        def each(a):
            return jnp.repeat(a, c, axis=0)

        split = jnp.tile(jnp.arange(c, dtype=jnp.int32), n)
        dirs, wts, alive, tir = _children(
            static, scene, each(directions), each(ns), each(ng), each(entering), each(kind),
            each(mat),
            weights.reshape(n * c, 1), split, key)
        slots = dirs.shape[1]
        child_channels = jnp.broadcast_to(split[:, None], (n * c, slots)).reshape(n, c * slots)
        dirs = dirs.reshape(n, c * slots, 3)
        wts = wts.reshape(n, c * slots, 1)
        alive = alive.reshape(n, c * slots)
        tir = tir.reshape(n, c).any(axis=1)
    else:
        dirs, wts, alive, tir = _children(static, scene, directions, ns, ng, entering, kind, mat,
                                          weights, channels, key)
        child_channels = jnp.broadcast_to(channels[:, None], alive.shape)
    shape = dirs.shape
    starts = offset_origin(jnp.broadcast_to(point[:, None, :], shape),
                            jnp.broadcast_to(error[:, None, :], shape),
                            jnp.broadcast_to(ng[:, None, :], shape), dirs)
    return _ChunkOut(contrib, kind, tir, hits.triangle, hits.t, starts, dirs, wts, alive,
                     child_channels, shadow_count, status)


def _children(static: _Static, scene: SceneArrays, directions, ns, ng, entering, kind, mat,
              weights, channels, key):
    """The reflected and refracted children of rays that each carry one wavelength sample
    (spectral) or RGB weights: directions [N, B, 3], weights [N, B, K], alive [N, B] (a
    child of zero weight is not alive) and total internal reflection [N]."""
    f = static.features
    spectral = f.dispersion
    n, k = weights.shape
    shading_ok = dot(directions, ns) < 0
    # Seed eq. (2). With the shading normal unless it would send the ray below the
    # geometric surface (or faces away from the ray); then with the geometric normal.
    r_s = optics.reflect(directions, ns)
    use_s = shading_ok & (dot(r_s, ng) > 0)
    is_mirror = kind == KIND_CODES["mirror"]
    is_glass = kind == KIND_CODES["dielectric"]
    tir = jnp.zeros((n,), bool)
    if f.dielectric:
        a, bc = scene.cauchy[mat, 0], scene.cauchy[mat, 1]
        if spectral:
            n_in = optics.cauchy(a, bc, scene.wavelengths[channels])  # Cauchy, seed §3
        else:
            n_in = a  # no dispersion: B = 0
        n1, n2 = optics.interface_indices(entering, n_in, 1.0)
        t_s, tir_s = optics.refract(directions, ns, n1, n2)  # seed eq. (1)
        use_s = use_s & (tir_s | (dot(t_s, ng) < 0))
    normal = jnp.where(use_s[:, None], ns, ng)
    refl = optics.reflect(directions, normal)
    child_w = [jnp.zeros((n, k), jnp.float32)]
    child_d = [refl]
    alive = [jnp.zeros((n,), bool)]
    if f.mirror:
        rho = _pick(scene.reflectance[mat], channels, spectral)
        child_w[0] = jnp.where(is_mirror[:, None], weights * rho, child_w[0])
        alive[0] = alive[0] | is_mirror
    if f.dielectric:
        refr, tir = optics.refract(directions, normal, n1, n2)
        cos_i = -dot(directions, normal)
        fresnel = optics.schlick if static.schlick else optics.fresnel
        big_r, big_t = fresnel(cos_i, n1, n2)  # R = 1, T = 0 under TIR
        big_r, big_t = big_r[:, None], big_t[:, None]
        tir = tir & is_glass
        if static.sampled:
            # One branch, reflected with probability R: weight unchanged (R / p = 1).
            u = jax.random.uniform(key, (n,), jnp.float32)  # float32 under x64 too
            take_r = tir | (u < big_r[:, 0])
            child_d[0] = jnp.where((is_glass & ~take_r)[:, None], refr, child_d[0])
            child_w[0] = jnp.where(is_glass[:, None], weights, child_w[0])
            alive[0] = alive[0] | is_glass
        else:
            child_w[0] = jnp.where(is_glass[:, None], weights * big_r, child_w[0])
            alive[0] = alive[0] | is_glass
            child_d.append(refr)
            child_w.append(jnp.where(is_glass[:, None], weights * big_t, 0.0))
            alive.append(is_glass & ~tir)
    dirs = jnp.stack(child_d, axis=1)  # [N, B, 3]
    wts = jnp.stack(child_w, axis=1)  # [N, B, K]
    alive = jnp.stack(alive, axis=1) & (wts.max(axis=2) > 0)
    return dirs, wts, alive, tir


# --------------------------------------------------------------------------------------------
# Levels (host side)
# --------------------------------------------------------------------------------------------

#: Compiled level functions, keyed by the static arguments and the argument shapes: the
#: whole render compiles once (and a second render of the same shapes not at all).
_COMPILED: dict = {}


def _static(setup: RenderSetup, mode: str) -> _Static:
    features = dataclasses.replace(setup.features, max_depth=0, counters=False)
    return _Static(features=features, kernel=setup.scene.settings.kernel,
                   sky=setup.scene.settings.background == "sky", sampled=mode == "sampled",
                   schlick=setup.scene.settings.fresnel == "schlick")


def _check_mode(mode: str) -> None:
    if mode not in MODES:
        raise ValueError(f"mode must be one of {', '.join(MODES)}, got {mode!r}")


def _check_chunk(chunk) -> int:
    if isinstance(chunk, bool) or not isinstance(chunk, int | np.integer) or chunk < 1:
        raise ValueError(f"chunk must be a positive integer (rays per call), got {chunk!r}")
    return int(chunk)


def _chunk_args(setup: RenderSetup, rays: Rays, start: int, chunk: int, key):
    """The padded chunk ``rays[start:start + chunk]`` as device arrays."""
    stop = min(start + chunk, len(rays))
    m = stop - start
    pad = chunk - m

    def padded(a, fill=0):
        a = a[start:stop]
        if pad:
            a = np.concatenate([a, np.full((pad, *a.shape[1:]), fill, a.dtype)])
        return jnp.asarray(a)

    directions = rays.directions[start:stop]
    if pad:  # unit directions in the padding too: no NaN anywhere
        directions = np.concatenate([directions, np.tile(np.float32([0, 0, 1]), (pad, 1))])
    valid = np.zeros(chunk, bool)
    valid[:m] = True
    return (setup.device_structure, setup.arrays, padded(rays.origins),
            jnp.asarray(directions), padded(rays.weights), padded(rays.channels),
            jnp.asarray(valid), key), m


def compiled_program(cache: dict, fn, args, timing: dict, **static):
    """``fn`` (a jitted function) lowered and compiled for ``args`` and its static keyword
    arguments, once per signature (the statics, the arguments' tree, shapes and dtypes) in
    ``cache``; the seconds spent compiling are added to ``timing["compile"]``. Compiled
    ahead of time so that a render can say how long it compiled."""
    leaves, treedef = jax.tree.flatten(args)
    signature = (fn, tuple(sorted(static.items())), treedef,
                 tuple((np.shape(x), str(x.dtype)) for x in leaves))
    program = cache.get(signature)
    if program is None:
        start = time.perf_counter()
        program = cache[signature] = fn.lower(*args, **static).compile()
        timing["compile"] = timing.get("compile", 0.0) + time.perf_counter() - start
    return program


def shade_level(
    setup: RenderSetup,
    rays: Rays,
    *,
    mode: str = "tree",
    key: Array | None = None,
    chunk: int = CHUNK,
    _timing: dict | None = None,
) -> Level:
    """Trace one level: closest hits of ``rays``, their contributions and their children.

    Children with zero weight (a refracted ray under total internal reflection, the
    children of a black mirror) are left out; none is pruned by the threshold here.
    ``key`` (a ``jax.random`` key) drives the branch choice in ``mode="sampled"``.
    """
    _check_mode(mode)
    chunk = _check_chunk(chunk)
    static = _static(setup, mode)
    timing = {} if _timing is None else _timing
    if key is None:
        key = jax.random.PRNGKey(0)
    parts = []
    for index, start in enumerate(range(0, len(rays), chunk)):
        args, m = _chunk_args(setup, rays, start, chunk, jax.random.fold_in(key, index))
        out = compiled_program(_COMPILED, _shade_chunk, args, timing, static=static)(*args)
        raise_on_status(out.status)
        parts.append(_ChunkOut(*(np.asarray(x)[:m] if np.ndim(x) else int(x) for x in out)))
    return level_from_chunks(parts, rays, setup.ray_channels)


def level_from_chunks(parts: list, rays: Rays, k: int) -> Level:
    """One level's :class:`Level` from its chunks' outputs (host arrays, padding removed)
    for the level's ``rays``: the chunks concatenated, the live children gathered
    parent-major (children stay in their parents' order: coherent chunks next level)."""
    if not parts:
        return Level(np.zeros((0, k), np.float32), np.zeros(0, np.int32), np.zeros(0, bool),
                     np.zeros(0, np.int32), np.zeros(0, np.float32), _empty_rays(k),
                     np.zeros(0, np.int32), 0)
    arrays = len(_ChunkOut._fields) - 2  # then shadow_rays (summed), status (ORed)
    out = _ChunkOut(*(np.concatenate(x) if i < arrays else
                      (sum(x) if i == arrays else functools.reduce(np.bitwise_or, x))
                      for i, x in enumerate(zip(*parts, strict=True))))
    parent, slot = np.nonzero(out.child_alive)
    children = Rays(
        origins=out.child_origins[parent, slot], directions=out.child_directions[parent, slot],
        weights=out.child_weights[parent, slot], pixels=rays.pixels[parent],
        channels=out.child_channels[parent, slot],
        sources=out.triangles[parent].astype(np.int32))
    return Level(out.contributions, out.kinds, out.tir, out.triangles, out.t, children,
                 parent.astype(np.int32), int(out.shadow_rays))


def _empty_rays(k: int) -> Rays:
    return Rays(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32),
                np.zeros((0, k), np.float32), np.zeros(0, np.int32), np.zeros(0, np.int32),
                np.zeros(0, np.int32))


def camera_level(setup: RenderSetup, camera: Camera, spp: int = 1, *,
                 mode: str = "tree") -> Rays:
    """Level 0, from the eye (seed Théorème 2.2), pixel-major: ``spp`` rays per pixel, in
    the tree through its :func:`jrt.camera.subpixel_offsets` (stratified anti-aliasing; 1:
    the centre), in the sampled mode all through its centre (``spp`` paths); in spectral
    mode each replicated per wavelength sample (weights [N, 1]). (The renderer makes its
    own camera rays, as bundles: :mod:`jrt.wavefront`.)"""
    _check_mode(mode)
    subpixel = spp if mode == "tree" else 1
    origins, directions = (np.asarray(a) for a in camera_rays(camera, subpixel))
    pixels = camera.num_rays
    rays = np.repeat(np.arange(pixels * subpixel), spp // subpixel)  # [P * spp]
    pixel = np.repeat(np.arange(pixels, dtype=np.int32), spp)
    copies = setup.channels if setup.spectral else 1
    index = np.repeat(rays, copies)
    channels = (np.tile(np.arange(copies, dtype=np.int32), pixels * spp) if setup.spectral
                else np.zeros(index.size, np.int32))
    return Rays(
        origins=origins[index], directions=directions[index],
        weights=np.ones((index.size, setup.ray_channels), np.float32),
        pixels=np.repeat(pixel, copies), channels=channels,
        sources=np.full(index.shape, -1, np.int32))


def _accumulate(radiance: np.ndarray, rays: Rays, contributions: np.ndarray,
                spectral: bool) -> None:
    """radiance [P, C] += each ray's contribution at its pixel (and wavelength sample)."""
    p, c = radiance.shape
    if spectral:
        index = rays.pixels.astype(np.int64) * c + rays.channels
        values = contributions[:, 0]
    else:
        index = (rays.pixels.astype(np.int64)[:, None] * c + np.arange(c)).ravel()
        values = contributions.ravel()
    radiance += np.bincount(index, weights=values, minlength=p * c).reshape(p, c)


def render_arguments(
    scene_or_setup: RenderSetup | Scene | str | Path,
    *,
    max_depth: int | None,
    samples: int | None,
    mode: str,
    spp: int,
    features: Features | None,
    threshold: float | None,
) -> tuple[RenderSetup, int, float]:
    """A render's arguments checked, with the scene's defaults filled in: the setup, the
    depth and the pruning threshold (every renderer takes its arguments through here)."""
    _check_mode(mode)
    if isinstance(spp, bool) or not isinstance(spp, int) or spp < 1:
        raise ValueError(f"spp must be a positive integer, got {spp!r}")
    setup = (scene_or_setup if isinstance(scene_or_setup, RenderSetup)
             else prepare(scene_or_setup, features=features, samples=samples))
    setup = _with(setup, samples, features)
    depth = setup.features.max_depth if max_depth is None else int(max_depth)
    if not 1 <= depth <= 64:
        raise ValueError(f"max_depth must be in 1..64, got {max_depth!r}")
    threshold = setup.scene.settings.threshold if threshold is None else float(threshold)
    if not 0.0 <= threshold < 1.0:
        raise ValueError(f"threshold must be in [0, 1), got {threshold!r}")
    return setup, depth, threshold


def render_radiance(
    scene_or_setup: RenderSetup | Scene | str | Path,
    *,
    width: int | None = None,
    height: int | None = None,
    max_depth: int | None = None,
    samples: int | None = None,
    mode: str = "tree",
    spp: int = 1,
    key: Array | None = None,
    features: Features | None = None,
    threshold: float | None = None,
) -> tuple[Float[np.ndarray, "h w c"], RenderStats]:
    """Linear radiance per pixel and channel (see :func:`render_scene` for the arguments):
    float64 ``[H, W, C]`` in the :mod:`jrt.spectral` convention (C wavelength samples, or
    linear sRGB), and the :class:`RenderStats`.

    The scene's :func:`renderer` (every level in one compiled program), remembered for the
    setup: a second call with the same options compiles and guesses nothing."""
    from jrt import wavefront

    setup = (scene_or_setup if isinstance(scene_or_setup, RenderSetup)
             else prepare(scene_or_setup, features=features, samples=samples))
    setup = _with(setup, samples, features)
    render = wavefront.cached_renderer(
        setup, width=width, height=height, max_depth=max_depth, spp=spp, mode=mode,
        threshold=threshold)
    radiance = render(None, key)
    return np.asarray(radiance, np.float64), render.last_stats


def renderer(scene: RenderSetup | Scene | str | Path, **options):
    """``(render, params)``: the scene's render as a pure function of its parameters,
    :func:`jrt.wavefront.renderer` (the arguments are documented there)."""
    from jrt import wavefront

    return wavefront.renderer(scene, **options)


def host_radiance(
    scene_or_setup: RenderSetup | Scene | str | Path,
    *,
    width: int | None = None,
    height: int | None = None,
    max_depth: int | None = None,
    samples: int | None = None,
    mode: str = "tree",
    spp: int = 1,
    key: Array | None = None,
    chunk: int = CHUNK,
    features: Features | None = None,
    threshold: float | None = None,
    by_depth: bool = False,
) -> tuple[Float[np.ndarray, "h w c"] | Float[np.ndarray, "d h w c"], RenderStats]:
    """The reference tree, stepped level by level from the host (NumPy compaction and
    accumulation in float64 between levels, every camera ray per wavelength sample): what
    :func:`render_radiance` computes, by an independent route, and the tests compare it
    with. Slower (one device round trip per level and per ``chunk`` rays).

    Returns float64 ``[H, W, C]``, or with ``by_depth`` ``[D, H, W, C]``: entry ``d`` the
    image rendered at depth ``d + 1`` (levels ``0..d``), and the :class:`RenderStats`.
    """
    start = time.perf_counter()
    chunk = _check_chunk(chunk)
    setup, depth, threshold = render_arguments(
        scene_or_setup, max_depth=max_depth, samples=samples, mode=mode, spp=spp,
        features=features, threshold=threshold)
    camera = setup.camera(width, height)
    if key is None:
        key = jax.random.PRNGKey(0)
    timing: dict = {}
    rays = camera_level(setup, camera, spp, mode=mode)
    camera_rays_count = len(rays)
    pixels, c = camera.num_rays, setup.channels
    radiance = np.zeros((pixels, c), np.float64)
    snapshots = []
    per_level, shadow_rays, dropped, truncated = [], 0, 0.0, 0.0
    k = setup.ray_channels
    for level in range(depth):
        if len(rays) == 0:
            per_level.append(0)
            if by_depth:
                snapshots.append(radiance.copy())
            continue
        per_level.append(len(rays))
        result = shade_level(setup, rays, mode=mode, key=jax.random.fold_in(key, level),
                             chunk=chunk, _timing=timing)
        shadow_rays += result.shadow_rays
        _accumulate(radiance, rays, result.contributions, setup.spectral)
        if by_depth:
            snapshots.append(radiance.copy())
        children = result.children
        strength = children.weights.max(axis=1) if len(children) else np.zeros(0)
        if level == depth - 1:  # past the maximum depth: black
            truncated += float(children.weights.sum()) / k
            rays = _empty_rays(k)
            break
        keep = strength >= threshold
        dropped += float(children.weights[~keep].sum()) / k
        rays = children.take(np.flatnonzero(keep))
    per_level += [0] * (depth - len(per_level))
    radiance /= spp
    shape = (camera.height, camera.width, c)
    out = (np.stack(snapshots) / spp).reshape(-1, *shape) if by_depth else radiance.reshape(shape)
    stats = RenderStats(
        width=camera.width, height=camera.height, mode=mode, channels=c, spp=spp,
        max_depth=depth, rays_per_level=tuple(per_level), shadow_rays=shadow_rays,
        seconds=time.perf_counter() - start, compile_seconds=timing.get("compile", 0.0),
        dropped_weight=dropped, truncated_weight=truncated,
        rays_per_pixel_by_depth=tuple(r / camera_rays_count for r in per_level))
    return out, stats


def to_srgb(radiance: Float[np.ndarray, "*batch c"], setup: RenderSetup) -> np.ndarray:
    """Encoded sRGB float32 [..., 3] in [0, 1] of linear radiance over the setup's channels:
    spectral mode through XYZ (:func:`jrt.spectral.spectrum_to_srgb`), RGB mode by the
    IEC 61966-2-1 curve alone (:func:`jrt.spectral.encode_srgb`)."""
    x = jnp.asarray(radiance, jnp.float32)
    if setup.spectral:
        return np.asarray(spectrum_to_srgb(x, setup.tables), np.float32)
    return np.asarray(encode_srgb(x), np.float32)


def render_scene(
    scene_or_setup: RenderSetup | Scene | str | Path,
    *,
    width: int | None = None,
    height: int | None = None,
    max_depth: int | None = None,
    samples: int | None = None,
    mode: str = "tree",
    spp: int = 1,
    key: Array | None = None,
    features: Features | None = None,
    threshold: float | None = None,
) -> tuple[Float[np.ndarray, "h w 3"], RenderStats]:
    """Render a scene with the Whitted tree (or its sampled variant).

    Args:
        scene_or_setup: a :class:`RenderSetup` (from :func:`prepare`), a :class:`Scene`,
            a built-in scene name or a TOML path.
        width, height: image size; default the scene's camera.
        max_depth: tree levels (1: camera rays only); default the scene's features.
        samples: wavelength samples in spectral mode; default the scene's settings.
        mode: ``"tree"`` (every branch, Fresnel-weighted) or ``"sampled"`` (one branch per
            dielectric hit, reflected with probability R).
        spp: camera rays per pixel: in the tree at stratified sub-pixel positions
            (:func:`jrt.camera.subpixel_offsets`: anti-aliasing), in the sampled mode
            paths through the pixel's centre.
        key: ``jax.random`` key for the sampled mode (default ``PRNGKey(0)``).
        features: force what gets compiled (default: the scene's own features).
        threshold: pruning threshold on a ray's weight; default the scene's settings.

    Returns:
        ``(image, stats)``: float32 [H, W, 3] encoded sRGB in [0, 1], and
        :class:`RenderStats`.
    """
    setup = (scene_or_setup if isinstance(scene_or_setup, RenderSetup)
             else prepare(scene_or_setup, features=features, samples=samples))
    setup = _with(setup, samples, features)
    radiance, stats = render_radiance(
        setup, width=width, height=height, max_depth=max_depth, mode=mode, spp=spp, key=key,
        threshold=threshold)
    start = time.perf_counter()
    image = to_srgb(radiance, setup)
    return image, dataclasses.replace(stats, seconds=stats.seconds + time.perf_counter() - start)


def chunk_program(setup: RenderSetup, *, mode: str = "tree", chunk: int = 1024) -> str:
    """The jaxpr of the level function for this setup, as text: what a render compiles."""
    _check_mode(mode)
    rays = camera_level(setup, setup.camera(4, 4))
    args, _ = _chunk_args(setup, rays, 0, _check_chunk(chunk), jax.random.PRNGKey(0))
    fn = functools.partial(_shade_chunk.__wrapped__, static=_static(setup, mode))
    return str(jax.make_jaxpr(fn)(*args))


__all__ = [
    "CHUNK",
    "KIND_CODES",
    "MODES",
    "Level",
    "Rays",
    "RenderSetup",
    "RenderStats",
    "SceneArrays",
    "camera_level",
    "chunk_program",
    "host_radiance",
    "prepare",
    "render_arguments",
    "render_radiance",
    "renderer",
    "render_scene",
    "shade_level",
    "sky_rgb",
    "to_srgb",
]
