"""A pinhole camera: one ray per pixel centre, from the eye (reverse light path, seed §2).

Rays start at the eye and go out through the image plane: by the principle of reverse
light path (seed, Théorème 2.2) they retrace, backwards, the light that reaches the eye.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from jrt.kernels import cross, dot

#: :func:`frame_mesh`'s default margin: the bounding sphere, 5 % larger, fits the view.
FRAME_MARGIN = 1.05


@dataclasses.dataclass(frozen=True)
class Camera:
    """Pinhole camera. Lengths in scene units, the field of view in degrees.

    Attributes:
        eye: position of the pinhole.
        target: the point the camera looks at (the image centre).
        up: a vector giving the image's up direction (need not be orthogonal to the view).
        vfov: vertical field of view, degrees, in (0, 180).
        width, height: image size in pixels.
    """

    eye: tuple[float, float, float]
    target: tuple[float, float, float]
    up: tuple[float, float, float] = (0.0, 1.0, 0.0)
    vfov: float = 35.0
    width: int = 640
    height: int = 480

    def __post_init__(self):
        for field in ("eye", "target", "up"):
            value = np.asarray(getattr(self, field), np.float64)
            if value.shape != (3,) or not np.all(np.isfinite(value)):
                raise ValueError(f"camera {field} must be 3 finite numbers, got {value.tolist()}")
            object.__setattr__(self, field, tuple(float(x) for x in value))
        if not 0.0 < float(self.vfov) < 180.0:
            raise ValueError(f"camera vfov must be in (0, 180) degrees, got {self.vfov}")
        for field in ("width", "height"):
            value = getattr(self, field)
            if int(value) != value or int(value) < 1:
                raise ValueError(f"camera {field} must be a positive integer, got {value}")
        forward = np.subtract(self.target, self.eye)
        if np.linalg.norm(forward) == 0:
            raise ValueError("camera eye and target must differ")
        if np.linalg.norm(np.cross(forward, self.up)) == 0:
            raise ValueError("camera up must not be parallel to the view direction")

    @property
    def num_rays(self) -> int:
        return int(self.width) * int(self.height)


def subpixel_offsets(spp: int) -> np.ndarray:
    """float32 [spp, 2]: stratified positions (x right, y down) in the unit pixel, the
    Hammersley points ``((i + 1/2) / spp, φ2(i) + 1/(2 spp) mod 1)`` with ``φ2`` the base-2
    radical inverse (Hammersley & Handscomb, *Monte Carlo Methods*, 1964; pbrt-v4 §8.6.2).
    Every column of width 1/spp holds one point, and for spp a power of two so does every
    row, and every cell of any power-of-two grid of spp cells (a (0, m, 2)-net): anti-aliasing
    whose error falls faster than random jitter's. One sample is the pixel centre."""
    if isinstance(spp, bool) or not isinstance(spp, int | np.integer) or spp < 1:
        raise ValueError(f"spp must be a positive integer, got {spp!r}")
    i = np.arange(spp, dtype=np.uint64)
    radical = np.zeros(spp, np.float64)
    scale, bits = 0.5, i.copy()
    while bits.any():
        radical += (bits & np.uint64(1)).astype(np.float64) * scale
        bits >>= np.uint64(1)
        scale /= 2
    x = (np.arange(spp) + 0.5) / spp
    y = (radical + 0.5 / spp) % 1.0
    return np.stack([x, y], axis=1).astype(np.float32)


