"""The reference Whitted tree, stepped level by level from the host.

The same tree as :func:`jrt.whitted.render_radiance` (:mod:`jrt.whitted` says what a ray
does at a surface), by an independent route the tests compare the renderer with: every
camera ray per wavelength sample (no bundles), one level and one :data:`jrt.whitted.CHUNK`
of rays per device call of the level function (:func:`jrt.whitted._shade_chunk`), NumPy
compaction of the live children and float64 accumulation between levels. Slower (one device
round trip per level and per chunk), and it can return the image at every depth
(``by_depth=True``: a render at depth ``d`` is exactly the sum of levels ``0..d-1`` of any
deeper render).

    rays = camera_level(setup, setup.camera(32, 24))     # level 0, host arrays
    level = shade_level(setup, rays)                      # its hits, contributions, children
    radiance, stats = host_radiance(setup, max_depth=4)   # the whole tree

:mod:`jrt.whitted` re-exports these names (``jrt.whitted.host_radiance``).
"""

from __future__ import annotations

import functools
import time
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from jrt.camera import Camera, camera_rays
from jrt.programs import program_cache
from jrt.scene import Features, Scene
from jrt.trace import raise_on_status
from jrt.whitted import (
    CHUNK,
    RenderSetup,
    RenderStats,
    _check_mode,
    _ChunkOut,
    _shade_chunk,
    _static,
    compiled_program,
    render_arguments,
)


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
        kinds: int32 [N], the kind code hit (:data:`jrt.whitted.KIND_CODES`), ``MISS`` (-1)
            for none.
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


#: Compiled level functions, keyed by the static arguments and the argument shapes: the
#: whole render compiles once (and a second render of the same shapes not at all).
_COMPILED = program_cache()


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


def chunk_program(setup: RenderSetup, *, mode: str = "tree", chunk: int = 1024) -> str:
    """The jaxpr of the level function for this setup, as text: what a render compiles."""
    _check_mode(mode)
    rays = camera_level(setup, setup.camera(4, 4))
    args, _ = _chunk_args(setup, rays, 0, _check_chunk(chunk), jax.random.PRNGKey(0))
    fn = functools.partial(_shade_chunk.__wrapped__, static=_static(setup, mode))
    return str(jax.make_jaxpr(fn)(*args))


__all__ = [
    "Level",
    "Rays",
    "camera_level",
    "chunk_program",
    "host_radiance",
    "level_from_chunks",
    "shade_level",
]
