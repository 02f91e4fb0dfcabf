"""Every hit along each ray, sorted by distance: :func:`all_hits`.

    hits = jrt.all_hits(structure, origins, directions, max_hits=16)
    hits.t[i, :hits.count[i]]          # ray i's hits, nearest first

What a ray-casting user asks of a mesh beyond its first hit: how many times a ray crosses
the surface (inside or outside a closed mesh), every entry and exit of a line through it.

**How.** The same traversal as :func:`jrt.closest_hit`, any structure, any kernel, run by
the engine with no culling by a hit found: each lane keeps the distinct triangle rows its
ray hits (at most a *capacity* of them, ``max_hits + 4``, the nearest kept) and counts
them (``jrt.engine``'s ``capacity``; brute force keeps the nearest rows of every triangle
chunk, ``jrt.brute.all_rows``). A triangle that a kd-tree, grid, octree or BSP tree
references from several leaves is recognised and kept once. Then, in one place for every
structure (:func:`hits_of_rows`), each row's ``t, u, v`` is evaluated by the kernel (so a
structure's hits are brute force's, bit for bit, as for closest hits), the hits are ordered
by ``t`` and face, and tied ones are merged.

**Tie rule.** Hits whose ``t`` lie within the tie window of the first of them
(``jrt.hits.TIE_RELATIVE``, 2^-20 of ``t``) are one hit, reported on the lowest face
index among them, the rule :func:`jrt.closest_hit` applies (so ``all_hits``' first hit is
``closest_hit``'s). A ray through an edge or a vertex shared by several triangles crosses
the surface once and the watertight kernel reports each of those triangles: here it is
one hit. Coincident duplicated faces are one hit as well (one crossing of one surface);
two surfaces that truly meet at one point are too, which is what counting crossings (a
point inside a closed mesh) needs.

**Never a silent truncation.** ``count`` is how many hits the ray has, also beyond
``max_hits`` (``overflow`` is then set and the record holds the ``max_hits`` nearest).
When a ray hits more distinct triangles than the capacity, a call outside ``jit`` traces
those rays again with room for all of them, so ``count`` is exact; inside a caller's
``jit`` that cannot happen, ``overflow`` is set and ``count`` is an upper bound (a
triangle evicted from a full list and met again in another leaf is counted again).

``jit`` and ``vmap`` compose as with :func:`jrt.closest_hit` (its size buckets and
vmap rule); derivatives of ``t, u, v`` are the closed-form ones of
``jrt.hit_derivatives`` (the same as :func:`jrt.closest_hit`'s), zero for a padding slot.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jaxtyping import Array, Bool, Float, Int

from accel.structure import Structure
from jrt import engine, trace
from jrt.hit_derivatives import hit_tangents
from jrt.hits import tie_window, winner_hits
from jrt.kernels import DEFAULT_KERNEL, get_kernel
from jrt.programs import bounded_jit

#: ``max_hits`` when not given: a ray through a closed mesh such as the camel crosses it
#: 2-8 times.
DEFAULT_MAX_HITS = 16


class AllHits(NamedTuple):
    """All hits of a batch of rays, nearest first.

    Attributes:
        t: float32 [N, M] (M = ``max_hits``), ``+inf`` past a ray's hits.
        triangle: int32 [N, M], face indices, ``-1`` past a ray's hits.
        u, v: float32 [N, M], barycentrics (``jrt.Hits``' convention), 0 past a ray's hits.
        count: int32 [N], how many hits each ray has (may exceed M: see ``overflow``).
        overflow: bool [N], ``count > M``: the record holds the M nearest.
    """

    t: Float[Array, "n m"]
    triangle: Int[Array, "n m"]
    u: Float[Array, "n m"]
    v: Float[Array, "n m"]
    count: Int[Array, " n"]
    overflow: Bool[Array, " n"]


def capacity_for(max_hits: int) -> int:
    """Distinct triangles a lane keeps for ``max_hits`` hits: room for a few hits on edges
    or vertices, which a ray meets as two or more triangles (a ray with more is traced
    again with room for all, outside a caller's jit). Each slot costs every lane work on
    every leaf test: at ``2 max_hits + 4`` the collecting pass on 65,536 camel rays took
    1.7x as long as at ``max_hits + 4`` for max_hits 16."""
    return max_hits + 4


@functools.partial(jax.custom_jvp, nondiff_argnums=(0,))
def _evaluate(kernel, triangles, triangle_ids, rows, origins, directions):
    """t, face, u, v [N, K] of each ray against its ``rows`` [N, K] of ``triangles`` (-1:
    inf, -1, 0, 0): each column through :func:`jrt.hits.winner_hits`, the evaluation every
    closest hit gets, one column at a time over every ray (``lax.map``), so a ray's row is
    evaluated by the same code whichever column holds it and whichever structure found
    it."""
    fn = get_kernel(kernel)
    rays = jnp.concatenate([origins, directions], axis=1)

    def column(r):
        hits = winner_hits(fn, rays, triangles, triangle_ids, r)
        return hits.t, hits.triangle, hits.u, hits.v

    return tuple(a.T for a in lax.map(column, rows.T))


@_evaluate.defjvp
def _evaluate_jvp(kernel, primals, tangents):
    """The closed-form tangents of each hit (``jrt.hit_derivatives``), as closest hits."""
    triangles, _, rows, origins, directions = primals
    triangles_dot, _, _, origins_dot, directions_dot = tangents
    out = _evaluate(kernel, *primals)
    shape = rows.shape + (3,)
    t_dot, u_dot, v_dot = hit_tangents(
        triangles, rows, jnp.broadcast_to(origins[:, None], shape),
        jnp.broadcast_to(directions[:, None], shape), triangles_dot,
        jnp.broadcast_to(origins_dot[:, None], shape),
        jnp.broadcast_to(directions_dot[:, None], shape))
    hit = out[0] < jnp.inf
    t_dot, u_dot, v_dot = (jnp.where(hit, x, 0.0) for x in (t_dot, u_dot, v_dot))
    return out, (t_dot, np.zeros(rows.shape, jax.dtypes.float0), u_dot, v_dot)


def hits_of_rows(kernel: str, triangles, triangle_ids, origins, directions, rows, collected,
                 *, max_hits: int, capacity: int) -> AllHits:
    """The record of every ray's hits from the rows a traversal collected (``rows`` int32
    [N, K], -1 in free slots; ``collected`` [N], the distinct rows it hit): each row
    evaluated (:func:`_evaluate`), ordered by (t, face), tied hits merged (the module's
    tie rule), the first ``max_hits`` kept.

    No ``lax.sort``: XLA:CPU sorts each short row with a comparator call per comparison
    (three sorts of [65536, 36] took 0.8 s). The order is by rank instead, each entry's
    count of entries before it ([N, K, K] comparisons, vectorised), and the tie groups are
    one scan over the K columns; gathers and scatters place the entries."""
    t, face, u, v = _evaluate(kernel, triangles, triangle_ids, rows, origins, directions)
    n, k = t.shape
    valid = t < jnp.inf
    column = lax.broadcasted_iota(jnp.int32, (n, k), 1)
    # (t, face) keys, distinct in a row (its rows are): free slots after every hit.
    key = jnp.where(valid, face, jnp.iinfo(jnp.int32).max - k + column)
    t_i, t_j = t[:, :, None], t[:, None, :]
    before = (t_i < t_j) | ((t_i == t_j) & (key[:, :, None] < key[:, None, :]))
    rank = jnp.sum(before, axis=1, dtype=jnp.int32)
    ray = lax.broadcasted_iota(jnp.int32, (n, 1), 0)
    order = jnp.zeros((n, k), jnp.int32).at[ray, rank].set(column, unique_indices=True)
    t, face, u, v, valid = (jnp.take_along_axis(a, order, axis=1)
                            for a in (t, face, u, v, valid))

    # Tie groups, nearest first: a hit starts a group unless it lies within the tie window
    # of the group's first hit; a group's hit is its lowest face, emitted when it closes.
    def group(carry, x):
        start, rep, rep_face = carry
        j, t_j, face_j, valid_j = x
        new = valid_j & ((rep < 0) | (t_j > start + tie_window(start)))
        closing = (new | ~valid_j) & (rep >= 0)
        emitted = jnp.where(closing, rep, -1)
        lower = valid_j & ~new & (face_j < rep_face)
        rep = jnp.where(new | lower, j, jnp.where(closing, -1, rep))
        rep_face = jnp.where(new | lower, face_j, rep_face)
        return (jnp.where(new, t_j, start), rep, rep_face), emitted

    init = (jnp.full(n, jnp.inf, t.dtype), jnp.full(n, -1, jnp.int32),
            jnp.full(n, -1, jnp.int32))
    (_, last, _), emitted = lax.scan(
        group, init, (jnp.arange(k, dtype=jnp.int32), t.T, face.T, valid.T))
    emitted = jnp.concatenate([emitted.T, last[:, None]], axis=1)  # [N, K + 1]
    kept = emitted >= 0
    merged = jnp.sum(kept, axis=1, dtype=jnp.int32)
    m = min(max_hits, k)
    slot = jnp.cumsum(kept, axis=1, dtype=jnp.int32) - 1
    pick = jnp.zeros((n, m + 1), jnp.int32).at[ray, jnp.where(kept & (slot < m), slot, m)].set(
        jnp.maximum(emitted, 0))[:, :m]
    live = lax.broadcasted_iota(jnp.int32, (n, m), 1) < merged[:, None]
    record = tuple(jnp.where(live, jnp.take_along_axis(a, pick, axis=1), fill)
                   for a, fill in ((t, jnp.inf), (face, -1), (u, 0.0), (v, 0.0)))
    if m < max_hits:  # fewer slots than asked (max_hits > capacity cannot happen here)
        record = tuple(jnp.pad(a, ((0, 0), (0, max_hits - m)), constant_values=fill)
                       for a, fill in zip(record, (jnp.inf, -1, 0.0, 0.0), strict=True))
    count = jnp.where(collected > capacity, collected, merged)
    return AllHits(*record, count=count, overflow=count > max_hits)


_record = bounded_jit(jax.jit(hits_of_rows, static_argnames=("kernel", "max_hits", "capacity")))


def _leading(rows, collected):
    """``rows`` cut to the columns any ray fills, rounded up to a power of two (a few
    programs): the lists fill their leading columns (the engine appends, brute force
    keeps them nearest first), and :func:`hits_of_rows` costs K^2 a ray."""
    k = rows.shape[1]
    used = int(np.minimum(np.asarray(collected), k).max(initial=0))
    width = min(k, 1 << max(used - 1, 0).bit_length())
    return rows[:, :width] if width < k else rows


def _check_max_hits(max_hits):
    if isinstance(max_hits, bool) or not isinstance(max_hits, (int, np.integer)) \
            or max_hits < 1:
        raise ValueError(f"max_hits must be a positive integer (the hits kept per ray), "
                         f"got {max_hits!r}")
    return int(max_hits)


def _collect(structure, origins, directions, tmax, *, kernel, lanes, stack_size, capacity):
    """(rows [N, K], collected [N]) of the query with this capacity (``jrt.trace``). The
    rows are integers: nothing to differentiate, so the traversal sees its inputs'
    values only (a derivative around it never reaches the engine's loop)."""
    if trace._is_traced(origins, directions, tmax, *jax.tree.leaves(structure)):
        origins, directions, tmax = (lax.stop_gradient(a) for a in (origins, directions, tmax))
        structure = jax.tree.map(lax.stop_gradient, structure)
    (rows, collected), _ = trace._query(
        structure, origins, directions, tmax, kernel=kernel, any_hit=False, counters=False,
        lanes=lanes, stack_size=stack_size, capacity=capacity)
    return rows, collected


def all_hits(
    structure: Structure,
    origins: Float[Array, "n 3"],
    directions: Float[Array, "n 3"],
    max_hits: int = DEFAULT_MAX_HITS,
    *,
    tmax: Float[Array, " n"] | float | None = None,
    kernel: str = DEFAULT_KERNEL,
    lanes: int | None = None,
    stack_size: int = engine.DEFAULT_STACK_SIZE,
) -> AllHits:
    """Every hit of every ray with ``0 < t < tmax``, nearest first (see the module).

    Args:
        structure: from ``accel.build``.
        origins, directions: float [N, 3], as :func:`jrt.closest_hit` takes them (any
            direction length within ``jrt.engine.DIRECTION_LENGTHS``; ``t`` in its units).
        max_hits: hits kept per ray (the record's width M); ``count`` says how many there
            are, also beyond M (``overflow``). A static shape: one program per value.
        tmax, kernel, lanes, stack_size: as :func:`jrt.closest_hit`.

    Returns:
        :class:`AllHits`: t, triangle, u, v [N, M] padded with ``inf``, ``-1``, 0, 0;
        count [N]; overflow [N]. Hits tied within 2^-20 of ``t`` (a ray through a shared
        edge or vertex) are one hit, on the lowest face index: the module's tie rule.
    """
    max_hits = _check_max_hits(max_hits)
    capacity = capacity_for(max_hits)
    origins, directions, tmax = trace._check_rays(origins, directions, tmax)
    options = dict(kernel=kernel, lanes=lanes, stack_size=stack_size)
    rows, collected = _collect(structure, origins, directions, tmax, capacity=capacity,
                               **options)
    arrays = {name: jnp.asarray(structure[name]) for name in ("triangles", "triangle_ids")}
    traced = trace._is_traced(origins, directions, tmax, *jax.tree.leaves(structure))
    record = _record if not traced else hits_of_rows
    if not traced:
        rows = _leading(rows, collected)
    if not traced and origins.shape[0]:
        over = np.flatnonzero(np.asarray(collected) > capacity)
        if over.size:
            # More distinct triangles than the lanes kept: those rays again, with room for
            # all of them (the count, an upper bound, is enough), so that count is exact.
            room = 1 << int(np.asarray(collected)[over].max() - 1).bit_length()
            index = jnp.asarray(over)
            more_rows, more = _collect(structure, origins[index], directions[index],
                                       tmax[index], capacity=room, **options)
            more_rows = _leading(more_rows, more)
            full = record(kernel, arrays["triangles"], arrays["triangle_ids"],
                          origins[index], directions[index], more_rows, more,
                          max_hits=max_hits, capacity=room)
            base = record(kernel, arrays["triangles"], arrays["triangle_ids"], origins,
                          directions, rows, collected, max_hits=max_hits, capacity=capacity)
            return jax.tree.map(lambda a, b: a.at[index].set(b), base, full)
    return record(kernel, arrays["triangles"], arrays["triangle_ids"], origins, directions,
                  rows, collected, max_hits=max_hits, capacity=capacity)
