"""The Whitted tree as one compiled program, a pure function of the scene's parameters.

    render, params = renderer("glass-camel", width=640, height=480, max_depth=8)
    radiance = render(params)                          # jnp [H, W, C], linear
    params["materials"]["glass"]["B"] = 0.01           # any continuous value of the scene
    batch = jax.vmap(render)(stacked_params)           # one program for every item

The same tree as :func:`jrt.host_tree.host_radiance` (:mod:`jrt.whitted` says what a ray
does at a surface), with every level run inside one jitted program instead of one host round
trip per level. ``params`` (:mod:`jrt.params`) holds the scene's continuous values keyed as in
its TOML; everything that changes the program (features, image size, depth, ``spp``,
kernel, structure, the level capacities) is fixed by :func:`renderer`, the jax-md habit of
a constructor that returns a pure function. The camera rays are made from
``params["camera"]`` by :func:`jrt.camera._pinhole`, the program :func:`jrt.camera_rays`
runs. In spectral mode a camera ray is a *bundle* carrying every wavelength sample
(``weights [N, C]``) to its first surface, where its children part, one ray per sample:
the camera level holds ``C`` times fewer rays (76,800 instead of 1.23M for the glass camel
at 320x240 and 16 samples), and each path is the one the host tree traces.

The levels run in one ``lax.fori_loop`` whose body is compiled once, on batches of
``max(capacities[1:])`` rays (static), up to a depth that is an argument of the program
(one program serves every depth up to :func:`level_slots`). Spectral bundles make level 0
a body of its own (``capacities[0]`` rays, weights over every sample); otherwise the camera
level runs in the loop too. The padding rays carry ``valid = False`` and ``tmax = 0``, so
they never hit and add nothing. Each level is shaded in chunks (:func:`level_chunk`:
32,768 rays on a CPU, whose cache they fit, up to a million on an accelerator, whose lanes
they fill), in a loop over the chunks that hold live rays, by
:func:`jrt.whitted._shade_chunk`, the host tree's own level function: a level costs its
rays, not its capacity. Between levels, on the device:

* **accumulation**: each ray's contribution is added into its pixel (and wavelength
  sample) by a scatter-add (``radiance.at[index].add``), float32;
* **pruning**: a child whose weight (largest channel) is below the threshold is dropped, its
  weight counted in ``dropped_weight`` exactly as on the host;
* **compaction**: the kept children of the ``[N, B]`` slots (reflected, refracted) get their
  places in the next level by a prefix sum over the slots in parent-major order (the order
  ``np.nonzero`` gives on the host: children stay beside their parents, so the next level's
  rays stay coherent), and are scattered there.

**Overflow.** When a level would hold more rays than its capacity, the rays past it are not
traced: the program reports, per level, the rays it needed (``demand``) and the weight it
could not trace (``overflow_weight``), and the traversals' status word (a stack overflow),
the jax-md habit of flags out of jit. Called outside a trace, a :class:`Renderer` checks
them: it grows its capacities to the demand and renders again (kept for the next calls), so
no ray is ever lost silently; inside ``jit``/``vmap`` the check runs as a host callback that
raises. :meth:`Renderer.trace` is the pure function for callers that handle the flags
themselves. No callback sits in the program a concrete call runs, so JAX's persistent
compilation cache stores it (:mod:`jrt.compile_cache`).

**Capacities** are rounded up to :func:`jrt.trace.bucket_size` (at most 1.5x padding), so
renders of similar scenes share compiled programs. The first guess, before any render has
measured the scene, is :func:`initial_capacities`.
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
from jaxtyping import Array, Bool, Float, Int

import accel
from jrt.params import (
    camera_from_parameters,
    check_parameters,
    scene_arrays,
    scene_constants,
    scene_parameters,
)
from jrt.programs import program_cache
from jrt.refitting import refit
from jrt.scene import Scene
from jrt.trace import bucket_size, raise_on_status
from jrt.whitted import (
    CHUNK,
    RenderSetup,
    RenderStats,
    SceneArrays,
    _shade_chunk,
    _Static,
    _static,
    compiled_program,
    render_arguments,
)

#: How many times :func:`render_radiance` re-renders with grown capacities before it gives
#: up (each overflow fixes at least one level's capacity, so ``max_depth`` re-renders
#: always suffice; the bound is a guard).
MAX_RERENDERS = 64

#: The later levels' capacity of a tree of depth 1 (they are never traced).
_MIN_LATER = 1024

#: Compiled render programs, keyed by the static arguments and the argument shapes (shared
#: by every renderer: another scene of the same sizes and features compiles nothing).
_COMPILED = program_cache()

#: The renderers :func:`cached_renderer` made last (each holds its capacities, measured).
_RENDERERS = program_cache(maxsize=8)


class LevelRays(NamedTuple):
    """One level's rays on the device, padded to the level's capacity (a JAX pytree)."""

    origins: Float[Array, "n 3"]
    directions: Float[Array, "n 3"]
    weights: Float[Array, "n k"]
    pixels: Int[Array, " n"]
    channels: Int[Array, " n"]
    valid: Bool[Array, " n"]


class TreeStats(NamedTuple):
    """What :func:`trace_tree` did, per level ``d`` (device arrays; a JAX pytree).

    ``rays[d]``: rays traced at level d. ``demand[d]``: rays level d needed (more than
    ``rays[d]`` only when it overflowed). ``overflow_weight[d]``: weight of the rays level d
    could not hold (camera-ray units, as :class:`jrt.whitted.RenderStats`).
    """

    rays: Int[Array, " d"]
    demand: Int[Array, " d"]
    overflow_weight: Float[Array, " d"]
    shadow_rays: Int[Array, ""]
    dropped_weight: Float[Array, ""]
    truncated_weight: Float[Array, ""]
    status: Int[Array, ""]  # the queries' jrt.engine.STATUS_* bits (jrt.trace.raise_on_status)


def initial_capacities(setup: RenderSetup, camera_rays: int, max_depth: int) -> tuple[int, ...]:
    """A first guess of the level capacities before anything is measured: the camera rays,
    then a quarter of them per level with glass (the glass camel needs 19 % at level 1 and
    less after), a sixteenth with mirrors only, the smallest level for an opaque scene."""
    f = setup.features
    share = 0.25 if f.dielectric else (1 / 16 if f.mirror else 0.0)
    later = level_size(camera_rays * share)  # the smallest bucket for an opaque scene
    return (level_size(camera_rays),) + (later,) * (max_depth - 1)


def _empty_level(capacity: int, k: int) -> LevelRays:
    return LevelRays(jnp.zeros((capacity, 3), jnp.float32),
                     jnp.tile(jnp.float32([0, 0, 1]), (capacity, 1)),
                     jnp.zeros((capacity, k), jnp.float32), jnp.zeros(capacity, jnp.int32),
                     jnp.zeros(capacity, jnp.int32), jnp.zeros(capacity, bool))


class _Carry(NamedTuple):
    """What one level hands to the next inside :func:`trace_tree`'s loop."""

    rays: LevelRays
    radiance: Float[Array, " pc"]
    traced: Int[Array, " d"]
    demand: Int[Array, " d"]
    overflow: Float[Array, " d"]
    shadow: Int[Array, ""]
    dropped: Float[Array, ""]
    truncated: Float[Array, ""]
    status: Int[Array, ""]


