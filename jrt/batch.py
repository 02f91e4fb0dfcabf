"""Batched renders: many images of one scene in one compiled program, ``jax.vmap`` of the
pure Whitted renderer, the batch split over every local device.

    setup = prepare(load_scene("glass-camel"))
    images, stats = render_batch(setup, cameras=turntable(setup, 36, width=320, height=240))
    setup, scenes = prepare_sweep(load_scene("glass-camel"), "glass.B=0.002:0.02:8")
    radiance, stats = render_batch(setup, scenes=scenes)          # [8, H, W, C], linear
    radiance, stats = render_batch(setup, bands=[[400, 500], [500, 600], [600, 700]])
    srgb = batch_to_srgb(radiance, setup)                         # [B, H, W, 3]

A turntable, a material sweep and a set of wavelength bands are renders of the *same
geometry and structure* whose inputs differ in small arrays. :func:`jrt.wavefront.renderer`
renders a scene as a pure function of its parameters (:func:`jrt.params.scene_parameters`:
camera, material values, lamps, ambient) and its :class:`jrt.params.SceneConstants`
(geometry, channel tables, lamp spectra, sky). :func:`render_batch` stacks the items'
parameter pytrees and the per-item constants (tables, lamp spectra, sky: a few hundred
bytes; the geometry and the structure are shared, ``in_axes=None``) and calls
``jax.vmap`` of the renderer's tree program (:func:`jrt.wavefront._tree_program`), every
level of every item in one call. Every leaf is stacked whether it varies or not, so a
turntable, a sweep and a set of bands of the same sizes share one compiled program. The
ray queries are not vmapped into selects: their ``custom_vmap`` rule (:mod:`jrt.trace`)
traces all items' rays end to end in one engine call.

What may vary per item (any combination, all of one length B): ``cameras`` of one image
size (:func:`turntable`), written into ``params["camera"]``; ``scenes``, variants of the
setup's scene in material values or the ambient share (:func:`sweep_scenes`), written
into a copy of the setup's parameters (:func:`variant_parameters`: nothing is prepared or
built per item; what decides the geometry or the compiled program may not change);
``bands``, wavelength bands ``[lo, hi]`` nm with the setup's sample count, each item's
constants those of :func:`band_setup`.

**Each item is its single render**, ``wavefront.renderer(...)`` called with the item's
parameters: its camera rays come from the single renderer's own
:func:`jrt.wavefront._camera_rays` call (the same bits: in a glass tree an ulp of a camera
ray can become another path), and the tree is the same function, vmapped (the tests check
each item to float32 rounding). A group runs at the level capacities of the setup's
cached renderer (:func:`jrt.wavefront.cached_renderer`); when an item's ``demand``
exceeds them, the capacities grow to the group's largest demand
(:func:`jrt.wavefront.grown_capacities`, kept by the renderer) and the group renders
again; a traversal failure raises (:func:`jrt.trace.raise_on_status`).

**Memory and devices.** :func:`plan_batch` sizes a group from a byte budget
(:func:`memory_budget`: shares of the host's available RAM and of the accelerators' free
memory); the compiled program's ``memory_analysis()`` is checked against it and the group
halved while over, so the batch size decides how many calls a batch takes, never whether
it fits. A group's stacked inputs and outputs are split over ``jax.local_devices()``
along a ``"batch"`` :class:`jax.sharding.Mesh` axis (:class:`jax.sharding.NamedSharding`),
the shared arrays replicated; a group is padded to its size (a multiple of the device
count) with copies of its first item, dropped after. Beyond one machine see
:func:`process_items`. Only the tree mode is batched.
"""

from __future__ import annotations

import dataclasses
import math
import os
import re
import time
from collections.abc import Sequence
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec
from jaxtyping import ArrayLike, Float

from jrt import wavefront, whitted
from jrt.camera import Camera
from jrt.params import SceneConstants, scene_constants
from jrt.programs import program_cache
from jrt.scene import CAUCHY_B_RANGE, INDEX_RANGE, Features, Material, Scene, load_scene
from jrt.spectral import spectral_tables, spectrum_to_srgb
from jrt.trace import raise_on_status
from jrt.whitted import RenderSetup

