"""Batched renders: many images of one scene in one compiled program (``jax.vmap``), in
chunks sized to the memory at hand, the batch split over every local device.

    setup = prepare(load_scene("glass-camel"))
    images, stats = render_batch(setup, cameras=turntable(setup, 36, width=320, height=240))
    setup, scenes = prepare_sweep(load_scene("glass-camel"), "glass.B=0.002:0.02:8")
    radiance, stats = render_batch(setup, scenes=scenes)          # [8, H, W, C], linear
    radiance, stats = render_batch(setup, bands=[[400, 500], [500, 600], [600, 700]])
    srgb = batch_to_srgb(radiance, setup)                         # [B, H, W, 3]

**Why batch.** A turntable, a sweep of the glass's Cauchy B or a set of wavelength bands are
many renders of the *same geometry and structure* whose inputs differ only in small arrays:
the camera rays, a few material numbers, the channel tables. Rendering them one by one pays
per-call and per-level costs (dispatch, padding, host work, and the engine's loop, some 80
XLA kernels per iteration whatever the lane count) once per image. Here every batch item is
an axis of one ``jax.vmap`` of the renderer's level function (:func:`jrt.whitted._shade_chunk`,
its Python function under ``__wrapped__``): item ``b`` of a call shades chunk ``j`` of its
own level's rays with its own :class:`jrt.whitted.SceneArrays` leaves (materials, lamps,
sky, channel tables: a few hundred bytes); the geometry leaves and the structure are shared
(``in_axes=None``) and stored once. One compiled program serves the whole batch, every level
and every chunk, and the same program serves a turntable, a sweep or a set of bands of the
same sizes.

**The traversal is not vmapped.** The two ray queries (:func:`jrt.closest_hit`,
:func:`jrt.occluded`) batch natively (their ``custom_vmap`` rule in :mod:`jrt.trace` lays
the items' rays end to end and traces them in *one* unbatched engine call): vmapping the
engine's loop would turn its conditionals into selects that compute both sides (measured
10x slower). Every ray gets the same hit as in a single render.

**What may vary per item** (any combination, all of one length B):

* ``cameras``: :class:`jrt.Camera` s of one image size (e.g. :func:`turntable`);
* ``scenes``: variants of the setup's scene that differ in material parameters (e.g.
  :func:`sweep_scenes`: a glass's index or Cauchy A, B, a diffuse albedo, a mirror's
  reflectance) or the ambient share: same objects, floor, lamps, material names and kinds,
  kernel, background and Fresnel model (those decide the geometry and what is compiled);
* ``bands``: wavelength bands ``[lo, hi]`` nm (spectral scenes): item ``b`` samples its own
  band with the setup's sample count (:func:`band_setup` gives the equal single render).

Each item is exactly the render :func:`jrt.whitted.render_radiance` gives for that camera,
scene and tables (tree mode): the host side of a level (accumulation by pixel, children in
parent order, pruning by weight, the depth cut) is the same code path item by item, and the
device side the same function, vmapped. The tests check equality with a Python loop of
single renders to float32 rounding, 1e-5 of the peak (at the same chunk size: XLA compiles
the level function for a different shape, and for very small ones, 128 rays a device,
float32 rounding in the shading can differ by a few ulps, in single renders as much as
here; on an AVX2 host 2 of 1,728 values of a test frame moved by 1e-6 of the peak).

**Memory stays bounded.** A call holds ``items × chunk`` rays; both come from a byte budget
(:func:`memory_budget`: a share of the free memory of the accelerators where
``device.memory_stats()`` reports it, and of the host's available RAM), see
:func:`plan_batch`: first as many items per call as fit (all of them when they do) with a
chunk as large as a level-0 image (at most :data:`jrt.whitted.CHUNK`), then, when that does
not fit, smaller chunks down to :data:`MIN_CHUNK`. After compiling, the program's own
``memory_analysis()`` is checked against the budget and the chunk halved while it is over.
Items are rendered in groups of ``items`` (all their levels, then the next group), so the
host holds the rays of one group only: the batch size never decides whether a render fits,
only how many calls it takes.

**Devices.** The items of a call are split over ``jax.local_devices()`` with a
:class:`jax.sharding.Mesh` (axis ``"batch"``) and :class:`jax.sharding.NamedSharding`:
batched inputs, the shading and every output are sharded along the batch axis, the shared
arrays replicated; a group is padded with empty items (all rays padding) to a multiple of
the device count. One code path for one device or many. The traversal inside splits the
call's rays (all items') over the same devices with the engine's own ``shard_map``, as for a
single render; XLA moves the rays between the two layouts. Beyond one machine, see
:func:`process_items` and the README: each process of a ``jax.distributed`` job renders its
share of the batch on its own devices.

Only the tree mode is batched: the sampled mode's random branches depend on the chunk
layout, so a batch could not equal the single renders.
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

from jrt import whitted
from jrt.camera import Camera
from jrt.scene import CAUCHY_B_RANGE, INDEX_RANGE, Features, Material, Scene, load_scene
from jrt.spectral import spectral_tables, spectrum_to_srgb
from jrt.whitted import Rays, RenderSetup, SceneArrays

#: The smallest chunk (rays per item and call): below it a call is all overhead.
MIN_CHUNK = 256
#: Device bytes per ray of a call, an upper bound. ``memory_analysis()`` of the batched
#: level function (glass and diffuse camels, one lamp, 2 XLA:CPU devices, jax 0.10.2)
#: measured 240-250 B/ray of temporaries and outputs past a fixed part, and 40 B/ray of
#: inputs; about three times that covers other scenes and backends (and the compiled
#: program's own figure is checked against the budget after compiling).
RAY_BYTES = 1024
#: Extra device bytes per ray and lamp (the [N, L, 3] shadow-ray arrays).
LAMP_RAY_BYTES = 128
#: Device bytes of a call besides its rays: the traversal engine's persistent lanes and
#: their stacks (measured 4.6 MB with 2 devices of 2048 lanes each), with room for more.
CALL_BYTES = 16 << 20
#: Host bytes per camera ray of an item held during its render (each level's rays, the
#: level's outputs, children before pruning, the radiance in float64).
HOST_RAY_BYTES = 256
#: Shares of the free memory a batch may plan for: of the host's RAM (CPU backend, and the
#: host side of any backend) and of the accelerators' memory.
HOST_FRACTION = 0.25
DEVICE_FRACTION = 0.5

#: Scalar fields a sweep can vary, per material kind.
SWEEP_FIELDS = {"dielectric": ("index", "A", "B"), "diffuse": ("albedo",),
                "mirror": ("reflectance",)}
_SWEEP_SPEC = "MATERIAL.FIELD=START:STOP:N (e.g. glass.B=0.002:0.02:8)"


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
    """How a batch is cut: ``items`` per call (a multiple of ``devices``), ``chunk`` rays per
    item and call; ``bytes`` the planned memory of a group (device and host together)."""

    items: int
    chunk: int
    devices: int
    budget: int
    bytes: int


def _pow2_floor(n: int) -> int:
    return 1 << (max(1, int(n)).bit_length() - 1)


def _pow2_ceil(n: int) -> int:
    return 1 << max(0, int(n) - 1).bit_length()


def plan_batch(batch: int, rays_per_item: int, *, memory_bytes: int, devices: int = 1,
               lamps: int = 0) -> BatchPlan:
    """Items per call and rays per item and call for a batch of ``batch`` items of
    ``rays_per_item`` camera rays each within ``memory_bytes``.

    Why this order: a call's cost is dominated by the engine's loop, whose passes cost
    about the same for few rays as for many, so the plan first fits as many items as it
    can at a chunk of a whole level-0 image (powers of two, at most
    :data:`jrt.whitted.CHUNK`; fewer distinct shapes, fewer compiles), rounds that down to a
    multiple of ``devices`` (the sharding needs equal shares; at least one item a device),
    and only when that does not fit halves the chunk, down to :data:`MIN_CHUNK`. A budget
    below one call of ``devices`` items of :data:`MIN_CHUNK` rays cannot be met by
    chunking and gets that smallest call.
    """
    for name, value in (("batch", batch), ("rays_per_item", rays_per_item),
                        ("memory_bytes", memory_bytes), ("devices", devices)):
        if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < 1:
            raise ValueError(f"{name} must be a positive integer, got {value!r}")
    ray_bytes = RAY_BYTES + LAMP_RAY_BYTES * int(lamps)
    host = int(rays_per_item) * HOST_RAY_BYTES

    def cost(items, chunk):
        return CALL_BYTES + items * (chunk * ray_bytes + host)

    chunk = min(max(_pow2_ceil(rays_per_item), MIN_CHUNK), whitted.CHUNK)
    per_item = chunk * ray_bytes + host
    items = int(min(batch, max(1, (memory_bytes - CALL_BYTES) // per_item)))
    # Equal shares per device: down to a multiple of the devices, or up to one item each.
    items = max(devices, items // devices * devices)
    while chunk > MIN_CHUNK and cost(items, chunk) > memory_bytes:
        chunk //= 2
    return BatchPlan(items=items, chunk=chunk, devices=int(devices), budget=int(memory_bytes),
                     bytes=cost(items, chunk))


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
    batch item is ``whitted.render_radiance(with_camera(setup, camera))``."""
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
    sample count: what :func:`render_batch` renders for an item of ``bands``, so that
    ``whitted.render_radiance(band_setup(setup, lo, hi))`` is that item's single render.
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


