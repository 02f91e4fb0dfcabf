"""Scene assembly: a validated :class:`Scene` into arrays the renderers consume.

:func:`assemble` loads each object's mesh, places it (scale, rotation, translation:
:meth:`Object.transform`), computes its corner normals with its crease angle
(:func:`jrt.normals.corner_normals`), appends the floor (:func:`floor_quad`), and resolves
the automatic camera (:func:`jrt.camera.frame_mesh`) and lamp (:func:`default_lamp`).
NumPy only; building the acceleration structure over the result is the renderer's step
(``accel.build(scene.settings.accel, geometry.vertices, geometry.faces)``).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from jrt.camera import Camera
from jrt.data import MESHES, camel_path
from jrt.mesh import Mesh, MeshError, load_mesh, mesh_from_arrays
from jrt.normals import corner_normals
from jrt.scene.model import Features, Lamp, Material, Object, Scene, SceneError


def default_lamp(mesh: Mesh, camera: Camera) -> np.ndarray:
    """A lamp above the camera's left shoulder, well outside the mesh: float32 [3].

    With ``d`` the distance from the eye to the centre of the mesh's bounding box: the eye
    moved ``0.6 d`` to the left (against ``forward x up``) and ``1.2 d`` up (+y).
    """
    lo, hi = mesh.bounds
    centre = (lo + hi) / 2
    eye = np.asarray(camera.eye, np.float32)
    forward = centre - eye
    right = np.cross(forward, np.asarray(camera.up, np.float32))
    right /= np.linalg.norm(right)
    return (eye - 0.6 * np.linalg.norm(forward) * right
            + np.array([0, 1.2 * np.linalg.norm(forward), 0], np.float32)).astype(np.float32)


@dataclasses.dataclass(frozen=True, eq=False)
class SceneGeometry:
    """A scene as arrays: every object transformed, the floor appended (last two faces).

    Attributes:
        mesh: the whole scene as one validated :class:`jrt.Mesh` (float32 vertices [V, 3],
            int32 faces [F, 3]); build the acceleration structure over it.
        material_of_face: int32 [F], index into ``materials`` of each face.
        normals: float32 [F, 3, 3], the shading normal of each face's corners
            (:func:`jrt.normals.corner_normals` of each object with its ``crease_angle``;
            the floor flat).
        materials: the scene's materials, in index order.
        lamps: the lamps, each with its position resolved.
        camera: the resolved :class:`jrt.Camera`.
        object_faces: ``(start, stop)`` face range of each object, then of the floor.
        features: ``scene.features()``.
    """

    mesh: Mesh
    material_of_face: np.ndarray
    normals: np.ndarray
    materials: tuple[Material, ...]
    lamps: tuple[Lamp, ...]
    camera: Camera
    object_faces: tuple[tuple[int, int], ...]
    features: Features

    @property
    def vertices(self) -> np.ndarray:
        return self.mesh.vertices

    @property
    def faces(self) -> np.ndarray:
        return self.mesh.faces

    @property
    def lamp_positions(self) -> np.ndarray:
        """float32 [L, 3]."""
        return np.asarray([lamp.position for lamp in self.lamps], np.float32).reshape(-1, 3)

    @property
    def lamp_intensities(self) -> np.ndarray:
        """float32 [L]."""
        return np.asarray([lamp.intensity for lamp in self.lamps], np.float32)


def _load_object_mesh(obj: Object) -> Mesh:
    return load_mesh(camel_path(obj.mesh) if obj.mesh in MESHES else obj.mesh)


def floor_quad(lo, hi, extent: float, gap: float) -> tuple[np.ndarray, np.ndarray]:
    """float64 [4, 3] corners and int [2, 3] faces (normal +y) of the floor under the box
    ``lo``..``hi`` (see :class:`Floor`)."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    centre = (lo + hi) / 2
    half = extent * max(float(hi[0] - lo[0]), float(hi[2] - lo[2]), 1e-12) / 2
    y = lo[1] - gap * float(np.linalg.norm(hi - lo))
    x0, x1, z0, z1 = centre[0] - half, centre[0] + half, centre[2] - half, centre[2] + half
    corners = np.array([[x0, y, z0], [x1, y, z0], [x1, y, z1], [x0, y, z1]])
    # (a, d, c) and (a, c, b): (d - a) x (c - a) = (0, dz dx, 0), pointing up.
    return corners, np.array([[0, 3, 2], [0, 2, 1]])


def assemble(scene: Scene) -> SceneGeometry:
    """Load, transform and concatenate the scene's meshes; resolve the camera and lamps.

    Raises :class:`SceneError` for a mesh that fails :func:`jrt.load_mesh`'s validation,
    FileNotFoundError when the camel data cannot be found.
    """
    vertices, faces, material, ranges, normals = [], [], [], [], []
    loaded: dict[str, Mesh] = {}
    count = 0  # vertices so far
    for i, obj in enumerate(scene.objects):
        try:
            if obj.mesh not in loaded:
                loaded[obj.mesh] = _load_object_mesh(obj)
        except MeshError as exc:
            raise SceneError(f"{scene.source}: objects[{i}].mesh: {exc}") from exc
        mesh = loaded[obj.mesh]
        start = sum(len(f) for f in faces)
        vertices.append(obj.transform(mesh.vertices))
        normals.append(corner_normals(vertices[-1], mesh.faces, obj.crease_angle))
        faces.append(mesh.faces.astype(np.int64) + count)
        material.append(np.full(len(mesh.faces), scene.material_index(obj.material)))
        ranges.append((start, start + len(mesh.faces)))
        count += len(mesh.vertices)
    try:
        objects = mesh_from_arrays(np.concatenate(vertices), np.concatenate(faces),
                                   name=f"{scene.name} (objects)")
    except MeshError as exc:  # e.g. a scale that underflows float32
        raise SceneError(f"{scene.source}: objects: {exc}") from exc
    camera = scene.camera.resolve(objects.vertices)
    lamps = tuple(
        lamp if lamp.position is not None else dataclasses.replace(
            lamp, position=tuple(float(x) for x in default_lamp(objects, camera)))
        for lamp in scene.lamps
    )
    if scene.floor is not None:
        lo, hi = objects.bounds
        corners, quad = floor_quad(lo, hi, scene.floor.extent, scene.floor.gap)
        start = len(objects.faces)
        vertices.append(corners)
        faces.append(quad + count)
        normals.append(corner_normals(corners, quad, 0.0))
        material.append(np.full(2, scene.material_index(scene.floor.material)))
        ranges.append((start, start + 2))
    whole = mesh_from_arrays(np.concatenate(vertices), np.concatenate(faces),
                             name=scene.name) if scene.floor is not None else objects
    return SceneGeometry(
        mesh=whole,
        material_of_face=np.concatenate(material).astype(np.int32),
        normals=np.concatenate(normals).astype(np.float32),
        materials=scene.materials,
        lamps=lamps,
        camera=camera,
        object_faces=tuple(ranges),
        features=scene.features(),
    )


__all__ = ["SceneGeometry", "assemble", "default_lamp", "floor_quad"]