#: Device bytes per ray slot of an item (its level-0 plus a later level's capacity), an
#: upper bound. ``memory_analysis()`` of the vmapped tree program (glass camel, one lamp,
#: 4 wavelength samples, 2 XLA:CPU devices, jax 0.10.2) measured 300-750 B a slot past a
#: fixed 2 MB; the compiled program's own figure is checked against the budget after
#: compiling.
RAY_BYTES = 1024
#: Extra device bytes per ray slot and lamp (the shadow rays).
LAMP_RAY_BYTES = 128
#: Device bytes of a call besides its items: the engine's lanes and stacks, the geometry.
CALL_BYTES = 16 << 20
#: Host bytes per pixel and channel of an item (the float32 result and its float64 copy).
HOST_PIXEL_BYTES = 12
#: Shares of the free memory a batch may plan for: the host's RAM, the accelerators'.
HOST_FRACTION = 0.25
DEVICE_FRACTION = 0.5

#: Scalar fields a sweep can vary, per material kind.
SWEEP_FIELDS = {"dielectric": ("index", "A", "B"), "diffuse": ("albedo",),
                "mirror": ("reflectance",)}
_SWEEP_SPEC = "MATERIAL.FIELD=START:STOP:N (e.g. glass.B=0.002:0.02:8)"

#: The SceneConstants fields that differ between items (a band's tables and what is
#: computed from them); the others hold the geometry and are shared.
_ITEM_CONSTANTS = ("lamp_spectra", "sky", "tables")
_CONSTANT_AXES = SceneConstants(*(0 if name in _ITEM_CONSTANTS else None
                                  for name in SceneConstants._fields))


# --------------------------------------------------------------------------------------------
# Memory
# --------------------------------------------------------------------------------------------


def host_memory() -> int:
    """Bytes of host RAM available now (``os.sysconf``; psutil when installed)."""
    try:
        import psutil  # optional

        return int(psutil.virtual_memory().available)
    except ImportError:
        pass
    try:
        return int(os.sysconf("SC_AVPHYS_PAGES")) * int(os.sysconf("SC_PAGE_SIZE"))
    except (AttributeError, OSError, ValueError):
        return 4 << 30  # no way to ask: assume a small machine


def device_memory(device: jax.Device) -> int | None:
    """Free bytes on ``device`` (``bytes_limit - bytes_in_use`` from
    ``device.memory_stats()``), or None where the backend does not report them (CPU)."""
    try:
        stats = device.memory_stats()
    except Exception:  # noqa: BLE001  (backends without the call raise various errors)
        return None
    if not stats or "bytes_limit" not in stats:
        return None
    return max(0, int(stats["bytes_limit"]) - int(stats.get("bytes_in_use", 0)))


def memory_budget(devices: Sequence[jax.Device] | None = None) -> int:
    """Bytes a batched render may plan for: :data:`HOST_FRACTION` of the host's available
    RAM, and no more than :data:`DEVICE_FRACTION` of the devices' free memory where they
    report it (GPU, TPU). On CPU the devices are the host: its RAM is the one budget."""
    devices = list(jax.local_devices() if devices is None else devices)
    budget = int(host_memory() * HOST_FRACTION)
    free = [device_memory(d) for d in devices]
    if free and all(f is not None for f in free):
        budget = min(budget, int(sum(free) * DEVICE_FRACTION))
    return max(budget, 1)



@dataclasses.dataclass(frozen=True)
class BatchPlan:
    """How a batch is cut: ``items`` per call (a multiple of ``devices``); ``bytes`` the
    planned memory of a group (device and host together) within ``budget``."""

    items: int
    devices: int
    budget: int
    bytes: int


