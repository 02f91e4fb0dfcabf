"""Brute-force traversal: every ray against every triangle, in bounded chunks.

Never builds a [rays x triangles] array: rays go through in chunks of ``ray_chunk``
(``lax.map``), and each chunk scans the triangles in chunks of ``tri_chunk``, so memory
stays at ``ray_chunk x tri_chunk`` whatever the sizes. The oracle that every acceleration
structure is checked against.

Tie rule (shared by every traversal, ``jrt.hits.prefer``): the smallest ``t`` wins, and
among hits tied within 2^-20 of ``t`` the lowest triangle row (the lowest face index,
since rows keep the mesh's order).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from jax import lax

from jrt.hits import Hits, prefer, tie_window, winner_hits
from jrt.kernels import get_kernel
from jrt.programs import bounded_jit

RAY_CHUNK = 256
TRI_CHUNK = 2048


def _pad_rays(origins, directions, tmax, ray_chunk):
    n = origins.shape[0]
    chunks = max(1, -(-n // ray_chunk))
    pad = chunks * ray_chunk - n
    # Padding rays point along +z from the origin with tmax 0: they can hit nothing.
    o = jnp.pad(origins, ((0, pad), (0, 0)))
    d = jnp.concatenate([directions, jnp.tile(jnp.asarray([[0.0, 0.0, 1.0]], directions.dtype),
                                              (pad, 1))])
    tm = jnp.pad(tmax, (0, pad))
    return (
        o.reshape(chunks, ray_chunk, 3),
        d.reshape(chunks, ray_chunk, 3),
        tm.reshape(chunks, ray_chunk),
    )


def _chunk_triangles(triangles, tri_chunk):
    count = triangles.shape[0]
    chunks = max(1, -(-count // tri_chunk))
    # Zero triangles (all corners at the origin) are degenerate: no kernel ever hits them.
    padded = jnp.pad(triangles, ((0, chunks * tri_chunk - count), (0, 0), (0, 0)))
    return padded.reshape(chunks, tri_chunk, 3, 3), jnp.arange(chunks, dtype=jnp.int32) * tri_chunk


def _chunk_t(kernel, o, d, tm, tris):
    """t [tri_chunk, ray_chunk] of one ray chunk against one triangle chunk, tmax applied.

    Triangles run along the outer axis and rays along the inner one, so that the
    reductions below are elementwise across rays (vectorised), not along a row.
    """
    t, _, _ = kernel(o[None, :, :], d[None, :, :], tris[:, None, 0], tris[:, None, 1],
                     tris[:, None, 2])
    return jnp.where(t < tm[None, :], t, jnp.inf)


@bounded_jit
@functools.partial(jax.jit, static_argnames=("kernel", "ray_chunk", "tri_chunk", "rows_out"))
def closest_hit(triangles, triangle_ids, origins, directions, tmax, *, kernel: str,
                ray_chunk: int = RAY_CHUNK, tri_chunk: int = TRI_CHUNK,
                rows_out: bool = False) -> Hits:
    """Closest hit of every ray among ``triangles`` [T, 3, 3] (rows ``triangle_ids`` [T]);
    with ``rows_out``, ``(hits, rows)``: the winners' rows too (int32 [N], -1: a miss)."""
    fn = get_kernel(kernel)
    n = origins.shape[0]
    o, d, tm = _pad_rays(origins, directions, tmax, ray_chunk)
    tri_chunks, bases = _chunk_triangles(triangles, tri_chunk)

    def per_ray_chunk(args):
        o, d, tm = args

        def body(carry, chunk):
            best_t, best_row = carry
            tris, base = chunk
            t = _chunk_t(fn, o, d, tm, tris)
            # Two plain reductions instead of one argmin: a variadic (value, index) reduce
            # does not vectorise on XLA:CPU and ran 10x slower. The lowest row among equal
            # t wins, as the tie rule asks.
            # The tie rule (jrt.hits.prefer): the lowest row among the hits tied with the
            # chunk's smallest t, then against the best of the earlier chunks.
            chunk_min = t.min(axis=0)
            rows = lax.broadcasted_iota(jnp.int32, t.shape, 0)
            tied = (t <= (chunk_min + tie_window(chunk_min))[None, :]) & (t < jnp.inf)
            local = jnp.where(tied, rows, tri_chunk).min(axis=0)
            chunk_t = jnp.where(rows == local[None, :], t, jnp.inf).min(axis=0)
            chunk_row = jnp.where(local < tri_chunk, local + base, -1)
            better = (chunk_row >= 0) & prefer(chunk_t, chunk_row, best_t, best_row)
            best = (jnp.where(better, chunk_t, best_t), jnp.where(better, chunk_row, best_row))
            return best, None

        init = (jnp.full(o.shape[0], jnp.inf, o.dtype), jnp.full(o.shape[0], -1, jnp.int32))

        def scan(_):
            (best_t, best_row), _ = lax.scan(body, init, (tri_chunks, bases))
            return best_t, best_row

        # A chunk whose rays all have tmax <= 0 (padding, jrt.engine.pad_rays) can hit
        # nothing (a hit needs 0 < t < tmax): it skips the triangles.
        return lax.cond(jnp.any(tm > 0), scan, lambda _: init, None)

    best_t, best_row = lax.map(per_ray_chunk, (o, d, tm))
    best_t, best_row = best_t.reshape(-1)[:n], best_row.reshape(-1)[:n]
    # The winner's t, u, v evaluated once, as every traversal does (see winner_hits).
    hits = winner_hits(fn, jnp.concatenate([origins, directions], axis=1),
                       tri_chunks.reshape(-1, 3, 3),
                       jnp.pad(triangle_ids, (0, tri_chunks.shape[0] * tri_chunk
                                              - triangle_ids.shape[0])), best_row)
    return (hits, best_row) if rows_out else hits