@dataclasses.dataclass(frozen=True)
class BatchStats:
    """What a batched render did.

    ``rays_per_level[b]`` and ``shadow_rays[b]``: item b's rays, as
    :class:`jrt.whitted.RenderStats` counts them. ``seconds``: the whole batch, compile
    included; ``compile_seconds`` the part spent compiling. ``items_per_call`` and
    ``chunk``: the :class:`BatchPlan` used (after the memory check); ``calls``: compiled
    calls made. ``devices``: the local devices the batch was split over; ``placement``:
    ``(device id, first item, stop)`` of every shard of the last call's output, the proof of
    the split.
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
    chunk: int
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
                f"images/s; {self.items_per_call} items x {self.chunk:,} rays a call, "
                f"{self.calls} calls, {self.devices} device(s)")


#: Compiled batched level functions, keyed by static arguments, batch axes and shapes.
_COMPILED: dict = {}


def _batched_level(static, axes: SceneArrays):
    """The level function vmapped over items: per-item rays (axis 0) and the SceneArrays
    leaves marked 0 in ``axes``; the structure and the key shared."""
    level = whitted._shade_chunk.__wrapped__  # un-jitted: the program is this one

    def one(structure, arrays, origins, directions, weights, channels, valid, key):
        return level(structure, arrays, origins, directions, weights, channels, valid, key,
                     static=static)

    return jax.vmap(one, in_axes=(None, axes, 0, 0, 0, 0, 0, None))


def _compile(args, static, axes, mesh: Mesh, timing: dict):
    leaves, treedef = jax.tree.flatten(args)
    signature = (static, tuple(a is not None for a in axes), treedef,
                 tuple(d.id for d in mesh.devices.flat),
                 tuple((np.shape(x), str(x.dtype)) for x in leaves))
    exe = _COMPILED.get(signature)
    if exe is None:
        start = time.perf_counter()
        batch = NamedSharding(mesh, PartitionSpec("batch"))
        exe = jax.jit(_batched_level(static, axes), out_shardings=batch).lower(*args).compile()
        timing["compile"] = timing.get("compile", 0.0) + time.perf_counter() - start
        _COMPILED[signature] = exe
    return exe


def _measured_bytes(exe, devices: int) -> int | None:
    """The compiled program's own memory (per device, times the devices), if reported."""
    try:
        m = exe.memory_analysis()
        per = m.temp_size_in_bytes + m.output_size_in_bytes + m.argument_size_in_bytes
    except Exception:  # noqa: BLE001  (not every backend reports it)
        return None
    return int(per) * devices