def _level_step(structure, scene: SceneArrays, carry: _Carry, level, key, threshold, *,
                static: _Static, next_capacity: int, last, channels: int) -> _Carry:
    """Level ``level``: shade its rays, add their light into the pixels, and make the next
    level from the kept children (none past the last level: their weight is truncated)."""
    rays = carry.rays
    level = jnp.asarray(level, jnp.int32)  # 32-bit under x64 too
    level_key = jax.random.fold_in(key, jnp.asarray(level, jnp.uint32))  # 32-bit under x64
    out = _shade_level(structure, scene, rays, level_key, static)
    contributions = jnp.where(rays.valid[:, None], out.contributions, 0.0)
    k = out.child_weights.shape[2]  # a child's channels (a bundle's children carry one)
    if static.features.dispersion and not static.bundle:  # one wavelength sample per ray
        index = rays.pixels * channels + rays.channels
        radiance = carry.radiance.at[index].add(contributions[:, 0])
    else:
        index = rays.pixels[:, None] * channels + jnp.arange(channels, dtype=jnp.int32)
        radiance = carry.radiance.at[index.ravel()].add(contributions.ravel())
    alive = out.child_alive & rays.valid[:, None]  # [N, B]
    weights = out.child_weights  # [N, B, K]
    truncated = carry.truncated + jnp.where(
        last, jnp.where(alive[..., None], weights, 0.0).sum() / k, 0.0)
    keep = alive & (weights.max(axis=2) >= threshold) & ~last
    dropped = carry.dropped + jnp.where(
        last, 0.0, jnp.where((alive & ~keep)[..., None], weights, 0.0).sum() / k)
    # Parent-major places in the next level (as np.nonzero on the host).
    flat_keep = keep.reshape(-1)
    place = jnp.cumsum(flat_keep, dtype=jnp.int32) - 1
    fits = flat_keep & (place < next_capacity)
    lost = jnp.where((flat_keep & ~fits)[:, None], weights.reshape(-1, k), 0.0).sum() / k
    target = jnp.where(fits, place, next_capacity)  # out of range: dropped by the scatter
    parent = jnp.repeat(jnp.arange(rays.valid.shape[0], dtype=jnp.int32), weights.shape[1])

    def scatter(empty, values):
        return empty.at[target].set(values, mode="drop")

    nxt = _empty_level(next_capacity, k)
    children = LevelRays(
        origins=scatter(nxt.origins, out.child_origins.reshape(-1, 3)),
        directions=scatter(nxt.directions, out.child_directions.reshape(-1, 3)),
        weights=scatter(nxt.weights, weights.reshape(-1, k)),
        pixels=scatter(nxt.pixels, rays.pixels[parent]),
        channels=scatter(nxt.channels, out.child_channels.reshape(-1)),
        valid=scatter(nxt.valid, fits))
    after = jnp.minimum(level + 1, carry.demand.shape[0] - 1)
    demand = jnp.where(last, carry.demand,
                       carry.demand.at[after].set(flat_keep.sum(dtype=jnp.int32)))
    overflow = jnp.where(last, carry.overflow, carry.overflow.at[after].set(lost))
    return _Carry(children, radiance, carry.traced.at[level].set(rays.valid.sum(dtype=jnp.int32)),
                  demand, overflow, carry.shadow + out.shadow_rays, dropped, truncated,
                  carry.status | out.status)


