"""The Whitted tree as one compiled program: every level on the device.

    radiance, stats = render_radiance(setup, width=160, height=120, max_depth=8)

The same tree as :func:`jrt.whitted.render_radiance` (its module doc says what a ray does at
a surface), with the levels run inside one jitted function instead of one host round trip
per level. Level 0 (the camera rays) is a batch of ``capacities[0]`` rays; the later levels
run in one ``lax.fori_loop`` whose body is compiled once, on batches of
``max(capacities[1:])`` rays (static). The padding rays carry ``valid = False`` and
``tmax = 0``, so they never hit and add nothing. Each level is shaded :data:`CHUNK` rays at
a time (``lax.map``) by :func:`jrt.whitted._shade_chunk`, the host tree's own level function,
so each ray's path is the same computation as on the host.
Between levels, on the device:

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
could not trace (``overflow_weight``), the jax-md habit of overflow flags out of jit.
:func:`render_radiance` then grows the capacities to the demand and renders again, so no
ray is ever lost silently; :func:`trace_tree` is the pure function for callers that handle
the flags themselves.

**Capacities** are rounded up to :func:`jrt.trace.bucket_size` (at most 1.5x padding), so
renders of similar scenes share compiled programs. The first guess, before any render has
measured the scene, is :func:`initial_capacities`.
"""

from __future__ import annotations

import functools
import time
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from jrt.trace import bucket_size
from jrt.whitted import (
    CHUNK,
    Rays,
    RenderSetup,
    RenderStats,
    SceneArrays,
    _shade_chunk,
    _Static,
    _static,
    camera_level,
    render_arguments,
)

#: How many times :func:`render_radiance` re-renders with grown capacities before it gives
#: up (each overflow fixes at least one level's capacity, so ``max_depth`` re-renders
#: always suffice; the bound is a guard).
MAX_RERENDERS = 64

#: The later levels' capacity of a tree of depth 1 (they are never traced).
_MIN_LATER = 1024

#: Compiled trees, keyed by the static arguments and the argument shapes.
_COMPILED: dict = {}


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


def initial_capacities(setup: RenderSetup, camera_rays: int, max_depth: int) -> tuple[int, ...]:
    """A first guess of the level capacities before anything is measured: the camera rays,
    then a quarter of them per level with glass (the glass camel needs 19 % at level 1 and
    less after), a sixteenth with mirrors only, the smallest level for an opaque scene."""
    f = setup.features
    share = 0.25 if f.dielectric else (1 / 16 if f.mirror else 0.0)
    later = level_size(camera_rays * share)  # the smallest bucket for an opaque scene
    return (level_size(camera_rays),) + (later,) * (max_depth - 1)


def _pad(rays: Rays, capacity: int) -> LevelRays:
    """Host rays as a device level of ``capacity`` rays (unit directions in the padding)."""
    n = len(rays)
    pad = capacity - n

    def padded(a, fill=0):
        return jnp.asarray(np.concatenate([a, np.full((pad, *a.shape[1:]), fill, a.dtype)]))

    directions = np.concatenate([rays.directions, np.tile(np.float32([0, 0, 1]), (pad, 1))])
    return LevelRays(padded(rays.origins), jnp.asarray(directions), padded(rays.weights),
                     padded(rays.pixels), padded(rays.channels),
                     jnp.asarray(np.arange(capacity) < n))


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


