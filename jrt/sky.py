"""The sky: the background every renderer shows where a ray meets nothing.

A vertical gradient from :data:`SKY_TOP` (zenith) to :data:`SKY_BOTTOM` (nadir), linear
sRGB. Its blue channel always exceeds its red one, while the (warm) camel's red exceeds its
blue: :func:`jrt.render.silhouette` tells the mesh from the sky by that alone.

* :func:`sky_rgb` sees it along ray directions, with the weight :func:`direction_weight`
  ``w = (1 - d_y) / 2``, so that reflected and refracted rays see it too (:mod:`jrt.whitted`);
* :func:`sky_rgb_by_row` spreads it over the image rows instead, with the weight
  :func:`row_weights` (:mod:`jrt.render`'s camera rays: top row ``w = 0``, bottom row
  ``w = 1``);
* :func:`sky_blend` mixes its two ends, ``top (1 - w) + bottom w``: in RGB, or over a
  renderer's channels once the ends are turned into them.
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, Float

#: Linear sRGB of the sky at the zenith (and the image's top row).
SKY_TOP = (0.38, 0.55, 0.80)
#: Linear sRGB of the sky at the nadir (and the image's bottom row).
SKY_BOTTOM = (0.80, 0.86, 0.94)


def sky_blend(top: Float[Array, "*#batch c"], bottom: Float[Array, "*#batch c"],
              w: Float[Array, "*#batch 1"]) -> Float[Array, "*batch c"]:
    """``top (1 - w) + bottom w``: the sky between its two ends at weight ``w`` in [0, 1]."""
    return top * (1 - w) + bottom * w


def direction_weight(directions: Float[Array, "*batch 3"]) -> Float[Array, " *batch"]:
    """The sky's weight along unit ``directions``: ``(1 - d_y) / 2`` clipped to [0, 1], 0
    straight up, 1 straight down."""
    return jnp.clip((1 - directions[..., 1]) / 2, 0, 1)


def row_weights(height: int, width: int) -> Float[Array, " pixels"]:
    """The sky's weight at each pixel of a ``height`` x ``width`` image, row-major: its row
    over ``height - 1`` (0 on the top row, 1 on the bottom one)."""
    # Explicit float32 and int32: the same values, and float32 under jax_enable_x64 too.
    return ((jnp.arange(height * width, dtype=jnp.int32) // width).astype(jnp.float32)
            / max(height - 1, 1))


def _ends() -> tuple[Float[Array, " 3"], Float[Array, " 3"]]:
    # Explicit float32: the same values, and float32 under jax_enable_x64 too.
    return jnp.asarray(SKY_TOP, jnp.float32), jnp.asarray(SKY_BOTTOM, jnp.float32)


def sky_rgb(directions: Float[Array, "*batch 3"]) -> Float[Array, "*batch 3"]:
    """Linear sRGB of the sky seen along unit ``directions`` (float32)."""
    d = jnp.asarray(directions, jnp.float32)
    return sky_blend(*_ends(), direction_weight(d)[..., None])


def sky_rgb_by_row(height: int, width: int) -> Float[Array, "pixels 3"]:
    """Linear sRGB of the sky at each pixel of a ``height`` x ``width`` image, row-major,
    by its row (:func:`row_weights`), float32."""
    return sky_blend(*_ends(), row_weights(height, width)[:, None])


__all__ = ["SKY_BOTTOM", "SKY_TOP", "direction_weight", "row_weights", "sky_blend", "sky_rgb",
           "sky_rgb_by_row"]