#: SceneArrays leaves that hold the geometry: the same in every item (never batched).
GEOMETRY_FIELDS = ("vertices", "faces", "normals", "material")


def _stack_arrays(items: list[SceneArrays]) -> tuple[SceneArrays, SceneArrays]:
    """(arrays, axes): the geometry leaves once (axis None), every other leaf (materials,
    lamps, sky, channel tables: a few hundred bytes an item) stacked on a leading item axis
    (axis 0), whether it varies or not, so that a turntable, a sweep and a set of bands
    share one compiled program."""
    fields, axes = [], []
    for name, values in zip(SceneArrays._fields, zip(*items, strict=True), strict=True):
        if name in GEOMETRY_FIELDS:
            fields.append(values[0])
            axes.append(None)
        else:
            fields.append(np.stack([np.asarray(v) for v in values]))
            axes.append(0)
    return SceneArrays(*fields), SceneArrays(*axes)


def _level_of(rays: Rays, parts: list, k: int) -> whitted.Level:
    """A :class:`jrt.whitted.Level` from one item's chunk outputs, as shade_level builds it."""
    return whitted.level_from_chunks(parts, rays, k)


def _chunk_inputs(rays: list[Rays], start: int, chunk: int, k: int):
    """Item-stacked padded chunk ``[start, start + chunk)`` of each item's rays (NumPy), the
    padding as in ``jrt.whitted._chunk_args`` (unit directions, invalid)."""
    p = len(rays)
    origins = np.zeros((p, chunk, 3), np.float32)
    directions = np.tile(np.float32([0, 0, 1]), (p, chunk, 1))
    weights = np.zeros((p, chunk, k), np.float32)
    channels = np.zeros((p, chunk), np.int32)
    valid = np.zeros((p, chunk), bool)
    counts = []
    for i, r in enumerate(rays):
        m = max(0, min(chunk, len(r) - start))
        counts.append(m)
        if m:
            s = slice(start, start + m)
            origins[i, :m] = r.origins[s]
            directions[i, :m] = r.directions[s]
            weights[i, :m] = r.weights[s]
            channels[i, :m] = r.channels[s]
            valid[i, :m] = True
    return (origins, directions, weights, channels, valid), counts