def plan_batch(batch: int, rays_per_item: int, *, memory_bytes: int, devices: int = 1,
               lamps: int = 0, pixels_per_item: int = 0) -> BatchPlan:
    """Items per call for a batch of ``batch`` items within ``memory_bytes``.

    ``rays_per_item``: the ray slots an item's tree holds at once (its level-0 capacity
    plus a later level's); ``pixels_per_item``: its pixels times channels (the host's
    copy). As many items as fit, in equal shares of the ``devices``: the whole batch
    padded up to whole shares when it fits, else rounded down to them, and at least one
    item a device (a budget below that smallest call gets it anyway).
    """
    for name, value in (("batch", batch), ("rays_per_item", rays_per_item),
                        ("memory_bytes", memory_bytes), ("devices", devices)):
        if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < 1:
            raise ValueError(f"{name} must be a positive integer, got {value!r}")
    per_item = (int(rays_per_item) * (RAY_BYTES + LAMP_RAY_BYTES * int(lamps))
                + int(pixels_per_item) * HOST_PIXEL_BYTES)
    items = int(min(batch, max(1, (memory_bytes - CALL_BYTES) // per_item)))
    # Equal shares per device: the whole batch padded up, else down to whole shares.
    items = (-(-items // devices) if items == batch else max(1, items // devices)) * devices
    return BatchPlan(items=items, devices=int(devices), budget=int(memory_bytes),
                     bytes=CALL_BYTES + items * per_item)


# --------------------------------------------------------------------------------------------
# What varies: cameras, materials, wavelength bands
# --------------------------------------------------------------------------------------------


def turntable(setup: RenderSetup, frames: int, *, width: int | None = None,
              height: int | None = None) -> list[Camera]:
    """``frames`` cameras around the scene camera's target: the eye turned about the
    vertical (+y, the scenes are y-up) axis through the target in steps of 360/frames
    degrees (counter-clockwise seen from above); frame 0 is the scene's own camera."""
    if isinstance(frames, bool) or not isinstance(frames, int | np.integer) or frames < 1:
        raise ValueError(f"turntable frames must be a positive integer, got {frames!r}")
    base = setup.camera(width, height)
    eye, target = np.asarray(base.eye), np.asarray(base.target)
    offset = eye - target
    cameras = [base]
    for i in range(1, int(frames)):
        a = 2 * math.pi * i / int(frames)
        c, s = math.cos(a), math.sin(a)
        # Rotation about +y: x' = c x + s z, z' = -s x + c z.
        turned = np.array([c * offset[0] + s * offset[2], offset[1],
                           -s * offset[0] + c * offset[2]])
        cameras.append(dataclasses.replace(base, eye=tuple(target + turned)))
    return cameras


def with_camera(setup: RenderSetup, camera: Camera) -> RenderSetup:
    """``setup`` looking through ``camera`` (and at its image size): the single render of a
    batch item is that of ``wavefront.renderer(with_camera(setup, camera))``."""
    if not isinstance(camera, Camera):
        raise ValueError(f"camera must be a jrt.Camera, got {type(camera).__name__}")
    spec = dataclasses.replace(setup.scene.camera, width=camera.width, height=camera.height)
    return dataclasses.replace(setup, scene=dataclasses.replace(setup.scene, camera=spec),
                               geometry=dataclasses.replace(setup.geometry, camera=camera))


@dataclasses.dataclass(frozen=True)
class Sweep:
    """A parameter sweep: ``material.field`` takes each of ``values``."""

    material: str
    field: str
    values: tuple[float, ...]

    @property
    def label(self) -> str:
        return f"{self.material}.{self.field}"


def parse_sweep(spec: str) -> Sweep:
    """``"glass.B=0.002:0.02:8"`` -> ``Sweep("glass", "B", 8 values linearly spaced from
    0.002 to 0.02)`` (both ends included; n = 1 gives START alone). Checks the form and
    the numbers only; :func:`sweep_scenes` checks the material and field against a scene."""
    if not isinstance(spec, str):
        raise ValueError(f"a sweep is a string {_SWEEP_SPEC}, got {spec!r}")
    match = re.fullmatch(r"\s*([^=\s]+)\.([^.=\s]+)\s*=\s*([^:]+):([^:]+):([^:]+)\s*", spec)
    if match is None:
        raise ValueError(f"sweep {spec!r} is malformed: expected {_SWEEP_SPEC}")
    material, field, start, stop, count = match.groups()
    numbers = []
    for what, text in (("START", start), ("STOP", stop)):
        try:
            value = float(text)
        except ValueError:
            raise ValueError(f"sweep {spec!r}: {what} {text.strip()!r} is not a number "
                             f"(expected {_SWEEP_SPEC})") from None
        if not math.isfinite(value):
            raise ValueError(f"sweep {spec!r}: {what} must be finite, got {text.strip()!r}")
        numbers.append(value)
    try:
        n = int(count)
    except ValueError:
        raise ValueError(f"sweep {spec!r}: N {count.strip()!r} is not an integer "
                         f"(the number of values, >= 1)") from None
    if n < 1:
        raise ValueError(f"sweep {spec!r}: N must be an integer >= 1 (the number of values), "
                         f"got {n}")
    values = tuple(float(v) for v in np.linspace(numbers[0], numbers[1], n))
    return Sweep(material=material, field=field, values=values)


def _swept(mat: Material, field: str, value: float, where: str) -> Material:
    """``mat`` with ``field`` set to ``value`` (the ranges of :mod:`jrt.scene`)."""
    allowed = SWEEP_FIELDS[mat.kind]
    if field not in allowed:
        raise ValueError(f"{where}: material {mat.name!r} ({mat.kind}) has no sweepable "
                         f"field {field!r}; allowed: {', '.join(allowed)}")
    if field in ("index", "A"):
        lo, hi = INDEX_RANGE
        if not lo < value <= hi:
            raise ValueError(f"{where}: {mat.name}.{field} = {value:g} is outside ({lo:g}, "
                             f"{hi:g}]")
    elif field == "B":
        lo, hi = CAUCHY_B_RANGE
        if not lo <= value <= hi:
            raise ValueError(f"{where}: {mat.name}.B = {value:g} µm² is outside [{lo:g}, "
                             f"{hi:g}]")
    elif not 0.0 <= value <= 1.0:
        raise ValueError(f"{where}: {mat.name}.{field} = {value:g} is outside [0, 1] (a grey "
                         f"{field}: the value in all three channels)")
    a, b = mat.cauchy if mat.cauchy is not None else (mat.index, 0.0)
    if field == "index":
        return dataclasses.replace(mat, index=value, glass=None, cauchy=None)
    if field == "A":
        return dataclasses.replace(mat, index=None, glass=None, cauchy=(value, b))
    if field == "B":
        return dataclasses.replace(mat, index=None, glass=None, cauchy=(a, value))
    return dataclasses.replace(mat, **{field: (value, value, value)})


def sweep_scenes(scene: Scene, sweep: Sweep | str) -> list[Scene]:
    """One scene per value of ``sweep`` (a :class:`Sweep` or its text, see
    :func:`parse_sweep`), each ``scene`` with that material field set:

    * dielectric ``index``: a constant index in (1, 5] (the Cauchy terms dropped);
    * dielectric ``A``, ``B``: Cauchy's ``n(λ) = A + B/λ²`` (λ in µm, B in µm² in [0, 1]),
      the other term kept (a constant index is ``A = index, B = 0``);
    * diffuse ``albedo``, mirror ``reflectance``: a grey, the value in all three channels.

    Raises ValueError naming the material (with the scene's materials) or the field (with
    the fields allowed for that kind) or a value out of range.
    """
    if isinstance(sweep, str):
        sweep = parse_sweep(sweep)
    names = [m.name for m in scene.materials]
    if sweep.material not in names:
        raise ValueError(f"sweep {sweep.label}: scene {scene.name!r} has no material "
                         f"{sweep.material!r}; its materials: {', '.join(names)}")
    index = names.index(sweep.material)
    out = []
    for value in sweep.values:
        mat = _swept(scene.materials[index], sweep.field, float(value), f"sweep {sweep.label}")
        materials = scene.materials[:index] + (mat,) + scene.materials[index + 1:]
        out.append(dataclasses.replace(scene, materials=materials))
    return out


def covering_features(scenes: Sequence[Scene]) -> Features:
    """The features that compile every scene of ``scenes`` (variants of one scene): the
    first scene's, with dispersion when any has it (a scene without dispersion renders
    spectrally to the same image, at the cost of its samples)."""
    if not scenes:
        raise ValueError("covering_features needs at least one scene")
    first = scenes[0].features()
    return dataclasses.replace(first, dispersion=any(s.features().dispersion for s in scenes))


def prepare_sweep(scene: Scene | str | Path, sweep: Sweep | str, *,
                  samples: int | None = None,
                  structure=None) -> tuple[RenderSetup, list[Scene]]:
    """``(setup, scenes)`` for :func:`render_batch`: the sweep's scenes and one setup (one
    structure, built unless given) whose features cover them all
    (:func:`covering_features`). The sweep is checked before anything is built."""
    if not isinstance(scene, Scene):
        scene = load_scene(scene)
    scenes = sweep_scenes(scene, sweep)
    setup = whitted.prepare(scenes[0], features=covering_features(scenes), samples=samples,
                            structure=structure)
    return setup, scenes


def _lamp_spectrum(scene: Scene) -> str:
    return scene.lamps[0].spectrum if scene.lamps else "D65"  # as jrt.whitted._tables


def band_setup(setup: RenderSetup, lo: float, hi: float) -> RenderSetup:
    """``setup`` sampling the band ``[lo, hi]`` nm (360 <= lo < hi <= 830) with its own
    sample count: what :func:`render_batch` renders for an item of ``bands`` (its
    constants), so that ``wavefront.renderer(band_setup(setup, lo, hi))`` renders that
    item's single render.
    Each band's lamps are scaled to luminance 1 over the band, as a single render is."""
    if not setup.spectral:
        raise ValueError("wavelength bands need a spectral setup (a material with Cauchy "
                         "B != 0, or features with dispersion); this one renders in RGB")
    tables = spectral_tables(setup.tables.samples, _lamp_spectrum(setup.scene), lo, hi)
    arrays = whitted._scene_arrays(setup.scene, setup.geometry, tables, True)
    return dataclasses.replace(setup, tables=tables, arrays=arrays)


def _check_variant(setup: RenderSetup, scene: Scene, i: int) -> None:
    """A variant may change material parameters and the ambient share, nothing that moves
    the geometry or changes what is compiled."""
    if not isinstance(scene, Scene):
        raise ValueError(f"scenes[{i}] must be a jrt.scene.Scene, got {type(scene).__name__}")
    base = setup.scene
    for what in ("objects", "floor", "lamps"):
        if getattr(scene, what) != getattr(base, what):
            raise ValueError(f"scenes[{i}] ({scene.name}) changes the {what} of the setup's "
                             f"scene {base.name!r}: a batch shares its geometry and lamps; "
                             "allowed to vary: material parameters and settings.ambient")
    for what in ("kernel", "background", "fresnel", "accel"):
        mine, theirs = getattr(scene.settings, what), getattr(base.settings, what)
        if mine != theirs:
            raise ValueError(f"scenes[{i}] ({scene.name}) has settings.{what} = {mine!r}, the "
                             f"setup {theirs!r}: it decides what is compiled; make them equal")
    kinds = [(m.name, m.kind) for m in scene.materials]
    expected = [(m.name, m.kind) for m in base.materials]
    if kinds != expected:
        raise ValueError(f"scenes[{i}] ({scene.name}) has materials {kinds}, the setup "
                         f"{expected}: names and kinds must match (parameters may differ)")
    if scene.features().dispersion and not setup.spectral:
        raise ValueError(f"scenes[{i}] ({scene.name}) has dispersion (a Cauchy B != 0) but "
                         "the setup renders in RGB: prepare it with features covering every "
                         "variant (jrt.batch.covering_features, or jrt.batch.prepare_sweep)")


# --------------------------------------------------------------------------------------------
# The batch on the device
# --------------------------------------------------------------------------------------------


def camera_parameters(camera: Camera) -> dict:
    """``params["camera"]`` (:func:`jrt.params.scene_parameters`) of ``camera``."""
    return {"eye": jnp.asarray(camera.eye, jnp.float32),
            "target": jnp.asarray(camera.target, jnp.float32),
            "up": jnp.asarray(camera.up, jnp.float32),
            "vfov": jnp.asarray(camera.vfov, jnp.float32)}


def variant_parameters(params: dict, scene: Scene) -> dict:
    """A copy of ``params`` with ``scene``'s material values and ambient share written in
    (every continuous field: albedo, reflectance, index or A and B, ambient). A dielectric
    comes out as ``{"A", "B"}`` whatever its form, so that variants with and without a
    Cauchy term stack (and render the same rows as the single render's ``{"index"}``)."""
    out = jax.tree.map(lambda x: x, params)  # new containers, the same leaves
    for mat in scene.materials:
        if mat.kind == "diffuse":
            value = {"albedo": jnp.asarray(mat.albedo, jnp.float32)}
        elif mat.kind == "mirror":
            value = {"reflectance": jnp.asarray(mat.reflectance, jnp.float32)}
        else:
            a, b = mat.cauchy if mat.cauchy is not None else (mat.index, 0.0)
            value = {"A": jnp.asarray(a, jnp.float32), "B": jnp.asarray(b, jnp.float32)}
        out["materials"][mat.name] = value
    out["settings"]["ambient"] = jnp.asarray(scene.settings.ambient, jnp.float32)
    return out


@dataclasses.dataclass(frozen=True)
class BatchStats:
    """What a batched render did.

    ``rays_per_level[b]`` and ``shadow_rays[b]``: item b's rays, from its
    :class:`jrt.wavefront.TreeStats` (counted as :class:`jrt.whitted.RenderStats` counts a
    single render's). ``seconds``: the whole batch, compile included; ``compile_seconds``
    the part spent compiling. ``items_per_call``: the group size used (after the memory
    check); ``capacities``: the level capacities of the last call; ``calls``: compiled calls
    made (a group renders again after an overflow). ``devices``: the local devices the batch
    was split over; ``call_bytes``: the program's memory (measured, else planned);
    ``placement``: ``(device id, first item, stop)`` of every shard of the last call's
    output, the proof of the split.
    """

    batch: int
    width: int
    height: int
    channels: int
    max_depth: int
    rays_per_level: tuple[tuple[int, ...], ...]
    shadow_rays: tuple[int, ...]
    seconds: float
    compile_seconds: float
    items_per_call: int
    capacities: tuple[int, ...]
    calls: int
    devices: int
    memory_budget: int
    call_bytes: int
    placement: tuple[tuple[int, int, int], ...]

    @property
    def total_rays(self) -> int:
        return int(sum(sum(r) for r in self.rays_per_level) + sum(self.shadow_rays))

    @property
    def images_per_second(self) -> float:
        return self.batch / self.seconds if self.seconds > 0 else float("nan")

    def summary(self) -> str:
        return (f"{self.batch} images {self.width}x{self.height} ({self.channels} channels), "
                f"depth {self.max_depth}: {self.total_rays:,} rays in {self.seconds:.2f} s "
                f"(compile {self.compile_seconds:.2f} s), {self.images_per_second:.3f} "
                f"images/s; {self.items_per_call} items a call, {self.calls} calls, "
                f"{self.devices} device(s)")


#: Compiled batched programs and their measured bytes (None where the backend does not
#: say), keyed by the renderer's static shape, the devices and the arguments' shapes.
_COMPILED = program_cache()


def _compiled(args, shape, mesh: Mesh, timing: dict) -> tuple:
    """``(program, bytes)``: the vmapped tree program for ``args``, compiled once, and its
    own memory (``memory_analysis()``: per device, times the devices)."""
    leaves, treedef = jax.tree.flatten(args)
    signature = (shape, tuple(d.id for d in mesh.devices.flat), treedef,
                 tuple((np.shape(x), str(x.dtype)) for x in leaves))
    if signature not in _COMPILED:
        def one(params, constants, origins, directions, structure, threshold, key, depth):
            return wavefront._tree_program(params, constants, structure, threshold, key,
                                           origins, directions, depth, shape=shape)

        batched = jax.vmap(one, in_axes=(0, _CONSTANT_AXES, 0, 0, None, None, None, None))
        start = time.perf_counter()
        program = jax.jit(batched, out_shardings=NamedSharding(
            mesh, PartitionSpec("batch"))).lower(*args).compile()
        timing["compile"] = timing.get("compile", 0.0) + time.perf_counter() - start
        try:
            m = program.memory_analysis()
            measured = (m.temp_size_in_bytes + m.output_size_in_bytes
                        + m.argument_size_in_bytes) * mesh.devices.size
        except Exception:  # noqa: BLE001  (not every backend reports it)
            measured = None
        _COMPILED[signature] = program, measured
    return _COMPILED[signature]


def _stack(trees: list):
    """The pytrees ``trees`` (one structure) as one, every leaf stacked on a new axis 0."""
    return jax.tree.map(lambda *xs: np.stack([np.asarray(x) for x in xs]), *trees)


def _as_cameras(cameras, width, height) -> list[Camera] | None:
    if cameras is None:
        return None
    cameras = list(cameras)
    for i, c in enumerate(cameras):
        if not isinstance(c, Camera):
            raise ValueError(f"cameras[{i}] must be a jrt.Camera, got {type(c).__name__}")
    if width is not None or height is not None:
        cameras = [dataclasses.replace(c, width=int(width or c.width),
                                       height=int(height or c.height)) for c in cameras]
    sizes = sorted({(c.width, c.height) for c in cameras})
    if len(sizes) > 1:
        raise ValueError(f"cameras of one batch must share an image size, got "
                         f"{', '.join(f'{w}x{h}' for w, h in sizes)} (or pass width, height)")
    return cameras


def render_batch(
    setup: RenderSetup,
    *,
    cameras: Sequence[Camera] | None = None,
    scenes: Sequence[Scene] | None = None,
    bands: Float[ArrayLike, "b 2"] | None = None,
    width: int | None = None,
    height: int | None = None,
    max_depth: int | None = None,
    threshold: float | None = None,
    memory_bytes: int | None = None,
) -> tuple[Float[np.ndarray, "b h w c"], BatchStats]:
    """Linear radiance of a batch of renders of ``setup``'s geometry (tree mode).

    Args:
        setup: from :func:`jrt.whitted.prepare` (or :func:`prepare_sweep`).
        cameras: B cameras of one image size (default: the setup's camera for every item).
        scenes: B variants of ``setup.scene`` (material parameters, ambient; see the module
            doc); default the setup's scene for every item.
        bands: float [B, 2], each item's wavelength band ``[lo, hi]`` nm (spectral setups),
            sampled with the setup's sample count; default the setup's tables.
        width, height: image size; default the cameras' (or the scene camera's).
        max_depth, threshold: as :func:`jrt.wavefront.renderer` (default the setup's).
        memory_bytes: the budget for :func:`plan_batch`; default :func:`memory_budget`.

    Returns:
        ``(radiance, stats)``: float64 [B, H, W, C] (item b equal to the single render of
        its camera, scene and band, C the setup's channels) and :class:`BatchStats`.

    Raises:
        ValueError: no batch input, inputs of different lengths, cameras of different sizes,
            a variant scene that changes more than material parameters, bands for an RGB
            setup or out of 360..830 nm, bad depth, threshold or budget.
    """
    start = time.perf_counter()
    if not isinstance(setup, RenderSetup):
        raise TypeError(f"setup must be a jrt.whitted.RenderSetup (from prepare), got "
                        f"{type(setup).__name__}")
    cameras = _as_cameras(cameras, width, height)
    if scenes is not None:
        scenes = list(scenes)
    if bands is not None:
        bands = np.asarray(bands, np.float64)
        if bands.ndim != 2 or bands.shape[1] != 2:
            raise ValueError(f"bands must have shape [B, 2] (lo, hi nm per item), got "
                             f"{bands.shape}")
        if not setup.spectral:
            band_setup(setup, 400.0, 700.0)  # raises the RGB error
    given = {name: len(v) for name, v in (("cameras", cameras), ("scenes", scenes),
                                           ("bands", bands)) if v is not None}
    if not given:
        raise ValueError("a batch needs cameras, scenes or bands (each a sequence of B items)")
    if len(set(given.values())) > 1:
        raise ValueError("the batch inputs must have one length B, got "
                         + ", ".join(f"{k} {v}" for k, v in given.items()))
    batch = next(iter(given.values()))
    if batch < 1:
        raise ValueError("a batch needs at least one item, got empty " + ", ".join(given))
    devices = list(jax.local_devices())
    budget = memory_budget(devices) if memory_bytes is None else memory_bytes
    if isinstance(budget, bool) or not isinstance(budget, int | np.integer) or budget < 1:
        raise ValueError(f"memory_bytes must be a positive integer (bytes), got {budget!r}")
    if scenes is not None:
        for i, s in enumerate(scenes):
            _check_variant(setup, s, i)

    # Per item: parameters and constants (the renderer's, with the item's changes).
    camera0 = cameras[0] if cameras is not None else setup.camera(width, height)
    _, depth, threshold = whitted.render_arguments(  # checked, the scene's defaults
        setup, max_depth=max_depth, samples=None, mode="tree", spp=1, features=None,
        threshold=threshold)
    render = wavefront.cached_renderer(setup, width=camera0.width, height=camera0.height,
                                       max_depth=depth, threshold=threshold)
    base = variant_parameters(render.params, setup.scene)
    params, constants = [], []
    for i in range(batch):
        item = base if scenes is None else variant_parameters(base, scenes[i])
        if cameras is not None:
            item = {**item, "camera": camera_parameters(cameras[i])}
        params.append(item)
        if bands is not None:
            lo, hi = (float(x) for x in bands[i])
            try:
                own = scene_constants(band_setup(setup, lo, hi))
            except ValueError as exc:
                raise ValueError(f"bands[{i}] = [{lo:g}, {hi:g}] nm: {exc}") from None
        else:
            own = render._constants
        constants.append({name: getattr(own, name) for name in _ITEM_CONSTANTS})
    mesh = Mesh(np.asarray(devices), ("batch",))
    replicated = NamedSharding(mesh, PartitionSpec())
    split = NamedSharding(mesh, PartitionSpec("batch"))
    shared = jax.device_put((render._constants, setup.device_structure, render._threshold,
                             render._key, render.depth_argument), replicated)

    def call_args(indices):
        """The program's arguments for the items ``indices``, stacked and split."""
        constants_b = shared[0]._replace(  # the geometry shared, the rest per item
            **jax.device_put(_stack([constants[i] for i in indices]), split))
        # Each item's camera rays by the single renderer's own call (bit for bit its rays).
        rays = {i: wavefront._camera_rays(params[i]["camera"], render.shape())
                for i in set(indices)}
        origins, directions = (jax.device_put(np.stack([rays[i][j] for i in indices]), split)
                               for j in (0, 1))
        return (jax.device_put(_stack([params[i] for i in indices]), split), constants_b,
                origins, directions, *shared[1:])

    timing: dict = {}
    pixels = camera0.num_rays * setup.channels

    def fit(items):
        """The program for ``items`` a call at the renderer's capacities, the group halved
        (in whole shares of the devices) while its measured memory is over the budget."""
        while True:
            program, measured = _compiled(call_args([0] * items), render.shape(), mesh,
                                          timing)
            host = items * pixels * HOST_PIXEL_BYTES
            if measured is None or measured + host <= budget or items <= len(devices):
                return program, items, measured
            items = max(len(devices), items // 2 // len(devices) * len(devices))

    capacities = render.capacities
    plan = plan_batch(batch, capacities[0] + max(capacities[1:], default=0),
                      memory_bytes=int(budget), devices=len(devices),
                      lamps=setup.features.lamps, pixels_per_item=pixels)
    program, items, measured = fit(plan.items)
    images, levels, shadow = [], [], []
    calls, placement, rerenders = 0, (), 0
    while len(images) < batch:
        real = list(range(len(images), min(len(images) + items, batch)))
        radiance, stats = program(*call_args(real + [real[0]] * (items - len(real))))
        calls += 1
        host = jax.device_get(stats)
        raise_on_status(np.bitwise_or.reduce(host.status))
        worst = host.demand.max(axis=0)[:depth]
        if (worst > np.asarray(render.capacities)).any():  # grow, and render the group again
            rerenders += 1
            if rerenders > wavefront.MAX_RERENDERS:  # pragma: no cover - each fixes a level
                raise RuntimeError(f"level capacities still overflow after {rerenders} renders")
            render.capacities = wavefront.grown_capacities(render.capacities, worst)
            program, items, measured = fit(items)
            continue
        placement = tuple((s.device.id, s.index[0].start or 0, s.index[0].stop or items)
                          for s in radiance.addressable_shards)
        images.extend(np.asarray(jax.device_get(radiance)[:len(real)], np.float64))
        levels.extend(tuple(int(r) for r in row[:depth]) for row in host.rays[:len(real)])
        shadow.extend(int(r) for r in host.shadow_rays[:len(real)])

    stats = BatchStats(
        batch=batch, width=camera0.width, height=camera0.height, channels=setup.channels,
        max_depth=depth, rays_per_level=tuple(levels), shadow_rays=tuple(shadow),
        seconds=time.perf_counter() - start, compile_seconds=timing.get("compile", 0.0),
        items_per_call=items, capacities=tuple(render.capacities), calls=calls,
        devices=len(devices), memory_budget=int(budget),
        call_bytes=int(measured if measured is not None else plan.bytes), placement=placement)
    return np.stack(images), stats


def batch_to_srgb(radiance: Float[ArrayLike, "b h w c"], setup: RenderSetup,
                  bands: Float[ArrayLike, "b 2"] | None = None) -> Float[np.ndarray, "b h w 3"]:
    """Encoded sRGB float32 [B, H, W, 3] in [0, 1] of :func:`render_batch`'s radiance,
    through the setup's tables (:func:`jrt.whitted.to_srgb`), or each item's band tables."""
    radiance = np.asarray(radiance)
    if radiance.ndim != 4 or radiance.shape[-1] != setup.channels:
        raise ValueError(f"radiance must be [B, H, W, {setup.channels}], got {radiance.shape}")
    if bands is None:
        return whitted.to_srgb(radiance, setup)
    bands = np.asarray(bands, np.float64)
    if bands.shape != (radiance.shape[0], 2):
        raise ValueError(f"bands must be [{radiance.shape[0]}, 2], got {bands.shape}")
    out = []
    for r, (lo, hi) in zip(radiance, bands, strict=True):
        tables = spectral_tables(setup.tables.samples, _lamp_spectrum(setup.scene), lo, hi)
        out.append(np.asarray(spectrum_to_srgb(jnp.asarray(r, jnp.float32), tables)))
    return np.stack(out).astype(np.float32)


def process_items(count: int) -> Sequence[int]:
    """The batch items this process renders in a multi-process job (``jax.distributed``):
    items ``process_index, process_index + process_count, ...`` of ``count``. One process:
    all of them."""
    if isinstance(count, bool) or not isinstance(count, int | np.integer) or count < 0:
        raise ValueError(f"count must be a non-negative integer, got {count!r}")
    return range(jax.process_index(), int(count), jax.process_count())


__all__ = [
    "DEVICE_FRACTION", "HOST_FRACTION", "SWEEP_FIELDS", "BatchPlan", "BatchStats", "Sweep",
    "band_setup", "batch_to_srgb", "camera_parameters", "covering_features", "device_memory",
    "host_memory", "memory_budget", "parse_sweep", "plan_batch", "prepare_sweep",
    "process_items", "render_batch", "sweep_scenes", "turntable", "variant_parameters",
    "with_camera",
]