def _level_step(structure, scene: SceneArrays, carry: _Carry, level, key, threshold, *,
                static: _Static, next_capacity: int, last, channels: int) -> _Carry:
    """Level ``level``: shade its rays, add their light into the pixels, and make the next
    level from the kept children (none past the last level: their weight is truncated)."""
    rays = carry.rays
    k = rays.weights.shape[1]
    out = _shade_level(structure, scene, rays, jax.random.fold_in(key, level), static)
    contributions = jnp.where(rays.valid[:, None], out.contributions, 0.0)
    if static.features.dispersion:
        index = rays.pixels * channels + rays.channels
        radiance = carry.radiance.at[index].add(contributions[:, 0])
    else:
        index = rays.pixels[:, None] * channels + jnp.arange(channels)
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
        channels=scatter(nxt.channels, rays.channels[parent]),
        valid=scatter(nxt.valid, fits))
    after = jnp.minimum(level + 1, carry.demand.shape[0] - 1)
    demand = jnp.where(last, carry.demand,
                       carry.demand.at[after].set(flat_keep.sum(dtype=jnp.int32)))
    overflow = jnp.where(last, carry.overflow, carry.overflow.at[after].set(lost))
    return _Carry(children, radiance, carry.traced.at[level].set(rays.valid.sum(dtype=jnp.int32)),
                  demand, overflow, carry.shadow + out.shadow_rays, dropped, truncated)


@functools.partial(jax.jit, static_argnames=("static", "capacities", "pixels", "channels"))
def trace_tree(
    structure,
    scene: SceneArrays,
    camera: LevelRays,
    threshold: Float[Array, ""],
    key: Array,
    *,
    static: _Static,
    capacities: tuple[int, ...],
    pixels: int,
    channels: int,
) -> tuple[Float[Array, "p c"], TreeStats]:
    """The whole tree, levels ``0..len(capacities)-1``, from the camera level: linear radiance
    ``[pixels, channels]`` (summed over the camera rays of a pixel; divide by spp) and the
    :class:`TreeStats`. Pure: no host step between levels.

    Level 0 holds ``capacities[0]`` rays; the later levels run in one loop (one compiled
    body, whatever the depth) and all hold ``max(capacities[1:])``."""
    depth = len(capacities)
    later = max(capacities[1:], default=_MIN_LATER)
    zeros_i = jnp.zeros(depth, jnp.int32)
    carry = _Carry(camera, jnp.zeros(pixels * channels, jnp.float32), zeros_i,
                   zeros_i.at[0].set(camera.valid.sum(dtype=jnp.int32)),
                   jnp.zeros(depth, jnp.float32), jnp.zeros((), jnp.int32),
                   jnp.zeros((), jnp.float32), jnp.zeros((), jnp.float32))
    step = functools.partial(_level_step, structure, scene, static=static,
                             next_capacity=later, channels=channels, threshold=threshold,
                             key=key)
    carry = step(carry, 0, last=jnp.asarray(depth == 1))
    if depth > 1:
        carry = jax.lax.fori_loop(
            1, depth, lambda level, c: step(c, level, last=level == depth - 1), carry)
    stats = TreeStats(rays=carry.traced, demand=carry.demand, overflow_weight=carry.overflow,
                      shadow_rays=carry.shadow, dropped_weight=carry.dropped,
                      truncated_weight=carry.truncated)
    return carry.radiance.reshape(pixels, channels), stats


