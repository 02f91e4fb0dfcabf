"""The record every builder returns: flat NumPy arrays plus static metadata.

`accel` never imports JAX. `jrt` registers :class:`Structure` as a JAX pytree
(see ``jrt.structure``): the arrays are the leaves, ``kind`` and ``layout`` are
static (they change the compiled code), and ``stats`` stays on the host (it is
dropped when the record goes through a JAX transformation, so that two builds
of the same layout share one compiled kernel).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

import numpy as np


@dataclasses.dataclass(frozen=True)
class Structure:
    """An acceleration structure flattened to arrays.

    Attributes:
        kind: the builder's name (``"brute"``, ``"bvh"``, ...); selects the traversal step.
        arrays: name -> array; every array the traversal reads. Triangles are stored
            once, as ``triangles`` float32 [T, 3, 3] (vertex k of triangle i is
            ``triangles[i, k]``) with ``triangle_ids`` int32 [T], the index of each row in
            the mesh's face list. Degenerate (zero-area) faces are left out, so they are
            never hit.
        layout: static constants of the layout as sorted (name, value) pairs (hashable).
        stats: host-side build statistics (build time, bytes, counts); not a pytree leaf.
    """

    kind: str
    arrays: Mapping[str, np.ndarray]
    layout: tuple[tuple[str, Any], ...] = ()
    stats: Mapping[str, Any] = dataclasses.field(default_factory=dict, compare=False)

    def __getitem__(self, name: str) -> np.ndarray:
        return self.arrays[name]

    @property
    def num_triangles(self) -> int:
        """Triangles the structure can hit (degenerate ones are left out)."""
        return int(self.arrays["triangle_ids"].shape[0])

    @property
    def nbytes(self) -> int:
        """Bytes of all arrays together."""
        return int(sum(np.asarray(a).nbytes for a in self.arrays.values()))

    def layout_value(self, name: str) -> Any:
        return dict(self.layout)[name]
