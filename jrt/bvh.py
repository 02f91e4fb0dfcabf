"""BVH traversal: the wide BVH's step on the shared engine (layout in ``accel.bvh``).

Near child first with a stack (a stackless traversal, measured, took 2.7x more steps and
ran 2x slower). The root's step is taken for every ray at once before the loop
(``Traversal.entry``: the root's row is one for all rays, so the step needs no gather): a
ray that enters none of the root's children takes no lane, and one that enters exactly
one starts there. A lane's state is the reference it visits next and the distance at
which its box was entered. A stack entry is a reference and the smallest entry distance
of itself and of every entry below it (a prefix minimum, taken when it is pushed): the
stack is not sorted by distance (a child's pushed sibling may lie beyond an ancestor's),
but with the prefix minimum a lane that must pop while its closest hit lies before every
entry left stops at once, instead of popping them one step each. On the camel that cut
the steps per ray by 8 % (camera rays) and 12 % (incoherent rays) at width 4. A popped
entry's distance is that lower bound, so a lane may step into a node it could have
skipped, never skip one it needs. One step at an interior node
gathers the node's row (the quantised boxes of its ``W`` children, decoded with a shift,
a mask and a multiply-add each), tests every box against
``[0, best_t]``, sorts the children it enters by entry distance, goes to the nearest and
pushes the others, farthest first, in one write (``Traversal.max_push = W - 1``). A
nearest child that is a leaf is handed to the engine's leaf loop at once and the step goes
to the next nearest, so a leaf costs no step of its own unless it was pushed.

The sort is a sorting network (Knuth, TAOCP vol. 3, 5.3.4: 1 comparator for 2 keys, 5
for 4, 19 for 8) on one [L] vector per child, farthest first with the children missed
last, so the entries to push are the first ones, in the order they must be pushed.
"""

from __future__ import annotations

import functools

import jax.numpy as jnp
from jax import lax

from accel.bvh import EMPTY_SLOT, FRAME_WORDS, QUANT_MAX, reference_column
from jrt.engine import ENTRY_MISS, Step, Traversal, box_interval
from jrt.fusion import computed_once

#: Comparators (i, j) of optimal sorting networks by input count (Knuth, TAOCP 5.3.4).
SORTING_NETWORKS = {
    2: ((0, 1),),
    4: ((0, 1), (2, 3), (0, 2), (1, 3), (1, 2)),
    8: ((0, 2), (1, 3), (4, 6), (5, 7), (0, 4), (1, 5), (2, 6), (3, 7), (0, 1), (2, 3),
        (4, 5), (6, 7), (2, 4), (3, 5), (1, 4), (3, 6), (1, 2), (3, 4), (5, 6)),
}


def _start(arrays, ray, first):
    """A fresh lane visits ``first`` (the root, or the one root child its ray enters)."""
    return first, jnp.full(ray.tmax.shape, -jnp.inf, jnp.float32)


def _pick(index, values):
    """``values[index]`` per lane from a short list of [L] vectors (selects, no gather)."""
    out = values[-1]
    for k in range(len(values) - 2, -1, -1):
        out = jnp.where(index == k, values[k], out)
    return out


def node_columns(nodes, refs):
    """``nodes[refs].T``: each lane's node row, gathered word by word into [words, L].

    The box tests read every word as an [L] vector. Gathered as rows [L, words] and
    transposed in the readers, each of the ``W`` box-test kernels read its words with a
    stride of a row (XLA:CPU fuses the transpose into them); gathered with the lanes
    last, the gather writes each word's [L] vector once and the tests read them
    contiguously (paired 1M-ray calls on the camel, four runs of 12-16 rounds: incoherent
    rays 1.03-1.11x, camera rays 1.00-1.06x). A row's words still come from one cache
    line. Indices are clipped, as ``nodes[refs]`` clips them: a corrupt reference reads a node
    of the array, never memory beyond it (the engine's iteration budget then stops it).
    """
    return lax.gather(
        nodes, refs[:, None],
        lax.GatherDimensionNumbers(offset_dims=(0,), collapsed_slice_dims=(0,),
                                   start_index_map=(0,)),
        slice_sizes=(1, nodes.shape[1]), mode=lax.GatherScatterMode.CLIP)


def traversal(structure) -> Traversal:
    """The engine traversal of a BVH built by ``accel.bvh``."""
    return make(structure.layout_value("leaf_bits"), structure.layout_value("width"))