def _shade_level(structure, scene: SceneArrays, rays: LevelRays, key, static: _Static):
    """:func:`jrt.whitted._shade_chunk` over a level, :data:`CHUNK` rays at a time
    (``lax.map``: one compiled body; a chunk's rays and the traversal's state stay in cache,
    which a whole level of a million rays does not)."""
    n = rays.valid.shape[0]
    chunk = min(CHUNK, n)
    assert n % chunk == 0, (n, chunk)
    keys = jax.random.split(key, n // chunk)

    def one(item):
        part, k = item
        return _shade_chunk(structure, scene, part.origins, part.directions, part.weights,
                            part.channels, part.valid, k, static=static)

    parts = jax.tree.map(lambda a: a.reshape(n // chunk, chunk, *a.shape[1:]), rays)
    out = jax.lax.map(one, (parts, keys))
    return jax.tree.map(lambda a: a.reshape(n, *a.shape[2:]) if a.ndim >= 2 else a.sum(), out)


def level_size(rays: int) -> int:
    """A level's capacity for ``rays`` rays: a size bucket (:func:`jrt.trace.bucket_size`)
    up to one :data:`CHUNK`, then a whole number of chunks (at most one chunk of padding:
    a level runs chunk by chunk, so padding past that would be traced for nothing)."""
    size = bucket_size(max(1, int(rays)))
    return size if size <= CHUNK else -(-int(rays) // CHUNK) * CHUNK


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


def render_radiance(
    scene_or_setup,
    *,
    width: int | None = None,
    height: int | None = None,
    max_depth: int | None = None,
    samples: int | None = None,
    mode: str = "tree",
    spp: int = 1,
    key: Array | None = None,
    threshold: float | None = None,
    capacities: tuple[int, ...] | None = None,
) -> tuple[Float[np.ndarray, "h w c"], RenderStats, tuple[int, ...]]:
    """:func:`jrt.whitted.render_radiance` with every level on the device: linear radiance
    ``[H, W, C]`` (float64 on the host), the :class:`jrt.whitted.RenderStats`, and the
    capacities the render ran with (pass them back to skip the re-renders next time).

    A level that overflows its capacity is never lost: the render is run again with the
    capacities grown to the measured demand (:func:`grown_capacities`)."""
    start = time.perf_counter()
    setup, depth, threshold = render_arguments(
        scene_or_setup, max_depth=max_depth, samples=samples, mode=mode, spp=spp,
        features=None, threshold=threshold)
    camera = setup.camera(width, height)
    host_rays = camera_level(setup, camera, spp)
    if capacities is None:
        capacities = initial_capacities(setup, len(host_rays), depth)
    capacities = tuple(int(c) for c in capacities)
    if len(capacities) != depth or capacities[0] < len(host_rays):
        raise ValueError(f"capacities must be {depth} level sizes, the first at least "
                         f"{len(host_rays)} (the camera rays), got {capacities}")
    key = jax.random.PRNGKey(0) if key is None else key
    static = _static(setup, mode)
    compile_seconds = 0.0
    for _ in range(MAX_RERENDERS):
        args = (setup.device_structure, setup.arrays, _pad(host_rays, capacities[0]),
                jnp.float32(threshold), key)
        options = dict(static=static, capacities=capacities, pixels=camera.num_rays,
                       channels=setup.channels)
        leaves, treedef = jax.tree.flatten(args)
        signature = (tuple(sorted(options.items())), treedef,
                     tuple((np.shape(x), str(x.dtype)) for x in leaves))
        program = _COMPILED.get(signature)
        if program is None:
            tic = time.perf_counter()
            program = _COMPILED[signature] = trace_tree.lower(*args, **options).compile()
            compile_seconds += time.perf_counter() - tic
        radiance, stats = program(*args)
        demand = np.asarray(stats.demand)
        if (demand <= np.asarray(capacities)).all():
            break
        capacities = grown_capacities(capacities, demand)
    else:  # pragma: no cover - each pass fixes a level
        raise RuntimeError(f"level capacities still overflow after {MAX_RERENDERS} renders")
    rays = tuple(int(r) for r in np.asarray(stats.rays))
    out = np.asarray(radiance, np.float64).reshape(camera.height, camera.width, -1) / spp
    result = RenderStats(
        width=camera.width, height=camera.height, mode=mode, channels=setup.channels,
        spp=spp, max_depth=depth, rays_per_level=rays, shadow_rays=int(stats.shadow_rays),
        seconds=time.perf_counter() - start, compile_seconds=compile_seconds,
        dropped_weight=float(stats.dropped_weight),
        truncated_weight=float(stats.truncated_weight),
        rays_per_pixel_by_depth=tuple(r / len(host_rays) for r in rays))
    return out, result, capacities


__all__ = [
    "MAX_RERENDERS",
    "LevelRays",
    "TreeStats",
    "grown_capacities",
    "initial_capacities",
    "render_radiance",
    "trace_tree",
]
