"""jrt: a JAX ray tracer.

Pure, jit-compiled JAX functions over arrays and pytrees. Acceleration structures are
built by the NumPy package :mod:`accel` and traversed here.
"""

from jrt import _xla  # (must run before JAX starts its backend)
from jrt.camera import Camera, camera_rays, frame_mesh
from jrt.data import camel_path, data_dir
from jrt.hits import Hits
from jrt.kernels import KERNELS, moller_trumbore, plane_barycentric, watertight
from jrt.mesh import Mesh, MeshError, load_mesh, mesh_from_arrays
from jrt.trace import closest_hit, occluded

tune_malloc = _xla.tune_malloc

__all__ = [
    "KERNELS",
    "Camera",
    "Hits",
    "Mesh",
    "MeshError",
    "camel_path",
    "camera_rays",
    "closest_hit",
    "data_dir",
    "frame_mesh",
    "load_mesh",
    "mesh_from_arrays",
    "moller_trumbore",
    "occluded",
    "plane_barycentric",
    "tune_malloc",
    "watertight",
]
