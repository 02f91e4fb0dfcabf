"""One resolver for the study's meshes (the camels, the bunny, the teapot, the fandisk).

The meshes ship inside the package, gzip-compressed, in ``jrt/meshes/`` (provenance in
``jrt/meshes/README.md``), so an installed jrt needs nothing else. A mesh is looked for:

1. when the environment variable ``JRT_DATA`` is set (and not empty), in that folder only,
   as the plain file (``camel.off``) or compressed (``camel.off.gz``). A folder that does not
   exist, or lacks the mesh, is an error: a variable set on purpose is never silently ignored
   for the packaged copy;
2. otherwise, the package's own copy (``jrt/meshes/camel.off.gz``).

:func:`jrt.load_mesh` reads both forms.
"""

from __future__ import annotations

import os
from pathlib import Path

ENV_VAR = "JRT_DATA"

#: The folder of the packaged meshes.
PACKAGE_DIR = Path(__file__).resolve().parent / "meshes"

#: Short names of the shipped meshes, and their (uncompressed) file names.
MESHES = {
    "camel": "camel.off",  # 34,546 vertices, 69,092 triangles, watertight, y-up
    "camel-19k": "camel-19k.off",  # 19,536 triangles, watertight
    "bunny": "bunny.obj",  # 69,451 triangles, holes in the base
    "teapot": "teapot.obj",  # 6,320 triangles, open patches
    "fandisk": "fandisk.obj",  # 12,946 triangles, closed, sharp creases
}

#: Compressed files carry this suffix after the mesh's own.
GZ = ".gz"


def _file_name(name: str) -> str:
    if name not in MESHES:
        raise ValueError(f"unknown mesh name {name!r}; allowed: {', '.join(MESHES)}")
    return MESHES[name]


def _env_dir() -> Path | None:
    """The folder named by ``JRT_DATA``, or None when it is unset or empty; an error when it
    is set to something that is not a folder."""
    value = os.environ.get(ENV_VAR)
    if not value:
        return None
    folder = Path(value).expanduser()
    if not folder.is_dir():
        what = "is not a folder" if folder.exists() else "does not exist"
        raise FileNotFoundError(
            f"${ENV_VAR} is set to {value!r}, but {folder} {what}. Point {ENV_VAR} at a folder "
            f"holding the meshes ({', '.join(MESHES.values())}, plain or {GZ}), or unset it "
            "to use the copies shipped with jrt."
        )
    return folder.resolve()


def data_dir() -> Path:
    """The folder meshes are read from: ``$JRT_DATA`` when set (it must exist), else the
    package's ``jrt/meshes``."""
    return _env_dir() or PACKAGE_DIR


def mesh_path(name: str = "camel") -> Path:
    """Path of a shipped mesh by short name (``camel``, ``camel-19k``, ``bunny``, ``teapot``,
    ``fandisk``): a plain or ``.gz`` file, both read by :func:`jrt.load_mesh`.

    Raises ValueError for an unknown name and FileNotFoundError, naming ``JRT_DATA``, the
    folder and the files looked for, when ``JRT_DATA`` is set and its folder lacks the mesh.
    """
    file = _file_name(name)
    folder = _env_dir()
    if folder is not None:
        for candidate in (folder / file, folder / (file + GZ)):
            if candidate.is_file():
                return candidate
        raise FileNotFoundError(
            f"${ENV_VAR} is set to {folder}, which holds neither {file} nor {file + GZ}. "
            f"Copy the mesh there, or unset {ENV_VAR} to use the copies shipped with jrt."
        )
    packaged = PACKAGE_DIR / (file + GZ)
    if not packaged.is_file():
        raise FileNotFoundError(
            f"the packaged mesh {packaged} is missing: this installation of jrt is incomplete "
            f"(reinstall it, or set {ENV_VAR} to a folder holding {file})."
        )
    return packaged


def camel_path(name: str = "camel") -> Path:
    """Path of a named mesh (default the camel); the same as :func:`mesh_path`."""
    return mesh_path(name)


def has_camel(name: str = "camel") -> bool:
    """True when :func:`mesh_path` finds the mesh (always, unless ``JRT_DATA`` points
    elsewhere or the installation is incomplete)."""
    try:
        mesh_path(name)
    except FileNotFoundError:
        return False
    return True
