"""Octree traversal: ordered, front to back, on the shared engine (layout in ``accel.octree``).

A parametric traversal in the spirit of Revelles, Ureña & Lastra, "An efficient
parametric algorithm for octree traversal" (WSCG 2000): a cell is never intersected as
a box; its children's parameter intervals come from the ray's crossings of the cell's
three mid-planes, within the cell's own interval [t0, t1]. Revelles steps from child to
child by the exit plane; here the eight children's intervals are formed at once and
visited in order of their entry, which handles the overlaps below the same way.

The cells are in the tree's local frame (``accel.octree``), and so is the origin the
steps read: ``o = ray.origin_axes``, the world origin minus ``frame``, with the
magnitude ``s = ray.scale(axis)`` (``|o|``, plus ``jrt.engine.margin_pad`` for a kernel
whose rounding depends on the world position). Per axis a, with ``g = centre_a - o_a``
and ``delta = BOX_MARGIN (|centre_a| + s_a)``, the ray is within ``delta`` of the
mid-plane for t between ``(g - delta)/d_a`` and ``(g + delta)/d_a``; call the smaller
F_a (the far half may be entered from then) and the larger N_a (the near half is
certainly left by then). The half the ray comes from (the lower one if d_a > 0) has the
interval [-inf, N_a] on that axis, the other half [F_a, inf]; a child's interval is the
intersection of its three halves' and [t0, t1]. Neighbouring children thus overlap by
the engine's margin around every plane (as ``jrt.engine.box_interval`` widens a box by
BOX_MARGIN of its corners' and the origin's magnitude), and a ray lying near a plane
visits both halves.

Zero direction components, explicitly: 1/d is ±inf, signed as the zero. If the origin
is off the plane by more than delta, (g ± delta) * inf are two infinities of one sign:
F_a = N_a = +inf when the ray stays in its first half (g and 1/d of one sign), -inf
when it stays in the other, so exactly the half that holds the origin is kept for all
t. If the origin is within delta of the plane, they are -inf and +inf: both halves for
all t. If g ± delta is exactly 0 (origin and centre both 0, or the origin exactly
delta off), 0 * inf is NaN, read as -inf for F_a and +inf for N_a: both halves.
The first half is chosen by the sign of 1/d, so -0.0 counts as negative.

A lane starts at the root with the root cube's interval (``jrt.engine.box_interval``,
so a ray that misses the cube takes one step). At a cell, [t0, t1] is first cut to
[t0, min(t1, best_t)]: nothing beyond the cull bound matters.

Order: each child gets the int32 key ``(bits(s_k) & ~7) | k`` (s_k >= 0, so its bit
pattern orders as the float; the low three bits make keys distinct and reorder only
children whose entries lie within 8 ulps of each other). A step at an interior cell takes,
among the non-empty children with ``s_k <= e_k``, the one of the smallest key above the
cell's last visited key, and also finds the next key after it. An interior child is
entered with [s_k, e_k] and, when a next key exists, the cell is pushed to continue after
the key; a leaf child is handed to the engine at once and the lane stays on the cell with
the new key (no push); a cell with nothing left pops. The keys depend on the ray, the
cell's centre and t0 only (not on t1 or best_t), so recomputing them at every visit of the
cell gives the same keys, and every child whose interval is not empty is visited exactly
once, in front-to-back order. Revelles' successor table would step through the same
children when the intervals do not overlap; the keys also order the extra children that
the margins add (a ray through an edge or a corner of the margins, or lying in a plane,
which visits both halves for all t) with no case analysis.

State and stack entry: (cell row, t0, t1, last key) and, in the entry, a bound: the
smallest entry distance of anything the entry or the entries below it still hold (the
next key's distance, minimum with the entry below's bound). A pop whose bound exceeds
best_t ends the lane: nothing on the stack can hold a closer hit. The stack holds at most
one entry per level, so its depth never exceeds the tree's.
"""

from __future__ import annotations

import functools

import jax.numpy as jnp
from jax import lax

from jrt.engine import BOX_MARGIN, Step, Traversal, box_interval
from jrt.fusion import computed_once

_NO_KEY = jnp.iinfo(jnp.int32).max
_KEY_MASK = 0x7FFFFFF8
_EMPTY = -1
_CHILDREN = 8


def _f2i(x):
    return lax.bitcast_convert_type(x, jnp.int32)


def _i2f(x):
    return lax.bitcast_convert_type(x, jnp.float32)


def _start(arrays, ray):
    root = arrays["nodes"][0]
    half = root[3]
    lo = [root[a] - half for a in range(3)]
    hi = [root[a] + half for a in range(3)]
    t0, t1 = box_interval(ray, lo, hi)
    n = ray.tmax.shape[0]
    return (jnp.zeros(n, jnp.int32), t0, t1, jnp.full(n, -1, jnp.int32))


