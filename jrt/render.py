"""A first renderer: Lambert shading, one point lamp, hard shadows by any-hit rays.

Camera rays start at the eye (reverse light path, seed Théorème 2.2). At a hit, the
shading normal interpolates the hit triangle's corner normals
(:func:`jrt.normals.corner_normals`: smooth across edges below the crease angle, sharp
across the others) with the hit's barycentrics ``(1-u-v, u, v)``; a shadow ray goes from
the hit point toward the lamp and stops at the first triangle it meets (``jrt.occluded``).
The pixel is ``albedo * (ambient + (1 - ambient) * max(0, n·l))`` when the lamp is
visible, ``albedo * ambient`` in shadow. The background is :mod:`jrt.sky`'s vertical
gradient over the image rows, whose blue channel always exceeds its red one, while the
(warm) camel's red exceeds its blue: a pixel belongs to the mesh iff red > blue, which the
tests use.
"""

from __future__ import annotations

import dataclasses
import time

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from accel.structure import Structure
from jrt.camera import Camera, camera_rays
from jrt.hits import Hits
from jrt.interaction import face_forward, surface_interaction
from jrt.kernels import DEFAULT_KERNEL, dot
from jrt.mesh import Mesh
from jrt.normals import DEFAULT_CREASE_ANGLE, corner_normals
from jrt.scene.assembly import default_lamp
from jrt.sky import sky_rgb_by_row
from jrt.trace import closest_hit, occluded

ALBEDO = (0.86, 0.68, 0.46)  # sand


@dataclasses.dataclass(frozen=True)
class RenderStats:
    width: int
    height: int
    primary_rays: int
    shadow_rays: int
    seconds: float

    @property
    def rays(self) -> int:
        return self.primary_rays + self.shadow_rays

    @property
    def mrays_per_second(self) -> float:
        return self.rays / self.seconds / 1e6

    def summary(self) -> str:
        return (
            f"{self.width}x{self.height}: {self.primary_rays:,} camera rays + "
            f"{self.shadow_rays:,} shadow rays in {self.seconds:.2f} s "
            f"({self.mrays_per_second:.3f} Mrays/s)"
        )


@jax.jit
def _shade_points(hits: Hits, origins, directions, faces, vertices, normals, lamp):
    """Hit points, shading normals, geometric normals and the direction to the lamp."""
    hit = hits.triangle >= 0
    surface = surface_interaction(vertices, faces, hits.triangle, hits.u, hits.v, directions,
                                  normals)
    point = surface.point
    # Face the viewer: both normals point back against the incoming ray.
    ng = face_forward(surface.geometric_normal, -directions)
    n = face_forward(surface.shading_normal, ng)
    to_lamp = lamp[None, :] - point
    dist = jnp.sqrt(dot(to_lamp, to_lamp))
    l = to_lamp / dist[:, None]
    return hit, point, n, ng, l, dist


def _compose(hit, n, l, lit, ambient, height, width):
    lambert = jnp.maximum(dot(n, l), 0.0) * lit
    shade = ambient + (1 - ambient) * lambert
    # Explicit float32: the same values, and float32 under jax_enable_x64 too.
    colour = jnp.asarray(ALBEDO, jnp.float32)[None, :] * shade[:, None]
    image = jnp.where(hit[:, None], colour, sky_rgb_by_row(height, width))
    return image.reshape(height, width, 3)


def render_lambert(
    mesh: Mesh,
    structure: Structure,
    camera: Camera,
    lamp: Float[Array, 3] | None = None,
    ambient: float = 0.15,
    kernel: str = DEFAULT_KERNEL,
    shadows: bool = True,
    crease_angle: float = DEFAULT_CREASE_ANGLE,
) -> tuple[np.ndarray, RenderStats]:
    """Render ``mesh`` (traced through ``structure``) seen by ``camera``.

    ``crease_angle`` (degrees, [0, 180]): edges whose faces meet at a larger angle shade
    sharp, the others smooth (:func:`jrt.normals.corner_normals`; 0 flat, 180 all smooth).

    Returns:
        image: float32 [height, width, 3] in [0, 1], linear.
        stats: ray counts and timing (traversal and shading, compile time excluded only
            if the same shapes were rendered before).
    """
    if not 0.0 <= ambient <= 1.0:
        raise ValueError(f"ambient must be in [0, 1], got {ambient}")
    lamp = default_lamp(mesh, camera) if lamp is None else np.asarray(lamp, np.float32)
    if lamp.shape != (3,) or not np.all(np.isfinite(lamp)):
        raise ValueError(f"lamp must be 3 finite numbers, got {lamp!r}")
    normals = jnp.asarray(corner_normals(mesh.vertices, mesh.faces, crease_angle))
    faces = jnp.asarray(mesh.faces)
    vertices = jnp.asarray(mesh.vertices)
    start = time.perf_counter()
    origins, directions = camera_rays(camera)
    hits = closest_hit(structure, origins, directions, kernel=kernel)
    hit, point, n, ng, l, dist = _shade_points(
        hits, origins, directions, faces, vertices, normals, jnp.asarray(lamp)
    )
    shadow_rays = 0
    if shadows:
        # Leave the surface along the geometric normal, on the lamp's side, by a small
        # multiple of the scene size, so that the shadow ray does not hit its own triangle.
        side = jnp.where(dot(ng, l) >= 0, 1.0, -1.0)[:, None]
        eps = 1e-4 * mesh.diagonal
        shadow_origin = point + side * ng * eps
        # Shadow rays only for the pixels that see the mesh and face the lamp, padded to a
        # multiple of 4096 so that similar views reuse the compiled query.
        wanted = np.flatnonzero(np.asarray(hit & (dot(ng, l) > 0)))
        shadow_rays = int(wanted.size)
        padded = np.zeros(-(-max(shadow_rays, 1) // 4096) * 4096, np.int32)
        padded[:shadow_rays] = wanted
        blocked = occluded(structure, shadow_origin[padded], l[padded], tmax=dist[padded],
                           kernel=kernel)[:shadow_rays]
        lit = jnp.zeros(hit.shape, jnp.float32).at[wanted].set(jnp.where(blocked, 0.0, 1.0))
    else:
        lit = jnp.where(hit, 1.0, 0.0)
    image = _compose(hit, n, l, lit, ambient, camera.height, camera.width)
    image = np.asarray(jax.block_until_ready(image))
    seconds = time.perf_counter() - start
    stats = RenderStats(camera.width, camera.height, camera.num_rays, shadow_rays, seconds)
    return image, stats


def to_srgb8(image: np.ndarray) -> np.ndarray:
    """uint8 sRGB from linear [0, 1] (IEC 61966-2-1 transfer function)."""
    x = np.clip(image, 0.0, 1.0)
    srgb = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
    return np.round(srgb * 255).astype(np.uint8)


def silhouette(rgb8: np.ndarray) -> np.ndarray:
    """bool [H, W]: the pixels that show the mesh (red above blue, see the module doc)."""
    rgb = rgb8.astype(np.int16)
    return rgb[..., 0] > rgb[..., 2]
