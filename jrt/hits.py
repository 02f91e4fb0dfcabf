"""The hit record shared by every traversal."""

from __future__ import annotations

from typing import NamedTuple

from jaxtyping import Array, Float, Int


class Hits(NamedTuple):
    """Closest hits of a batch of rays.

    Attributes:
        t: float32 [N], distance along the unit direction; ``+inf`` for a miss.
        triangle: int32 [N], index into the mesh's faces; ``-1`` for a miss.
        u, v: float32 [N], barycentrics: the point is ``(1-u-v) v0 + u v1 + v v2``; 0 for a miss.
    """

    t: Float[Array, " n"]
    triangle: Int[Array, " n"]
    u: Float[Array, " n"]
    v: Float[Array, " n"]