@functools.partial(jax.jit, static_argnames=("static", "later", "levels", "pixels",
                                             "channels"))
def trace_tree(
    structure,
    scene: SceneArrays,
    camera: LevelRays,
    threshold: Float[Array, ""],
    key: Array,
    depth: Int[Array, ""],
    *,
    static: _Static,
    later: int,
    levels: int,
    pixels: int,
    channels: int,
) -> tuple[Float[Array, "p c"], TreeStats]:
    """The whole tree, levels ``0..depth-1``, from the camera level: linear radiance
    ``[pixels, channels]`` (summed over the camera rays of a pixel; divide by spp) and the
    :class:`TreeStats` (per-level arrays of ``levels >= depth`` entries, past ``depth``
    zero). Pure: no host step between levels.

    Level 0 holds the camera level's rays; the later levels run in one loop (one compiled
    body) and all hold ``later`` rays. The depth is an argument, not a static: one program
    serves every depth up to ``levels`` (:func:`level_slots`)."""
    depth = jnp.asarray(depth, jnp.int32)
    zeros_i = jnp.zeros(levels, jnp.int32)
    carry = _Carry(camera, jnp.zeros(pixels * channels, jnp.float32), zeros_i,
                   zeros_i.at[0].set(camera.valid.sum(dtype=jnp.int32)),
                   jnp.zeros(levels, jnp.float32), jnp.zeros((), jnp.int32),
                   jnp.zeros((), jnp.float32), jnp.zeros((), jnp.float32),
                   jnp.zeros((), jnp.int32))
    # Spectral camera rays may come as bundles of every wavelength sample (weights
    # [N, C]); level 0 splits them, the later levels carry one sample per ray: level 0 is
    # then a program of its own. Otherwise every level, the camera's too, runs in the one
    # loop, on the larger of the two capacities (idle chunks are skipped, so a level still
    # costs its rays): one shading body to compile instead of two.
    bundle = static.features.dispersion and camera.weights.shape[1] > 1
    first_level = 1
    if not bundle:
        later = max(later, camera.valid.shape[0])
        carry = carry._replace(rays=jax.tree.map(
            lambda a, e: jnp.concatenate([a, e[a.shape[0]:]]), camera,
            _empty_level(later, camera.weights.shape[1])))
        first_level = 0
    step = functools.partial(_level_step, structure, scene, next_capacity=later,
                             channels=channels, threshold=threshold, key=key)
    if bundle:
        carry = step(carry, 0, last=depth == 1,
                     static=dataclasses.replace(static, bundle=True))
    step = functools.partial(step, static=static)
    carry = _loop(first_level, depth, levels, lambda level, c: step(
        c, level, last=level == depth - 1), carry, static.differentiable)
    stats = TreeStats(rays=carry.traced, demand=carry.demand, overflow_weight=carry.overflow,
                      shadow_rays=carry.shadow, dropped_weight=carry.dropped,
                      truncated_weight=carry.truncated, status=carry.status)
    return carry.radiance.reshape(pixels, channels), stats