@bounded_jit
@functools.partial(jax.jit, static_argnames=("kernel", "ray_chunk", "tri_chunk"))
def occluded(triangles, origins, directions, tmax, *, kernel: str,
             ray_chunk: int = RAY_CHUNK, tri_chunk: int = TRI_CHUNK):
    """bool [N]: does any triangle lie on the ray at ``0 < t < tmax``?

    Any-hit ("if we found one we stop", seed): a ray chunk stops scanning triangle chunks as
    soon as every ray in it is occluded.
    """
    fn = get_kernel(kernel)
    n = origins.shape[0]
    o, d, tm = _pad_rays(origins, directions, tmax, ray_chunk)
    tri_chunks, _ = _chunk_triangles(triangles, tri_chunk)
    # Padding rays (tmax 0 here, or tmax <= 0 from jrt.engine.pad_rays) can hit nothing
    # (a hit needs 0 < t < tmax): they count as occluded so that they never hold a chunk
    # back, and are answered False.
    index = jnp.arange(o.shape[0] * ray_chunk, dtype=jnp.int32)
    live = (index.reshape(o.shape[0], ray_chunk) < n) & (tm > 0)

    def per_ray_chunk(args):
        o, d, tm, live = args

        def cond(state):
            i, occ = state
            return (i < tri_chunks.shape[0]) & ~jnp.all(occ)

        def body(state):
            i, occ = state
            t = _chunk_t(fn, o, d, tm, tri_chunks[i])
            return i + 1, occ | jnp.any(t < jnp.inf, axis=0)

        _, occ = lax.while_loop(cond, body, (jnp.int32(0), ~live))
        return occ & live

    return lax.map(per_ray_chunk, (o, d, tm, live)).reshape(-1)[:n]


@bounded_jit
@functools.partial(jax.jit, static_argnames=("kernel", "capacity", "ray_chunk", "tri_chunk"))
def all_rows(triangles, origins, directions, tmax, *, kernel: str, capacity: int,
             ray_chunk: int = RAY_CHUNK, tri_chunk: int = TRI_CHUNK):
    """Every ray's hits among ``triangles`` [T, 3, 3]: ``(rows, count)``, int32 [N, K]
    (K = ``capacity``) and [N]: the rows hit at ``0 < t < tmax``, the K nearest of them
    (by ``t``, then row; -1 in the free slots), and how many rows it hits (each row once:
    brute force tests each once). What :func:`jrt.all_hits` makes its record from, as
    the engine's traversals do (``jrt.engine``'s ``capacity``)."""
    fn = get_kernel(kernel)
    n = origins.shape[0]
    o, d, tm = _pad_rays(origins, directions, tmax, ray_chunk)
    tri_chunks, bases = _chunk_triangles(triangles, tri_chunk)
    keep = min(capacity, tri_chunk)

    def per_ray_chunk(args):
        o, d, tm = args

        def body(carry, chunk):
            list_t, list_row, count = carry
            tris, base = chunk
            t = _chunk_t(fn, o, d, tm, tris).T  # [ray_chunk, tri_chunk]
            count = count + jnp.sum(t < jnp.inf, axis=1, dtype=jnp.int32)
            # The chunk's nearest (lax.top_k: of equal values the lower index first), then
            # the nearest of those and the list's (the list's rows are the lower ones).
            near_t, near = lax.top_k(-t, keep)
            both_t = jnp.concatenate([list_t, -near_t], axis=1)
            both_row = jnp.concatenate(
                [list_row, jnp.where(near_t > -jnp.inf, near.astype(jnp.int32) + base, -1)],
                axis=1)
            _, pick = lax.top_k(-both_t, capacity)
            return (jnp.take_along_axis(both_t, pick, axis=1),
                    jnp.take_along_axis(both_row, pick, axis=1), count), None

        init = (jnp.full((o.shape[0], capacity), jnp.inf, o.dtype),
                jnp.full((o.shape[0], capacity), -1, jnp.int32),
                jnp.zeros(o.shape[0], jnp.int32))

        def scan(_):
            (_, rows, count), _ = lax.scan(body, init, (tri_chunks, bases))
            return rows, count

        return lax.cond(jnp.any(tm > 0), scan, lambda _: init[1:], None)

    rows, count = lax.map(per_ray_chunk, (o, d, tm))
    return rows.reshape(-1, capacity)[:n], count.reshape(-1)[:n]


def compiled_programs() -> int:
    """How many closest-hit programs of brute force this process holds compiled (one per
    ray count, triangle count and kernel), as :func:`jrt.engine.compiled_programs`."""
    return closest_hit._cache_size()
