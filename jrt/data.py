"""One resolver for the data that lives outside the repository (the camel meshes).

Looked for, in order:
1. the folder named by the environment variable ``JRT_DATA``;
2. ``../shared/data`` beside the project root (the folder holding ``pyproject.toml``);
3. ``../shared/data`` beside the current working directory.
"""

from __future__ import annotations

import os
from pathlib import Path

ENV_VAR = "JRT_DATA"
PROJECT_ROOT = Path(__file__).resolve().parents[1]

#: Short names of the meshes the project uses, and their file names.
MESHES = {
    "camel": "camel.off",  # 34,546 vertices, 69,092 triangles, watertight, y-up
    "camel-19k": "camel-19k.off",  # 19,536 triangles
}


def _candidates() -> list[tuple[str, Path]]:
    found = []
    if os.environ.get(ENV_VAR):
        found.append((f"${ENV_VAR}", Path(os.environ[ENV_VAR]).expanduser()))
    found.append(("beside the project root", PROJECT_ROOT.parent / "shared" / "data"))
    found.append(("beside the working directory", Path.cwd().parent / "shared" / "data"))
    return found


def data_dir(required: str = MESHES["camel"]) -> Path:
    """The first candidate folder that holds ``required``; a clear error if none does."""
    tried = []
    for label, folder in _candidates():
        if (folder / required).is_file():
            return folder.resolve()
        tried.append(f"  {label}: {folder}")
    if not os.environ.get(ENV_VAR):
        tried.insert(0, f"  ${ENV_VAR}: (not set)")
    raise FileNotFoundError(
        f"cannot find {required}. Looked in:\n" + "\n".join(tried) + "\n"
        f"Set {ENV_VAR} to the folder that holds camel.off and camel-19k.off "
        f"(e.g. `export {ENV_VAR}=/path/to/data`), or put them in ../shared/data beside "
        "the project root. The meshes are not part of the repository."
    )


def camel_path(name: str = "camel") -> Path:
    """Path of a named mesh (``"camel"`` or ``"camel-19k"``)."""
    if name not in MESHES:
        raise ValueError(f"unknown mesh name {name!r}; allowed: {', '.join(MESHES)}")
    return data_dir(MESHES[name]) / MESHES[name]


def has_camel(name: str = "camel") -> bool:
    """True when :func:`camel_path` would find the mesh."""
    try:
        camel_path(name)
    except FileNotFoundError:
        return False
    return True