def _pick(k, values):
    """values[k] for k in 0..7 per lane, by a tree of selects on k's bits."""
    level = list(values)
    for b in range(3):
        bit = (k & (1 << b)) != 0
        level = [jnp.where(bit, level[2 * i + 1], level[2 * i]) for i in range(len(level) // 2)]
    return level[0]


def _plan(ray, rows, t0, t1, last, best_t):
    """The cell's next child: (whether there is one, whether there is one after it, its
    key, the next key, its reference, its interval [s, e]). All zero (no next child) is
    also the answer for a lane whose interval is empty, t0 > t1."""
    row = rows.T
    t1 = jnp.minimum(t1, best_t)
    starts, ends = [], []  # per axis: (lower half, upper half)
    for a in range(3):
        o, inv, c = ray.origin_axes[a], ray.inv_direction[a], row[a]
        gap = c - o
        delta = BOX_MARGIN * (jnp.abs(c) + ray.scale(a))
        p = (gap - delta) * inv
        q = (gap + delta) * inv
        far = jnp.minimum(p, q)
        near = jnp.maximum(p, q)
        far = jnp.where(far == far, far, -jnp.inf)
        near = jnp.where(near == near, near, jnp.inf)
        up = inv > 0  # the lower half comes first
        starts.append((jnp.where(up, -jnp.inf, far), jnp.where(up, far, -jnp.inf)))
        ends.append((jnp.where(up, near, jnp.inf), jnp.where(up, jnp.inf, near)))
    # Children's intervals, k = bx + 2 by + 4 bz, built axis by axis.
    s = [t0]
    e = [t1]
    for a in range(3):
        s = [jnp.maximum(x, starts[a][b]) for b in range(2) for x in s]
        e = [jnp.minimum(x, ends[a][b]) for b in range(2) for x in e]
    refs = [_f2i(row[4 + k]) for k in range(_CHILDREN)]
    keys = []
    for k in range(_CHILDREN):
        key = (_f2i(s[k]) & _KEY_MASK) | k
        ok = (s[k] <= e[k]) & (refs[k] != _EMPTY) & (key > last)
        keys.append(jnp.where(ok, key, _NO_KEY))
    first = functools.reduce(jnp.minimum, keys)
    second = functools.reduce(jnp.minimum, [jnp.where(x == first, _NO_KEY, x) for x in keys])
    k = first & 7
    child = _pick(k, refs)
    child_s, child_e = t0, t1
    for a in range(3):
        bit = (k & (1 << a)) != 0
        child_s = jnp.maximum(child_s, jnp.where(bit, starts[a][1], starts[a][0]))
        child_e = jnp.minimum(child_e, jnp.where(bit, ends[a][1], ends[a][0]))
    return first != _NO_KEY, second != _NO_KEY, first, second, child, child_s, child_e


def _as_entry(node, t0, t1, key, bound):
    return jnp.stack([node, _f2i(t0), _f2i(t1), key, _f2i(bound)], axis=1)


def traversal(structure) -> Traversal:
    """The engine traversal of an octree built by ``accel.octree``."""
    return make(structure.layout_value("leaf_bits"))


@functools.cache
def make(leaf_bits: int) -> Traversal:
    """The octree's :class:`jrt.engine.Traversal` for leaf references of ``leaf_bits``."""
    count_mask = (1 << leaf_bits) - 1

    def step(arrays, ray, state, best_t, top, has_top):
        node, t0, t1, last = state
        rows = arrays["nodes"][node]
        # Skipped when no lane's interval is live: all-zero is then every lane's answer.
        has_next, has_second, first, second, child, child_s, child_e = computed_once(
            jnp.any(t0 <= t1), _plan, ray, rows, t0, t1, last, best_t)
        leaf = has_next & (child < 0)
        descend = has_next & (child >= 0)
        stay = leaf & has_second  # the leaf goes to the engine; the cell continues
        pop = ~(descend | stay)
        code = ~jnp.where(leaf, child, -1)
        leaf_first = code >> leaf_bits
        leaf_count = jnp.where(leaf, code & count_mask, 0)

        top_node, top_t0, top_t1, top_key = top[:, 0], _i2f(top[:, 1]), _i2f(top[:, 2]), top[:, 3]
        top_bound = _i2f(top[:, 4])
        next_node = jnp.where(descend, child, jnp.where(stay, node, top_node))
        next_t0 = jnp.where(descend, child_s, jnp.where(stay, t0, top_t0))
        next_t1 = jnp.where(descend, child_e, jnp.where(stay, t1, top_t1))
        next_key = jnp.where(descend, -1, jnp.where(stay, first, top_key))
        # The pushed entry resumes after `first`; its next child starts at or after the
        # distance in `second`'s key (truncated by at most 7 ulps: a lower bound).
        second_s = _i2f(second & _KEY_MASK)
        bound = jnp.where(has_top, jnp.minimum(second_s, top_bound), second_s)
        finished = pop & has_top & (top_bound > best_t)
        return Step(
            state=(next_node, next_t0, next_t1, next_key), leaf_first=leaf_first,
            leaf_count=leaf_count, push=descend & has_second,
            entry=_as_entry(node, t0, t1, first, bound), pop=pop, finished=finished)

    return Traversal(start=_start, step=step, stack_width=5)