@functools.cache
def make(leaf_bits: int, width: int) -> Traversal:
    """The BVH's :class:`jrt.engine.Traversal` for ``width``-wide nodes."""
    count_mask = (1 << leaf_bits) - 1
    network = SORTING_NETWORKS[width]

    def decode(ref):
        code = ~ref
        return code >> leaf_bits, code & count_mask

    first_ref = reference_column(width)

    def child_keys(ray, rows, best_t):
        """Per child: the sort key (minus the entry distance, +inf if missed) and ref."""
        row = rows  # [words, L]: one [L] vector per word (see node_columns)
        origin = [lax.bitcast_convert_type(row[a], jnp.float32) for a in range(3)]
        scale = [lax.bitcast_convert_type(row[3 + a], jnp.float32) for a in range(3)]

        def bound(field, child):
            """``origin + q * scale`` of the field's byte (accel.bvh's layout): q * scale is
            exact, so a fused multiply-add rounds the same as the build's check."""
            byte = field * width + child
            q = (row[FRAME_WORDS + byte // 4] >> (8 * (byte % 4))) & QUANT_MAX
            return origin[field % 3] + q.astype(jnp.float32) * scale[field % 3]

        keys, refs = [], []
        for k in range(width):
            near, far = box_interval(ray, [bound(a, k) for a in range(3)],
                                     [bound(3 + a, k) for a in range(3)])
            ref = row[first_ref + k]
            enter = (near <= far) & (near <= best_t) & (ref != EMPTY_SLOT)
            keys.append(jnp.where(enter, -near, jnp.inf))
            refs.append(ref)
        return keys, refs

    def sort(keys, refs, below):
        """Farthest entered child first, missed children last; how many entered; and the
        bound each of the first ``width - 1`` would be pushed with (its entry distance or
        ``below``, the smallest under the old top, whichever is less), as int32 bits."""
        keys, refs = list(keys), list(refs)
        for i, j in network:
            swap = keys[j] < keys[i]
            keys[i], keys[j] = jnp.where(swap, keys[j], keys[i]), jnp.where(swap, keys[i], keys[j])
            refs[i], refs[j] = jnp.where(swap, refs[j], refs[i]), jnp.where(swap, refs[i], refs[j])
        entered = sum((key < jnp.inf).astype(jnp.int32) for key in keys)
        bounds = [lax.bitcast_convert_type(jnp.minimum(-keys[k], below), jnp.int32)
                  for k in range(width - 1)]
        return keys, refs, entered, bounds

    def step(arrays, ray, state, best_t, top, has_top):
        ref, ref_t = state
        live = ref_t <= best_t  # a popped entry beyond the closest hit is skipped
        interior = live & (ref >= 0)
        leaf_here = live & (ref < 0)
        rows = node_columns(arrays["nodes"], jnp.maximum(ref, 0))
        # Two boundaries (jrt.fusion.computed_once): without the first, every output of
        # the sort recomputed every box test (measured 2x slower steps at width 4).
        any_interior = jnp.any(interior)
        top_ref, top_min = top[:, 0], lax.bitcast_convert_type(top[:, 1], jnp.float32)
        below = jnp.where(has_top, top_min, jnp.inf)
        keys, refs = computed_once(any_interior, child_keys, ray, rows, best_t)
        # The pushed entries' bounds come out of the sort's boundary as [L] vectors, so
        # that building the [L, W - 1, 2] entries is a plain interleave: computed inside
        # it, XLA:CPU emitted a scalar loop with a branch per element (6 % of a camera
        # call on an AVX2 host, perf).
        keys, refs, entered, bounds = computed_once(any_interior, sort, keys, refs, below)
        entered = jnp.where(interior, entered, 0)

        # The nearest entered child is the last entered one; a leaf there is emitted now.
        nearest = _pick(entered - 1, refs)
        first_is_leaf = (entered > 0) & (nearest < 0)
        emit = leaf_here | first_is_leaf
        leaf_first, leaf_count = decode(jnp.where(emit, jnp.where(leaf_here, ref, nearest), -1))
        leaf_count = jnp.where(emit, leaf_count, 0)

        # Go to the nearest child that is not emitted; push the ones before it.
        go_index = entered - 1 - first_is_leaf.astype(jnp.int32)
        go = go_index >= 0
        pushed = jnp.maximum(go_index, 0)
        # Entries are pushed farthest first, so each one's prefix minimum is the smaller
        # of its own distance and the minimum below the old top.
        entry = jnp.stack([jnp.stack([refs[k], bounds[k]], axis=1) for k in range(width - 1)],
                          axis=1)
        next_ref = jnp.where(go, _pick(go_index, refs), top_ref)
        next_t = jnp.where(go, -_pick(go_index, keys), top_min)
        return Step(
            state=(next_ref, next_t), leaf_first=leaf_first, leaf_count=leaf_count,
            push=pushed, entry=entry, pop=~go, finished=~go & has_top & (top_min > best_t))

    def entry(arrays, ray, best_t):
        """The root's step for every ray at once (``jrt.engine.Traversal.entry``): the
        root's row is broadcast, not gathered. A ray that enters none of the root's
        children cannot hit (``ENTRY_MISS``); one that enters exactly one starts there (a
        leaf is then emitted by its first step); the others start at the root. On the
        camel, 63 % of the camera rays enter none (52 % miss the mesh's box) and 27 %
        exactly one; 10 % and 48 % of the incoherent rays. (Going on to the root's
        children's rows by selects, a second level, made the pass 8 ms a 1M-ray call
        slower for 0.2-0.35 steps a ray fewer: 0.96-1.02x in paired calls.)"""
        root = jnp.asarray(arrays["nodes"])[0][:, None]  # [words, 1]: one row, every ray
        keys, refs = child_keys(ray, root, best_t)
        entered = [key < jnp.inf for key in keys]
        count = sum(e.astype(jnp.int32) for e in entered)
        only = sum(jnp.where(e, ref, 0) for e, ref in zip(entered, refs, strict=True))
        # A leaf reference is ~code with code < 2^31 - 1, never ENTRY_MISS.
        return jnp.where(count == 0, ENTRY_MISS,
                         jnp.where(count == 1, only, 0)).astype(jnp.int32)

    return Traversal(start=_start, step=step, stack_width=2, max_push=width - 1, entry=entry)
