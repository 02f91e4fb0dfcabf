"""Makes :class:`accel.Structure` a JAX pytree.

The arrays are leaves; ``kind`` and ``layout`` are static (they select and shape the
compiled traversal); ``stats`` is host-side and dropped by the flattening, so two builds
with the same layout and array shapes share one compiled kernel.
"""

from __future__ import annotations

import jax

from accel.structure import Structure


def _flatten_with_keys(s: Structure):
    names = tuple(sorted(s.arrays))
    children = tuple((jax.tree_util.DictKey(n), s.arrays[n]) for n in names)
    return children, (s.kind, names, s.layout)


def _unflatten(aux, children) -> Structure:
    kind, names, layout = aux
    return Structure(kind=kind, arrays=dict(zip(names, children, strict=True)), layout=layout)


jax.tree_util.register_pytree_with_keys(Structure, _flatten_with_keys, _unflatten)