def _shade_level(structure, scene: SceneArrays, rays: LevelRays, key, static: _Static):
    """:func:`jrt.whitted._shade_chunk` over a level, :func:`level_chunk` rays at a time,
    in a loop over the chunks that hold live rays only: a level's rays are packed at its
    front (compaction), so the chunks past them, all padding, are never shaded and a level
    costs its rays, not its capacity. (A ``lax.cond`` per chunk skipped them too, but XLA:CPU
    compiled the shading inside it differently: last-bit differences that sent 11 glass
    paths of a 320x240 image elsewhere.)"""
    n = rays.valid.shape[0]
    chunk = level_chunk(n)
    live = _live_chunks(rays.valid, chunk)

    def shade(i):
        part = jax.tree.map(lambda a: jax.lax.dynamic_slice_in_dim(a, i * chunk, chunk), rays)
        k = jax.random.fold_in(key, jnp.asarray(i, jnp.uint32))  # 32-bit under x64 too
        return _shade_chunk(structure, scene, part.origins, part.directions, part.weights,
                            part.channels, part.valid, k, static=static)

    shapes = jax.eval_shape(shade, jnp.int32(0))
    if static.differentiable:
        # Each chunk slot shaded (or, past the live ones, zeros) as an output of its own,
        # stacked: a loop that carried the whole level and wrote each chunk into it made
        # reverse mode carry the level through every iteration.
        def shade_or_skip(i):
            return jax.lax.cond(i < live, shade, lambda i: jax.tree.map(
                lambda a: jnp.zeros(a.shape, a.dtype), shapes), i)

        parts = jax.lax.map(shade_or_skip, jnp.arange(n // chunk, dtype=jnp.int32))
        return parts._replace(
            **{name: value.reshape(n, *value.shape[2:])
               for name, value in parts._asdict().items() if value.ndim > 1},
            shadow_rays=parts.shadow_rays.sum(dtype=parts.shadow_rays.dtype),
            status=jax.lax.reduce(parts.status, parts.status.dtype.type(0),
                                  jax.lax.bitwise_or, (0,)))
    out = jax.tree.map(lambda a: jnp.zeros((n, *a.shape[1:]) if a.ndim else (), a.dtype),
                       shapes)

    def body(i, out):
        part = shade(i)
        return part._replace(
            **{name: jax.lax.dynamic_update_slice_in_dim(getattr(out, name), value,
                                                         i * chunk, 0)
               for name, value in part._asdict().items() if value.ndim},
            shadow_rays=out.shadow_rays + part.shadow_rays,
            status=out.status | part.status)

    return jax.lax.fori_loop(jnp.int32(0), live, body, out)


def _loop(lower: int, upper, most: int, body, init, differentiable: bool):
    """``lax.fori_loop(lower, upper, body, init)`` for a traced ``upper`` (at most
    ``most``). Differentiable: ``most - lower`` iterations, those from ``upper`` on
    skipped by a ``lax.cond``, since JAX cannot run backwards a loop whose trip count
    is a value (``renderer(..., differentiable=True)``)."""
    if not differentiable:
        return jax.lax.fori_loop(jnp.int32(lower), upper, body, init)
    return jax.lax.fori_loop(lower, most, lambda i, carry: jax.lax.cond(
        i < upper, functools.partial(body, i), lambda carry: carry, carry), init)


@jax.custom_batching.custom_vmap
def _live_chunks(valid: Bool[Array, " n"], chunk: int) -> Int[Array, ""]:
    """The chunks of ``chunk`` rays that hold the live rays (packed at the front). Under
    ``jax.vmap``: the most over the batch items, unbatched, so that the loop it bounds stays
    one loop (a batched bound would run every item as long as the longest, masked)."""
    return (valid.sum(dtype=jnp.int32) + chunk - 1) // chunk


@_live_chunks.def_vmap
def _live_chunks_rule(axis_size, in_batched, valid, chunk):
    count = valid.sum(axis=-1, dtype=jnp.int32).max() if in_batched[0] else valid.sum(
        dtype=jnp.int32)
    return (count + chunk - 1) // chunk, False


#: The most rays :func:`_shade_level` shades at once, per backend: on a CPU a chunk's rays
#: and the traversal's state stay in cache; a GPU needs every ray of a level at once to fill
#: its lanes (65,536 by default; on an H200 the glass camel at 640x480 took 1.12 s with
#: chunks of 32k rays, 29x a closest_hit call on 1M incoherent rays).
MAX_CHUNK = {"cpu": CHUNK}
_MAX_CHUNK_ACCELERATOR = 1 << 20


def level_chunk(n: int) -> int:
    """The chunk of a level of ``n`` rays (a :func:`level_size`): ``n`` itself up to the
    backend's :data:`MAX_CHUNK`, else the largest whole number of :data:`CHUNK` blocks
    that divides ``n`` and fits."""
    most = MAX_CHUNK.get(jax.default_backend(), _MAX_CHUNK_ACCELERATOR)
    if n <= max(most, CHUNK):
        return n
    blocks = n // CHUNK
    assert blocks * CHUNK == n, n
    return CHUNK * max(d for d in range(1, most // CHUNK + 1) if blocks % d == 0)


def level_size(rays: int) -> int:
    """A level's capacity for ``rays`` rays: a size bucket (:func:`jrt.trace.bucket_size`)
    up to one :data:`CHUNK`, then a whole number of chunks (at most one chunk of padding:
    a level runs chunk by chunk, so padding past that would be traced for nothing)."""
    size = bucket_size(max(1, int(rays)))
    return size if size <= CHUNK else -(-int(rays) // CHUNK) * CHUNK


def level_slots(depth: int) -> int:
    """The per-level statistics a program holds: 8, 16, 32 or 64, the depth rounded up (a
    program serves every depth up to it)."""
    return max(8, 1 << (int(depth) - 1).bit_length())


def grown_capacities(capacities: tuple[int, ...], demand: np.ndarray) -> tuple[int, ...]:
    """Capacities after an overflow: the first level that overflowed gets its demand (exact:
    the levels before it were complete), and every later level at least as much, since its
    demand was measured from an incomplete level."""
    grown = list(capacities)
    first = next(d for d in range(len(grown)) if demand[d] > grown[d])
    need = level_size(int(demand[first]))
    for d in range(first, len(grown)):
        grown[d] = max(grown[d], need)
    return tuple(grown)


# --------------------------------------------------------------------------------------------
# The renderer as a pure function of the scene's parameters
# --------------------------------------------------------------------------------------------


class _Shape(NamedTuple):
    """What fixes a renderer's compiled program (hashable: static under ``jax.jit``)."""

    static: _Static
    first: int  # rays of level 0 (padded camera rays)
    later: int  # rays of every later level
    levels: int  # per-level statistics held (level_slots): depths up to it share the program
    width: int
    height: int
    spp: int
    subpixel: bool  # spp positions in the pixel (tree) or spp paths through its centre
    bundles: bool  # spectral camera rays carry every wavelength sample
    channels: int


def _camera_rays(camera_params, shape: _Shape):
    """The camera rays of ``params["camera"]`` (:func:`jrt.params.camera_from_parameters`,
    the program :func:`jrt.camera_rays` runs). Called outside the tree's program, it is
    that very program: the rays agree bit for bit with the host's, which matters, as a
    glass tree turns one ulp of a camera ray into another path."""
    return camera_from_parameters(camera_params, shape.width, shape.height,
                                  shape.spp if shape.subpixel else 1)


def _render_program(params, constants, structure, threshold, key, depth, *, shape: _Shape):
    """linear radiance [H, W, C] and :class:`TreeStats` of the tree for ``params`` (pure)."""
    origins, directions = _camera_rays(params["camera"], shape)
    return _tree_program(params, constants, structure, threshold, key, origins, directions,
                         depth, shape=shape)


@functools.partial(jax.jit, static_argnames=("shape",))
def _tree_program(params, constants, structure, threshold, key, origins, directions, depth,
                  *, shape: _Shape):
    """:func:`_render_program` from the camera rays [H * W * S, 3]."""
    scene = scene_arrays(params, constants)
    if "geometry" in params:  # moved vertices: the structure's boxes follow them
        structure = refit(structure, scene.vertices, constants.faces)
    pixels = shape.width * shape.height
    copies = 1 if shape.subpixel else shape.spp  # paths per position
    per_ray = 1 if shape.bundles or not shape.static.features.dispersion else shape.channels
    k = shape.channels if shape.static.features.dispersion else 3
    n = pixels * shape.spp * per_ray
    rays = jnp.repeat(jnp.arange(origins.shape[0], dtype=jnp.int32), copies * per_ray)
    pad = shape.first - n
    def padded(a, fill=0):  # to the capacity of level 0 (dtype kept: 32-bit under x64)
        return jnp.concatenate([a, jnp.full((pad, *a.shape[1:]), fill, a.dtype)])

    camera = LevelRays(
        origins=padded(origins[rays]),
        directions=jnp.concatenate(
            [directions[rays], jnp.tile(jnp.float32([0, 0, 1]), (pad, 1))]),
        weights=padded(jnp.ones((n, 1 if per_ray > 1 else k), jnp.float32)),
        pixels=padded(jnp.repeat(jnp.arange(pixels, dtype=jnp.int32), shape.spp * per_ray)),
        channels=padded(jnp.tile(jnp.arange(per_ray, dtype=jnp.int32), pixels * shape.spp)
                        if per_ray > 1 else jnp.zeros(n, jnp.int32)),
        valid=jnp.arange(shape.first, dtype=jnp.int32) < n)
    radiance, stats = trace_tree.__wrapped__(
        structure, scene, camera, threshold, key, depth, static=shape.static,
        later=shape.later, levels=shape.levels, pixels=pixels, channels=shape.channels)
    return radiance.reshape(shape.height, shape.width, shape.channels) / shape.spp, stats


class Renderer:
    """``render(params) -> radiance``: the Whitted tree of one scene as a function of its
    parameters (:func:`renderer` makes one; see it for the contract).

    Attributes:
        setup: the :class:`jrt.whitted.RenderSetup` (geometry, structure, channel tables).
        params: the scene's parameters as written (:func:`jrt.params.scene_parameters`).
        capacities: the level capacities the compiled program holds now.
        last_stats: the :class:`jrt.whitted.RenderStats` of the last call made outside a
            trace (None before).
    """

    def __init__(self, setup: RenderSetup, params, *, width: int, height: int, depth: int,
                 spp: int, mode: str, threshold: float, capacities: tuple[int, ...],
                 key: Array, bundles: bool, later_guess: int = _MIN_LATER,
                 differentiable: bool = False, geometry: bool = False):
        self.setup = setup
        self.differentiable = differentiable
        self.params = params
        self.mode = mode
        self.depth = depth
        with jax.ensure_compile_time_eval():  # a device array, even if made under a trace
            self._depth = jax.device_put(np.int32(depth))
        self.capacities = capacities  # the later levels: one size
        self.last_stats: RenderStats | None = None
        self._constants = scene_constants(setup, geometry=geometry)
        self._threshold = jnp.float32(threshold)
        self._key = key
        self._size = (width, height, spp)
        self._bundles = bundles
        # A depth-1 tree traces no later level; its program still holds the size a deeper
        # render of the scene would guess, so that every depth shares one program.
        self._later_guess = later_guess
        self.program = None  # the compiled program of the last call outside a trace

    @property
    def capacities(self) -> tuple[int, ...]:
        """Rays each level holds: the camera level, then one size for every later level
        (their loop is one compiled body)."""
        return self._capacities

    @capacities.setter
    def capacities(self, value) -> None:
        value = tuple(int(c) for c in value)
        later = max(value[1:], default=_MIN_LATER)
        self._capacities = value[:1] + (later,) * (len(value) - 1)

    @property
    def camera_rays(self) -> int:
        """Rays of level 0 (a spectral bundle counts once)."""
        width, height, spp = self._size
        per_ray = 1 if self._bundles or not self.setup.spectral else self.setup.channels
        return width * height * spp * per_ray

    def shape(self) -> _Shape:
        """The static part of the program, at the capacities of now."""
        width, height, spp = self._size
        static = dataclasses.replace(_static(self.setup, self.mode),
                                     differentiable=self.differentiable)
        return _Shape(static=static, first=self.capacities[0],
                      later=max(self.capacities[1:], default=self._later_guess),
                      levels=level_slots(self.depth), width=width, height=height, spp=spp,
                      subpixel=self.mode == "tree", bundles=self._bundles,
                      channels=self.setup.channels)

    @property
    def depth_argument(self) -> Int[Array, ""]:
        """The depth as the program takes it: an argument, so one program serves any depth
        (put on the device once, when the renderer is made)."""
        return self._depth

    def trace(self, params, key: Array | None = None):
        """``(radiance [H, W, C], TreeStats)``: the pure function (jit, vmap, grad compose
        with it), with the capacities of now. Its ``demand`` and ``overflow_weight`` say
        whether a level overflowed (then the radiance lacks that weight), ``status`` any
        traversal failure: check them outside the trace (:func:`check_tree`)."""
        return _render_program(params, self._constants, self.setup.device_structure,
                               self._threshold, self._key if key is None else key,
                               self.depth_argument, shape=self.shape())

    def __call__(self, params=None, key: Array | None = None):
        """Linear radiance ``[H, W, C]`` (a ``jnp`` float32 array; divide nothing: it is the
        mean over the pixel's samples). ``params`` default: the scene's own.

        Outside a trace the render checks its flags: a level that overflowed is rendered
        again with grown capacities (kept for the next calls), a traversal failure raises.
        Inside ``jit``/``vmap``/``grad`` it is :meth:`trace` with a run-time check (a host
        callback) that raises on overflow or failure."""
        params = self.params if params is None else params
        key = self._key if key is None else key
        leaves = jax.tree.leaves((params, key))
        if any(isinstance(x, jax.core.Tracer) for x in leaves):
            radiance, stats = self.trace(params, key)
            jax.debug.callback(functools.partial(check_tree, capacities=self.capacities),
                               stats.demand, stats.status)
            return radiance
        check_parameters(params, self.params)
        start = time.perf_counter()
        timing: dict = {}
        rays = _camera_rays(params["camera"], self.shape())  # the capacities do not move them
        for _ in range(MAX_RERENDERS):
            shape = self.shape()
            args = (params, self._constants, self.setup.device_structure, self._threshold,
                    key, *rays, self.depth_argument)
            program = compiled_program(_COMPILED, _tree_program, args, timing, shape=shape)
            self.program = program
            # Explicitly where the program wants them (the engine spreads the rays over
            # every local device): a no-op once they are there, and no implicit transfer.
            args = jax.device_put(args, program.input_shardings[0])
            radiance, stats = program(*args)
            demand, status = jax.device_get((stats.demand, stats.status))
            raise_on_status(status)
            demand = demand[:self.depth]
            if (demand <= np.asarray(self.capacities)).all():
                break
            self.capacities = grown_capacities(self.capacities, demand)
        else:  # pragma: no cover - each pass fixes a level
            raise RuntimeError(f"level capacities still overflow after {MAX_RERENDERS} renders")
        radiance.block_until_ready()
        self.last_stats = self._stats(stats, time.perf_counter() - start,
                                      timing.get("compile", 0.0))
        return radiance

    def _stats(self, stats: TreeStats, seconds: float, compile_seconds: float) -> RenderStats:
        width, height, spp = self._size
        host = jax.device_get(stats)
        rays = tuple(int(r) for r in host.rays[:self.depth])
        split = self.setup.channels if self._bundles and self.setup.spectral else 1
        return RenderStats(
            width=width, height=height, mode=self.mode, channels=self.setup.channels,
            spp=spp, max_depth=self.depth, rays_per_level=rays,
            shadow_rays=int(host.shadow_rays), seconds=seconds,
            compile_seconds=compile_seconds, dropped_weight=float(host.dropped_weight),
            truncated_weight=float(host.truncated_weight),
            rays_per_pixel_by_depth=tuple(r / (self.camera_rays * (split if d else 1))
                                          for d, r in enumerate(rays)))


def check_tree(demand, status, *, capacities) -> None:
    """Raise for the flags of a :class:`TreeStats`: a traversal failure
    (:func:`jrt.trace.raise_on_status`) or a level that needed more rays than it holds."""
    raise_on_status(status)
    demand = np.asarray(demand)[:len(capacities)]
    over = [d for d in range(len(capacities)) if demand[d] > capacities[d]]
    if over:
        d = over[0]
        raise OverflowError(
            f"level {d} of the Whitted tree needed {int(demand[d]):,} rays but holds "
            f"{capacities[d]:,}: its light is missing. Call the renderer once outside "
            f"jit/vmap/grad (it grows its capacities), or make it with capacities="
            f"{grown_capacities(tuple(capacities), demand)}.")


def renderer(
    scene: RenderSetup | Scene | str | Path,
    *,
    width: int | None = None,
    height: int | None = None,
    max_depth: int | None = None,
    spp: int = 1,
    samples: int | None = None,
    mode: str = "tree",
    threshold: float | None = None,
    capacities: tuple[int, ...] | None = None,
    key: Array | None = None,
    differentiable: bool = False,
    geometry: bool = False,
) -> tuple[Renderer, dict]:
    """A scene's Whitted render as a pure function of its parameters::

        render, params = renderer("glass-camel", width=640, height=480, max_depth=8)
        radiance = render(params)                      # jnp [H, W, C], linear
        params["materials"]["glass"]["A"] = 1.6        # any continuous value
        images = jax.vmap(render)(stacked_params)      # batched: one program

    ``params`` (:func:`jrt.params.scene_parameters`) holds the scene's continuous values
    keyed as in its TOML: materials (albedo, reflectance, A, B, index), lamps (position,
    intensity), camera (eye, target, up, vfov), settings (ambient). What changes the
    compiled program is fixed here: the scene's features, the image size, depth, ``spp``,
    kernel, structure, level capacities. Every level of the tree runs in one compiled
    program (no host step between levels).

    Args:
        scene: a :class:`jrt.whitted.RenderSetup`, a :class:`jrt.scene.Scene`, a built-in
            scene name or a TOML path.
        width, height: image size; default the scene's camera.
        max_depth: tree levels (1: camera rays only); default the scene's.
        spp: camera rays per pixel: in the tree at stratified sub-pixel positions
            (:func:`jrt.camera.subpixel_offsets`, anti-aliasing), in the sampled mode
            ``spp`` paths through the centre.
        samples: wavelength samples (spectral scenes); default the scene's.
        mode: ``"tree"`` or ``"sampled"`` (see :mod:`jrt.whitted`).
        threshold: the pruning threshold; default the scene's.
        capacities: rays per level (``max_depth`` sizes); default a guess from the
            scene's materials, grown on the first render that overflows.
        key: ``jax.random`` key (the sampled mode's branch choices); default PRNGKey(0).
        differentiable: compile for ``jax.grad`` too (reverse mode): the loops over the
            tree's levels and a level's chunks get static lengths (empty ones skipped),
            which JAX can run backwards. Forward mode (``jax.jvp``, ``jax.jacfwd``) works
            either way. See ``docs/gradients.md`` for what the derivative is.
        geometry: the vertices are parameters too (``params["geometry"]["vertices"]``,
            :mod:`jrt.params`): each render refits the structure to them
            (:func:`jrt.refit`: brute force or the BVH, ``settings.accel``) and
            recomputes the corner normals, so ``jax.grad`` reaches the vertices. Costs a
            refit a render; off by default.

    Raises:
        ValueError: ``geometry`` with a structure that cannot be refit.
    """
    setup, depth, threshold = render_arguments(
        scene, max_depth=max_depth, samples=samples, mode=mode, spp=spp, features=None,
        threshold=threshold)
    if geometry and accel.kind(setup.structure.kind).refit is None:
        can = ", ".join(k.name for k in accel.kinds() if k.refit is not None)
        raise ValueError(
            f"geometry=True refits the structure to the vertices on every render, and a "
            f"{setup.structure.kind} cannot be refit; set the scene's settings.accel to one "
            f"of {can}")
    camera = setup.camera(width, height)
    params = scene_parameters(setup, camera.width, camera.height, geometry=geometry)
    bundles = setup.spectral
    split = setup.channels if setup.spectral else 1
    first = camera.num_rays * spp
    guess = initial_capacities(setup, first * split, max(depth, 2))
    if capacities is None:
        capacities = (level_size(first),) + guess[1:depth]
    capacities = tuple(int(c) for c in capacities)
    if len(capacities) != depth or capacities[0] < first:
        raise ValueError(f"capacities must be {depth} level sizes, the first at least "
                         f"{first} (the camera rays), got {capacities}")
    render = Renderer(setup, params, width=camera.width, height=camera.height, depth=depth,
                      spp=spp, mode=mode, threshold=threshold, capacities=capacities,
                      key=jax.random.PRNGKey(0) if key is None else key, bundles=bundles,
                      later_guess=guess[1], differentiable=differentiable,
                      geometry=geometry)
    return render, params


def cached_renderer(setup: RenderSetup, **options) -> Renderer:
    """:func:`renderer` for a prepared setup, remembered (the last few): a second render of
    the same setup and options reuses the renderer and the capacities it measured, so it
    neither guesses again nor renders twice on an overflow."""
    key = (id(setup), tuple(sorted(options.items())))
    entry = _RENDERERS.get(key)
    if entry is None or entry[0] is not setup:
        entry = _RENDERERS[key] = (setup, renderer(setup, **options)[0])
    return entry[1]


__all__ = [
    "MAX_RERENDERS",
    "Renderer",
    "check_tree",
    "renderer",
    "LevelRays",
    "TreeStats",
    "grown_capacities",
    "cached_renderer",
    "initial_capacities",
    "trace_tree",
]