def _collect(out, counts: list[int], parts: list[list]) -> tuple[tuple[int, int, int], ...]:
    """Fetch one call's outputs and append item i's first ``counts[i]`` rows to
    ``parts[i]`` (padding items have no part); returns the outputs' placement
    ``(device id, first item, stop)`` per shard."""
    items = out.contributions.shape[0]
    placement = tuple((s.device.id, s.index[0].start or 0, s.index[0].stop or items)
                      for s in out.contributions.addressable_shards)
    out = jax.device_get(out)
    for i, (m, part) in enumerate(zip(counts, parts, strict=False)):
        if m:
            part.append(whitted._ChunkOut(
                *(x[i][:m] if j < 9 else int(x[i]) for j, x in enumerate(out))))
    return placement


class _Item:
    """One batch item's host state through the levels (as render_radiance keeps it)."""

    def __init__(self, rays: Rays, pixels: int, channels: int):
        self.rays = rays
        self.radiance = np.zeros((pixels, channels), np.float64)
        self.per_level: list[int] = []
        self.shadow_rays = 0


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
        max_depth, threshold: as :func:`jrt.whitted.render_radiance` (default the setup's).
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
        raise ValueError("a batch needs at least one item, got empty "
                         + ", ".join(given))
    depth = setup.features.max_depth if max_depth is None else max_depth
    if isinstance(depth, bool) or not isinstance(depth, int | np.integer) or not 1 <= depth <= 64:
        raise ValueError(f"max_depth must be an integer in 1..64, got {max_depth!r}")
    threshold = setup.scene.settings.threshold if threshold is None else float(threshold)
    if not 0.0 <= threshold < 1.0:
        raise ValueError(f"threshold must be in [0, 1), got {threshold!r}")
    devices = list(jax.local_devices())
    budget = memory_budget(devices) if memory_bytes is None else memory_bytes
    if isinstance(budget, bool) or not isinstance(budget, int | np.integer) or budget < 1:
        raise ValueError(f"memory_bytes must be a positive integer (bytes), got {budget!r}")

    # Per item: camera and SceneArrays.
    if cameras is None:
        cameras = [setup.camera(width, height)] * batch
    if scenes is not None:
        for i, s in enumerate(scenes):
            _check_variant(setup, s, i)
    arrays = []
    for i in range(batch):
        if scenes is None and bands is None:
            arrays.append(setup.arrays)
            continue
        scene = setup.scene if scenes is None else scenes[i]
        tables = setup.tables
        if bands is not None:
            lo, hi = (float(x) for x in bands[i])
            try:
                tables = spectral_tables(setup.tables.samples, _lamp_spectrum(setup.scene),
                                         lo, hi)
            except ValueError as exc:
                raise ValueError(f"bands[{i}] = [{lo:g}, {hi:g}] nm: {exc}") from None
        geometry = dataclasses.replace(setup.geometry, materials=scene.materials)
        arrays.append(whitted._scene_arrays(scene, geometry, tables, setup.spectral))
    stacked, axes = _stack_arrays(arrays)

    static = whitted._static(setup, "tree")
    k, c = setup.ray_channels, setup.channels
    camera0 = cameras[0]
    pixels = camera0.num_rays
    rays0 = pixels * (c if setup.spectral else 1)
    plan = plan_batch(batch, rays0, memory_bytes=int(budget), devices=len(devices),
                      lamps=setup.features.lamps)
    mesh = Mesh(np.asarray(devices), ("batch",))
    shared = NamedSharding(mesh, PartitionSpec())
    split = NamedSharding(mesh, PartitionSpec("batch"))
    structure = jax.device_put(setup.device_structure, shared)
    key = jax.device_put(jax.random.PRNGKey(0), shared)
    host_group = plan.items * rays0 * HOST_RAY_BYTES
    timing: dict = {}
    items_per_call, chunk = plan.items, plan.chunk

    def group_arrays(indices):
        fields = [(jax.device_put(v[np.asarray(indices)], split) if a is not None
                   else jax.device_put(v, shared)) for v, a in zip(stacked, axes, strict=True)]
        return SceneArrays(*fields)

    def call_args(arrays_dev, host_inputs):
        return (structure, arrays_dev, *(jax.device_put(x, split) for x in host_inputs), key)

    # Compile once, and shrink the chunk while the program's own memory is over the budget.
    probe = group_arrays([0] * items_per_call)
    while True:
        dummy = [whitted._empty_rays(k)] * items_per_call
        exe = _compile(call_args(probe, _chunk_inputs(dummy, 0, chunk, k)[0]), static, axes,
                       mesh, timing)
        measured = _measured_bytes(exe, len(devices))
        if measured is None or measured + host_group <= budget or chunk <= MIN_CHUNK:
            break
        chunk //= 2
    call_bytes = measured if measured is not None else plan.bytes - host_group

    results: list[_Item] = []
    calls = 0
    placement: tuple = ()
    for first in range(0, batch, items_per_call):
        real = list(range(first, min(first + items_per_call, batch)))
        indices = real + [real[0]] * (items_per_call - len(real))  # padding items
        arrays_dev = group_arrays(indices)
        group = [_Item(whitted.camera_level(setup, cameras[i]), pixels, c) for i in real]
        empty = [whitted._empty_rays(k)] * (items_per_call - len(real))
        for level in range(depth):
            rays = [g.rays for g in group]
            longest = max(len(r) for r in rays)
            for g in group:
                g.per_level.append(len(g.rays))
            if longest == 0:
                continue
            parts: list[list] = [[] for _ in group]
            # Two calls in flight: the next chunk is laid out and dispatched while the
            # device still works on the last one (JAX dispatches asynchronously).
            pending = None
            for begin in range(0, longest, chunk):
                inputs, counts = _chunk_inputs(rays + empty, begin, chunk, k)
                out = exe(*call_args(arrays_dev, inputs))
                calls += 1
                if pending is not None:
                    placement = _collect(*pending, parts)
                pending = (out, counts)
            placement = _collect(*pending, parts)
            for g, r, p in zip(group, rays, parts, strict=True):
                result = _level_of(r, p, k)
                g.shadow_rays += result.shadow_rays
                whitted._accumulate(g.radiance, r, result.contributions, setup.spectral)
                children = result.children
                if level == depth - 1 or not len(children):
                    g.rays = whitted._empty_rays(k)
                    continue
                keep = children.weights.max(axis=1) >= threshold
                g.rays = children.take(np.flatnonzero(keep))
        results.extend(group)

    shape = (camera0.height, camera0.width, c)
    radiance = np.stack([g.radiance.reshape(shape) for g in results])
    stats = BatchStats(
        batch=batch, width=camera0.width, height=camera0.height, channels=c, max_depth=depth,
        rays_per_level=tuple(tuple(g.per_level) for g in results),
        shadow_rays=tuple(g.shadow_rays for g in results),
        seconds=time.perf_counter() - start, compile_seconds=timing.get("compile", 0.0),
        items_per_call=items_per_call, chunk=chunk, calls=calls, devices=len(devices),
        memory_budget=int(budget), call_bytes=int(call_bytes), placement=placement)
    return radiance, stats


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
    "DEVICE_FRACTION",
    "HOST_FRACTION",
    "MIN_CHUNK",
    "SWEEP_FIELDS",
    "BatchPlan",
    "BatchStats",
    "Sweep",
    "band_setup",
    "batch_to_srgb",
    "covering_features",
    "device_memory",
    "host_memory",
    "memory_budget",
    "parse_sweep",
    "plan_batch",
    "prepare_sweep",
    "process_items",
    "render_batch",
    "sweep_scenes",
    "turntable",
    "with_camera",
]

