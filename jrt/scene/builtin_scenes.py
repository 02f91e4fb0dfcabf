"""The built-in scenes: one TOML file each in ``jrt/scene/builtin/``, shipped as package data.

A scene's name is its file's stem; the files are ordinary scene files (the schema of
:mod:`jrt.scene.toml_io`), so a user can copy one to start a scene of their own. They are
read once, at import, through :mod:`importlib.resources` (which also works from a zip or
a wheel).
"""

from __future__ import annotations

from importlib import resources

from jrt.scene.model import SceneError

#: The folder, inside the package ``jrt.scene``, that holds the built-in scenes' files.
BUILTIN_FOLDER = "builtin"


def _read_builtins() -> dict[str, str]:
    folder = resources.files("jrt.scene").joinpath(BUILTIN_FOLDER)
    files = sorted((f for f in folder.iterdir() if f.name.endswith(".toml")),
                   key=lambda f: f.name)
    return {f.name.removesuffix(".toml"): f.read_text(encoding="utf-8") for f in files}


#: The built-in scenes, {name: TOML text}, sorted by name: copy one to start a scene of
#: your own.
BUILTIN_SCENES: dict[str, str] = _read_builtins()


def builtin_toml(name: str) -> str:
    """The TOML text of the built-in scene ``name``."""
    if name not in BUILTIN_SCENES:
        raise SceneError(
            f"unknown built-in scene {name!r}; built-in scenes: {', '.join(BUILTIN_SCENES)}"
        )
    return BUILTIN_SCENES[name]


__all__ = ["BUILTIN_SCENES", "builtin_toml"]
