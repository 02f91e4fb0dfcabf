"""Controlling what XLA:CPU fuses: values materialised once for all their readers."""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax import lax


def computed_once(any_lane, fn, *args, always: bool = False):
    """``fn(*args)`` (a pytree of [L] arrays), materialised once for all its readers.

    XLA:CPU copies cheap elementwise producers into every fusion that reads them: the
    slab tests of a BVH step were recomputed in seven fusions, the triangle kernel in
    six. ``lax.optimization_barrier`` is removed before fusion on CPU; the boundary of a
    conditional is not. ``any_lane`` (a bool scalar) also skips the work when no lane
    needs it; the values are then garbage that no lane reads. A predicate that is always
    true but that XLA cannot fold (the engine's ``iteration >= 0``) only materialises.
    ``always=True`` computes ``fn`` in both branches, so that the predicate, whatever it
    is (XLA may fold it), never changes the values.
    """
    if always:
        return lax.cond(any_lane, fn, fn, *args)
    out_shape = jax.eval_shape(fn, *args)
    return lax.cond(any_lane, fn,
                    lambda *_: jax.tree.map(lambda a: jnp.zeros(a.shape, a.dtype), out_shape),
                    *args)
