"""The hit record shared by every traversal."""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import lax
from jaxtyping import Array, Float, Int

from jrt.fusion import computed_once


class Hits(NamedTuple):
    """Closest hits of a batch of rays.

    Attributes:
        t: float32 [N], the hit point is ``origin + t * direction``: a distance for a unit
            direction, in units of the direction's length otherwise; ``+inf`` for a miss.
        triangle: int32 [N], index into the mesh's faces; ``-1`` for a miss.
        u, v: float32 [N], barycentrics: the point is ``(1-u-v) v0 + u v1 + v v2``; 0 for a miss.
    """

    t: Float[Array, " n"]
    triangle: Int[Array, " n"]
    u: Float[Array, " n"]
    v: Float[Array, " n"]


#: Two hits whose ``t`` differ by at most this fraction of ``t`` are tied, and the lower
#: face index wins. Exact equality is not enough: XLA:CPU contracts multiply-adds into
#: fused ones differently in each compiled program, so the same kernel on the same
#: triangle can return ``t`` one or two ulps apart in a traversal loop and in brute
#: force; 2^-20 is 8 ulps of float32. Every traversal applies :func:`prefer`.
TIE_RELATIVE = 2.0**-20


def tie_window(t):
    """Half-width of the band of ``t`` values tied with ``t``."""
    return jnp.abs(t) * TIE_RELATIVE


def prefer(t, face, best_t, best_face):
    """Does a hit (t, face) replace the best so far (best_face -1: none yet)?

    Tie rule, shared by every traversal and brute force: a clearly smaller ``t`` wins;
    within the tie window the lower face index wins.
    """
    window = tie_window(best_t)
    return (best_face < 0) | (t < best_t - window) | ((t <= best_t + window) & (face < best_face))


def gather_triangles(triangles, rows):
    """``triangles[rows]`` ([n, 3, 3]), gathered as rows of 9 floats: a ``[T, 3, 3]`` gather
    compiles to a loop nest about twice as slow (2048 lanes: 6.5-7.9 against 4.1-4.5 µs)."""
    return triangles.reshape(-1, 9)[rows].reshape(-1, 3, 3)


#: Rays per chunk of :func:`winner_hits`.
WINNER_CHUNK = 1024


def winner_hits(fn, rays, triangles, triangle_ids, rows) -> Hits:
    """The hit record of each ray's winning row (-1: a miss), evaluated in one place.

    ``rays`` [n, C] holds each ray's origin in columns 0-2 and its direction in 3-5 (the
    engine's packed rows, C = 7, or origins and directions side by side, C = 6).

    XLA fuses the kernel differently inside each traversal loop, and the compiled code
    may round one ulp differently (fused multiply-adds); evaluating t, u, v of the winner
    once, elementwise over all rays, gives every structure (and brute force) the same
    numbers for the same triangle. The rays go through in chunks of ``WINNER_CHUNK``: one
    fixed-shape computation in every program, wherever a ray sits in the batch. Evaluated
    over the whole batch at once, the kernel was compiled per program and per batch size,
    and a change elsewhere in the engine moved u, v of two camel rays in 20k by an ulp
    (vectorised loop against its scalar remainder).

    Each chunk is sliced from the rows in place (the last one ends at the last ray and
    overlaps the one before it, whose rays it evaluates again to the same bits): padding
    copies of the ray arrays cost more than the kernel on the engine's interleaved
    shares. A chunk without a winning row (a patch of sky) skips the kernel.

    XLA:CPU computes each output of a fusion in a kernel of its own, and copied the whole
    triangle test into each of t, u, v and the face (watertight on 500k rays: 46.6 ns a
    test for t, u, v against 6.3 for t alone). So u and v leave the test as one complex64
    and the test's outputs are materialised once (``computed_once``): two copies instead
    of four, the same bits, 7-16 % off this pass.
    """
    n = rows.shape[0]
    if n < WINNER_CHUNK:  # one padded chunk, so that the kernel keeps its compiled shape
        pad = WINNER_CHUNK - n
        return jax.tree.map(lambda a: a[:n], winner_hits(
            fn, jnp.pad(rays, ((0, pad), (0, 0))), triangles, triangle_ids,
            jnp.pad(rows, (0, pad), constant_values=-1)))
    if triangles.shape[0] == 0:  # no triangle: every ray misses, no chunk to evaluate
        return _misses(n)

    def evaluate(start, chunk_rows):
        r = lax.dynamic_slice_in_dim(rays, start, WINNER_CHUNK)
        safe = jnp.maximum(chunk_rows, 0)
        tri = gather_triangles(triangles, safe)

        def test(origin, direction, tri):
            t, u, v = fn(origin, direction, tri[:, 0], tri[:, 1], tri[:, 2])
            return t, lax.complex(u, v)

        t, uv = computed_once(start >= 0, test, r[:, 0:3], r[:, 3:6], tri, always=True)
        hit = (chunk_rows >= 0) & (t < jnp.inf)
        zero = jnp.zeros_like(t)
        return Hits(t=jnp.where(hit, t, jnp.inf),
                    triangle=jnp.where(hit, triangle_ids[safe], -1),
                    u=jnp.where(hit, jnp.real(uv), zero), v=jnp.where(hit, jnp.imag(uv), zero))

    def body(i, out):
        start = jnp.minimum(i * WINNER_CHUNK, n - WINNER_CHUNK)
        chunk_rows = lax.dynamic_slice_in_dim(rows, start, WINNER_CHUNK)
        hits = lax.cond(jnp.any(chunk_rows >= 0), evaluate,
                        lambda *_: _misses(WINNER_CHUNK), start, chunk_rows)
        return jax.tree.map(lambda a, b: lax.dynamic_update_slice_in_dim(a, b, start, 0),
                            out, hits)

    # int32 bounds, so that the chunk starts stay int32 under jax_enable_x64.
    return lax.fori_loop(jnp.int32(0), jnp.int32(-(-n // WINNER_CHUNK)), body, _misses(n))


def _misses(n: int) -> Hits:
    """The hit record of ``n`` rays that hit nothing."""
    return Hits(t=jnp.full(n, jnp.inf, jnp.float32), triangle=jnp.full(n, -1, jnp.int32),
                u=jnp.zeros(n, jnp.float32), v=jnp.zeros(n, jnp.float32))
