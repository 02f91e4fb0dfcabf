"""Automatic framing (jrt.camera.frame_mesh): every vertex in the picture, from every side.

The projection is recomputed here in float64 from the camera's own record (eye, target,
up, vfov, width, height) by the pinhole model the camera documents: a point is in the
picture when its coordinates along the image's right and true-up axes, divided by its
depth along the view, lie within ``tan(vfov / 2) * width / height`` and ``tan(vfov / 2)``.
"""

from __future__ import annotations

import itertools
import math
from types import SimpleNamespace

import numpy as np
import pytest
import trimesh

from jrt import Camera, frame_mesh
from jrt.camera import camera_rays


def _extent_in_view(camera: Camera, points) -> float:
    """The largest of |x| / half_width and |y| / half_height over ``points`` [N, 3] (<= 1:
    all inside the picture), in float64; infinite if a point is not in front of the eye."""
    eye, target = np.asarray(camera.eye), np.asarray(camera.target)
    forward = (target - eye) / np.linalg.norm(target - eye)
    right = np.cross(forward, camera.up)
    right /= np.linalg.norm(right)
    true_up = np.cross(right, forward)
    rel = np.asarray(points, np.float64) - eye
    depth = rel @ forward
    if depth.min() <= 0:
        return math.inf
    half_h = math.tan(math.radians(camera.vfov) / 2)
    half_w = half_h * camera.width / camera.height
    x, y = rel @ right / depth, rel @ true_up / depth
    return float(max(np.abs(x).max() / half_w, np.abs(y).max() / half_h))


def _tall_thin() -> np.ndarray:
    """A 0.1 x 3 x 0.1 box's corners, away from the origin."""
    box = trimesh.creation.box(extents=(0.1, 3.0, 0.1))
    return np.asarray(box.vertices) + [2.0, -1.0, 0.5]


def _meshes(camel19k):
    wide = trimesh.creation.box(extents=(4.0, 0.2, 1.0)).vertices
    return {"camel-19k": camel19k.vertices, "tall thin box": _tall_thin(),
            "wide flat box": np.asarray(wide)}


@pytest.fixture(scope="module")
def camel19k():
    from jrt import camel_path, load_mesh

    return load_mesh(camel_path("camel-19k"))


SIZES = ((640, 480), (240, 320), (100, 100), (400, 60), (60, 400))
AZIMUTHS = (0.0, 50.0, 90.0, 137.0, 180.0, 270.0, 333.0)
ELEVATIONS = (-60.0, 0.0, 20.0, 75.0)


def test_every_vertex_projects_inside_the_image_from_every_side(camel19k):
    for name, vertices in _meshes(camel19k).items():
        for (w, h), az, el in itertools.product(SIZES, AZIMUTHS, ELEVATIONS):
            for vfov in (20.0, 60.0):
                camera = frame_mesh(vertices, width=w, height=h, vfov=vfov, azimuth=az,
                                    elevation=el)
                extent = _extent_in_view(camera, vertices)
                assert extent <= 1.0, (name, w, h, az, el, vfov, extent)


def test_every_turntable_frame_shows_the_whole_mesh(camel19k):
    """jrt.batch.turntable turns the eye about the framed target: the bounding sphere stays
    in view in every frame (a stand-in for a prepared scene: only its camera is read)."""
    from jrt.batch import turntable

    for name, vertices in _meshes(camel19k).items():
        for w, h in ((96, 72), (40, 120)):
            setup = SimpleNamespace(camera=lambda width, height, v=vertices: frame_mesh(
                v, width=width, height=height, azimuth=50.0, elevation=20.0))
            cameras = turntable(setup, 12, width=w, height=h)
            assert len(cameras) == 12 and len({c.eye for c in cameras}) == 12
            for i, camera in enumerate(cameras):
                assert _extent_in_view(camera, vertices) <= 1.0, (name, w, h, i)


def test_the_tall_box_fills_the_narrow_side_and_the_old_margin_cropped_it():
    v = _tall_thin()
    # Seen side-on, the box's diagonal is nearly its height: the sphere's diameter.
    camera = frame_mesh(v, width=320, height=240, azimuth=0.0, elevation=0.0)
    assert 0.85 < _extent_in_view(camera, v) <= 1.0
    # A margin below 1 zooms into the sphere and crops the top and bottom.
    tight = frame_mesh(v, width=320, height=240, azimuth=0.0, elevation=0.0, margin=0.85)
    assert _extent_in_view(tight, v) > 1.0


def test_the_projection_agrees_with_the_camera_rays():
    """The reference projection above is the camera's: the ray through the centre of the
    top-right pixel, extended, projects to that pixel centre."""
    camera = frame_mesh(_tall_thin(), width=8, height=6, azimuth=30.0, elevation=10.0)
    origins, directions = camera_rays(camera)
    point = np.asarray(origins)[7] + 5.0 * np.asarray(directions)[7].astype(np.float64)
    # Pixel (row 0, column 7) has its centre at x = 7.5/8 * 2 - 1, y = 1 - 0.5/6 * 2.
    eye = np.asarray(camera.eye)
    forward = np.asarray(camera.target) - eye
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, camera.up)
    right /= np.linalg.norm(right)
    true_up = np.cross(right, forward)
    rel = point - eye
    half_h = math.tan(math.radians(camera.vfov) / 2)
    x = rel @ right / (rel @ forward) / (half_h * 8 / 6)
    y = rel @ true_up / (rel @ forward) / half_h
    np.testing.assert_allclose([x, y], [7.5 / 8 * 2 - 1, 1 - 0.5 / 6 * 2], atol=1e-5)


def test_bad_margin_is_refused():
    for bad in (0.0, -1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="margin"):
            frame_mesh(_tall_thin(), margin=bad)
