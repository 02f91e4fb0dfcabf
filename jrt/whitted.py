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

* **miss**: adds ``w × background`` (``"black"``: 0; ``"sky"``: :func:`jrt.sky.sky_rgb`, a
  vertical gradient over the ray's *direction*, zenith :data:`jrt.sky.SKY_TOP` to nadir
  :data:`jrt.sky.SKY_BOTTOM`, turned into the channels as a reflectance lit by the lamp
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
Both come, with the hit point, from :func:`jrt.interaction.surface_interaction`.

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
:func:`jrt.host_tree.host_radiance` (also ``jrt.whitted.host_radiance``) is the same tree
stepped from the host, one level and one :data:`CHUNK` of rays per device call, NumPy
compaction between levels and every camera ray per wavelength sample: slower, and an
independent route the tests compare the renderer with (and it can return the image at every
depth, ``by_depth=True``: a render at depth ``d`` is exactly the sum of levels ``0..d-1`` of
any deeper render).

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
new ray goes to, each coordinate then rounded away with ``nextafter``
(:mod:`jrt.interaction`). The offset scales with the coordinates, not with a scene size.
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
from jrt.camera import Camera
from jrt.interaction import normalise, offset_ray_origin, surface_interaction
from jrt.kernels import dot
from jrt.scene import Features, Scene, SceneGeometry, assemble, load_scene
from jrt.sky import SKY_BOTTOM, SKY_TOP, direction_weight, sky_blend, sky_rgb
from jrt.spectral import (
    SpectralTables,
    encode_srgb,
    rgb_tables,
    rgb_to_reflectance,
    spectral_tables,
    spectrum_to_srgb,
)
from jrt.trace import query_status

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
    # Loops of static length (jrt.wavefront.renderer(..., differentiable=True)): every
    # level slot and every chunk of a level in a scan, the empty ones skipped by a cond,
    # so that reverse mode (jax.grad) can run them backwards; JAX cannot reverse a loop
    # whose trip count is a value.
    differentiable: bool = False


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
    # The hit point from the barycentrics, not o + t d, its error bound and its normals
    # (pbrt-v4 §6.8.5, Triangle::InteractionFromIntersection).
    surface = surface_interaction(scene.vertices, scene.faces, hits.triangle, hits.u, hits.v,
                                  directions, scene.normals)
    point, error, entering = surface.point, surface.error, surface.entering
    # Both normals facing the ray: the winding's outward ones when it enters.
    ng = jnp.where(entering[:, None], surface.geometric_normal, -surface.geometric_normal)
    ns = jnp.where(entering[:, None], surface.shading_normal, -surface.shading_normal)
    mat = scene.material[jnp.maximum(hits.triangle, 0)]
    kind = jnp.where(hit, scene.kind[mat], MISS)

    contrib = jnp.zeros((n, k), jnp.float32)
    shadow_count = jnp.zeros((), jnp.int32)
    if static.sky:
        # jrt.sky's gradient, its two ends turned into the channels (scene.sky).
        top = _pick(jnp.broadcast_to(scene.sky[0], (n, c)), channels, per_ray)
        bottom = _pick(jnp.broadcast_to(scene.sky[1], (n, c)), channels, per_ray)
        background = sky_blend(top, bottom, direction_weight(directions)[:, None])
        contrib = contrib + jnp.where((valid & ~hit)[:, None], weights * background, 0.0)

    if f.diffuse:
        is_diffuse = kind == KIND_CODES["diffuse"]
        albedo = _pick(scene.albedo[mat], channels, per_ray)
        ambient = scene.ambient
        if f.lamps:
            n_lamps = f.lamps
            # [N, L, 3]: from the hit point to each lamp.
            to_lamp = scene.lamp_positions[None, :, :] - point[:, None, :]
            l_dir = normalise(to_lamp)
            ng_l = jnp.broadcast_to(ng[:, None, :], l_dir.shape)
            cos = jnp.maximum(dot(jnp.broadcast_to(ns[:, None, :], l_dir.shape), l_dir), 0.0)
            # Light from below the geometric surface never reaches it.
            need = is_diffuse[:, None] & (dot(ng_l, l_dir) > 0) & (cos > 0)
            start = offset_ray_origin(jnp.broadcast_to(point[:, None, :], l_dir.shape),
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
    starts = offset_ray_origin(jnp.broadcast_to(point[:, None, :], shape),
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
        # Other materials have no index (0 in the table): 1 there, whose optics are
        # computed and then discarded, so that no 1/0 enters a derivative (0 * inf would
        # make reverse mode NaN; the glass rays' values are unchanged).
        n_in = jnp.where(is_glass, n_in, 1.0)
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
# Rendering
# --------------------------------------------------------------------------------------------

def _static(setup: RenderSetup, mode: str) -> _Static:
    features = dataclasses.replace(setup.features, max_depth=0, counters=False)
    return _Static(features=features, kernel=setup.scene.settings.kernel,
                   sky=setup.scene.settings.background == "sky", sampled=mode == "sampled",
                   schlick=setup.scene.settings.fresnel == "schlick")


def _check_mode(mode: str) -> None:
    if mode not in MODES:
        raise ValueError(f"mode must be one of {', '.join(MODES)}, got {mode!r}")


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


#: The host-stepped reference tree's names, defined in :mod:`jrt.host_tree` (which imports
#: this module) and reached from here too: ``jrt.whitted.host_radiance``.
_HOST_TREE = frozenset({"Level", "Rays", "camera_level", "chunk_program", "host_radiance",
                        "level_from_chunks", "shade_level"})


def __getattr__(name: str):
    if name in _HOST_TREE:
        from jrt import host_tree

        return getattr(host_tree, name)
    raise AttributeError(f"module 'jrt.whitted' has no attribute {name!r}")


__all__ = [
    "CHUNK",
    "KIND_CODES",
    "MODES",
    "RenderSetup",
    "RenderStats",
    "SceneArrays",
    "prepare",
    "render_arguments",
    "render_radiance",
    "renderer",
    "render_scene",
    "sky_rgb",
    "to_srgb",
]
