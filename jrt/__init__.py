"""jrt: a JAX ray tracer.

Pure, jit-compiled JAX functions over arrays and pytrees. Acceleration structures are
built by the NumPy package :mod:`accel` and traversed here.
"""

import importlib as _importlib

from jrt import _xla  # (must run before JAX starts its backend)
from jrt._xla import ImportOrderWarning
from jrt.all_hits import AllHits, all_hits
from jrt.camera import Camera, camera_rays, frame_mesh
from jrt.data import camel_path, data_dir, mesh_path
from jrt.engine import Counters, StackOverflowError, TraversalError
from jrt.hits import Hits
from jrt.kernels import KERNELS, moller_trumbore, plane_barycentric, watertight
from jrt.mesh import Mesh, MeshError, MeshWarning, load_mesh, mesh_from_arrays
from jrt.normals import corner_normals
from jrt.programs import clear_caches
from jrt.refitting import refit
from jrt.trace import closest_hit, occluded

tune_malloc = _xla.tune_malloc

#: Submodules reached as attributes (``jrt.optics.fresnel``) without an import of their own,
#: loaded on first use (PEP 562): ``import jrt`` stays as light as it was.
_SUBMODULES = frozenset({"batch", "host_tree", "interaction", "normals", "optics", "params",
                         "render", "scene", "sky", "spectral", "trimesh", "wavefront",
                         "whitted"})


def __getattr__(name: str):
    if name in _SUBMODULES:
        return _importlib.import_module(f"jrt.{name}")
    raise AttributeError(f"module 'jrt' has no attribute {name!r}")


__all__ = [
    "KERNELS",
    "AllHits",
    "Camera",
    "Counters",
    "Hits",
    "ImportOrderWarning",
    "Mesh",
    "MeshError",
    "MeshWarning",
    "all_hits",
    "camel_path",
    "camera_rays",
    "clear_caches",
    "closest_hit",
    "corner_normals",
    "data_dir",
    "frame_mesh",
    "load_mesh",
    "mesh_from_arrays",
    "mesh_path",
    "moller_trumbore",
    "occluded",
    "plane_barycentric",
    "refit",
    "StackOverflowError",
    "TraversalError",
    "tune_malloc",
    "watertight",
]