@functools.partial(jax.jit, static_argnames=("width", "height"))
def _pinhole(eye, target, up, vfov, width: int, height: int, offsets=None):
    """Rays through ``offsets`` [S, 2] of every pixel (default its centre), pixel-major:
    [H * W * S, 3]. ``vfov`` in degrees, float32: every caller (the host's camera, the
    renderer's parameters) goes through the same float32 operations, so the rays agree
    bit for bit (a glass tree magnifies a one-ulp change of a camera ray)."""
    vfov_radians = vfov * jnp.float32(math.pi / 180)
    offsets = jnp.full((1, 2), 0.5, jnp.float32) if offsets is None else offsets
    forward = target - eye
    forward = forward / jnp.sqrt(dot(forward, forward))
    right = cross(forward, up)
    right = right / jnp.sqrt(dot(right, right))
    true_up = cross(right, forward)
    half_h = jnp.tan(vfov_radians / 2)
    half_w = half_h * (width / height)
    # Positions in the pixels; row 0 is the top of the image.
    x = ((jnp.arange(width, dtype=jnp.float32)[:, None] + offsets[:, 0]) / width * 2 - 1) * half_w
    y = (1 - (jnp.arange(height, dtype=jnp.float32)[:, None] + offsets[:, 1]) / height * 2
         ) * half_h  # [H, S]
    d = (
        forward[None, None, None, :]
        + x[None, :, :, None] * right[None, None, None, :]
        + y[:, None, :, None] * true_up[None, None, None, :]
    ).reshape(-1, 3)
    d = d / jnp.sqrt(dot(d, d))[:, None]
    return jnp.broadcast_to(eye, d.shape), d


def camera_rays(camera: Camera, spp: int = 1) -> tuple[Float[Array, "n 3"], Float[Array, "n 3"]]:
    """Origins and unit directions, float32 [height * width * spp, 3], row-major from the
    top left: one ray through each pixel's centre, or ``spp`` through its
    :func:`subpixel_offsets`, pixel by pixel."""
    f32 = lambda v: jnp.asarray(v, jnp.float32)  # noqa: E731
    return _pinhole(
        f32(camera.eye), f32(camera.target), f32(camera.up), f32(camera.vfov),
        width=int(camera.width), height=int(camera.height),
        offsets=None if spp == 1 else jnp.asarray(subpixel_offsets(spp)),
    )


def frame_mesh(
    vertices,
    width: int = 640,
    height: int = 480,
    vfov: float = 30.0,
    azimuth: float = 50.0,
    elevation: float = 20.0,
    margin: float = FRAME_MARGIN,
    up: tuple[float, float, float] = (0.0, 1.0, 0.0),
) -> Camera:
    """A camera that frames the whole bounding sphere of ``vertices`` [V, 3].

    The sphere has the bounding box's centre ``c`` and half its diagonal ``r``: it holds
    every vertex whatever the direction it is seen from. The eye looks at ``c`` from
    ``azimuth`` degrees around the up axis (0 looks along -z, from +z) and ``elevation``
    degrees above the horizon, at the distance ``d`` where the sphere, its radius times
    ``margin``, just fits the narrower of the two fields of view::

        sin(min(vfov / 2, hfov / 2)) = margin * r / d,   tan(hfov / 2) = tan(vfov / 2) * w / h

    (a sphere seen from ``d`` fills a cone of half-angle ``asin(r / d)``, and the image's
    pyramid holds the cone of its narrower half-angle). With ``margin >= 1`` every vertex
    projects inside the image, from every azimuth and elevation: every frame of a turntable
    about ``c`` frames the whole mesh. A margin below 1 zooms in and may crop. The default
    is a 3/4 view from slightly above, for a y-up mesh, with a 5 % margin.
    """
    if not (math.isfinite(margin) and margin > 0):
        raise ValueError(f"frame_mesh margin must be a positive number, got {margin}")
    v = np.asarray(vertices, np.float64)
    lo, hi = v.min(axis=0), v.max(axis=0)
    centre = (lo + hi) / 2
    radius = max(float(np.linalg.norm(hi - lo)) / 2, 1e-12)
    half_v = math.radians(vfov) / 2
    half_h = math.atan(math.tan(half_v) * width / height)
    distance = radius * margin / math.sin(min(half_v, half_h))
    az, el = math.radians(azimuth), math.radians(elevation)
    offset = np.array([math.cos(el) * math.sin(az), math.sin(el), math.cos(el) * math.cos(az)])
    if tuple(up) != (0.0, 1.0, 0.0):
        raise ValueError("frame_mesh places the eye for a y-up mesh; pass a Camera yourself")
    return Camera(
        eye=tuple(centre + distance * offset), target=tuple(centre), up=up, vfov=vfov,
        width=width, height=height,
    )
