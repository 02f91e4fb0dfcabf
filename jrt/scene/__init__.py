"""Scenes: TOML files (or built-in names) into a validated, frozen description, and from it
the static features that decide what the renderer compiles and the arrays it renders.

NumPy side only: nothing here is traced by JAX, and no renderer is imported. The way in is
:func:`load_scene`; the way to arrays is :func:`assemble`; ``scene.features()`` is a
hashable record meant as a static argument to ``jax.jit``.

The package's parts:

- :mod:`jrt.scene.model`: the dataclasses (:class:`Scene`, :class:`Material`, ...), the
  allowed ranges and :class:`SceneError`;
- :mod:`jrt.scene.toml_io`: the TOML schema, the reader that checks each field and names it
  in errors (:func:`load_scene`, :func:`parse_scene`), and the writer (``Scene.to_toml``);
- :mod:`jrt.scene.builtin_scenes`: the built-in scenes, ``jrt/scene/builtin/NAME.toml``;
- :mod:`jrt.scene.assembly`: meshes placed, normals, floor, camera and lamps resolved
  (:func:`assemble`).
"""

from jrt.scene.assembly import SceneGeometry, assemble, floor_quad
from jrt.scene.builtin_scenes import BUILTIN_SCENES, builtin_toml
from jrt.scene.model import (
    BACKGROUNDS,
    CAUCHY_B_RANGE,
    FRESNEL_MODELS,
    ILLUMINANTS,
    INDEX_RANGE,
    KINDS,
    MAX_DEPTH,
    MAX_PIXELS,
    MAX_SAMPLES,
    CameraSpec,
    Features,
    Floor,
    Lamp,
    Material,
    Object,
    Scene,
    SceneError,
    Settings,
    Vec3,
)
from jrt.scene.toml_io import glass_catalogue, illuminant_names, load_scene, parse_scene

#: Every public name of the package (each module's own __all__ lists its part).
__all__ = [
    "BACKGROUNDS",
    "BUILTIN_SCENES",
    "CAUCHY_B_RANGE",
    "FRESNEL_MODELS",
    "ILLUMINANTS",
    "INDEX_RANGE",
    "KINDS",
    "MAX_DEPTH",
    "MAX_PIXELS",
    "MAX_SAMPLES",
    "CameraSpec",
    "Features",
    "Floor",
    "Lamp",
    "Material",
    "Object",
    "Scene",
    "SceneError",
    "SceneGeometry",
    "Settings",
    "Vec3",
    "assemble",
    "builtin_toml",
    "floor_quad",
    "glass_catalogue",
    "illuminant_names",
    "load_scene",
    "parse_scene",
]
