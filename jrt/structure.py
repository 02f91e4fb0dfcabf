"""Makes :class:`accel.Structure` a JAX pytree.

The arrays are leaves; ``kind`` and ``layout`` are static (they select and shape the
compiled traversal); ``stats`` is host-side and dropped by the flattening, so two builds
with the same layout and array shapes share one compiled kernel.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from accel.structure import Structure


def _flatten_with_keys(s: Structure):
    names = tuple(sorted(s.arrays))
    children = tuple((jax.tree_util.DictKey(n), s.arrays[n]) for n in names)
    return children, (s.kind, names, s.layout)


def _unflatten(aux, children) -> Structure:
    kind, names, layout = aux
    return Structure(kind=kind, arrays=dict(zip(names, children, strict=True)), layout=layout)


jax.tree_util.register_pytree_with_keys(
    Structure, _flatten_with_keys, _unflatten, flatten_func=lambda s: (
        tuple(s.arrays[n] for n in sorted(s.arrays)),
        (s.kind, tuple(sorted(s.arrays)), s.layout),
    )
)


def to_device(structure: Structure) -> Structure:
    """The same record with its arrays as JAX arrays (the stats are kept)."""
    arrays = {k: jnp.asarray(v) for k, v in structure.arrays.items()}
    return Structure(structure.kind, arrays, structure.layout, structure.stats)
