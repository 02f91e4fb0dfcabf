"""Ray and hit files for ``jrt trace``: NumPy ``.npz`` archives, validated on the way in.

Rays: ``origins`` and ``directions``, float [N, 3] (stored as float32); optional ``tmax``
[N], positive (``inf`` for no limit). Directions follow the library's one rule
(:data:`jrt.engine.DIRECTION_LENGTHS`, as ``jrt.closest_hit``): any length within
[1e-6, 1e6], with ``t`` and ``tmax`` in units of that length (a distance for unit
directions).
Hits: ``t`` (``inf`` for a miss), ``triangle`` (``-1`` for a miss), ``u``, ``v``; with
``--any-hit``, ``occluded`` (bool) instead.
"""

from __future__ import annotations

import zipfile
from pathlib import Path

import numpy as np

from jrt import engine


class RaysFileError(ValueError):
    """A rays file that cannot be traced; the message names the file, the array and the rule."""


def _float_array(path, archive, name, shape_text, ndim, n=None):
    try:
        a = archive[name]
    except (ValueError, OSError, EOFError, zipfile.BadZipFile) as exc:
        raise RaysFileError(f"{path}: '{name}' could not be read as a NumPy array ({exc})") from exc
    if not isinstance(a, np.ndarray):
        raise RaysFileError(f"{path}: '{name}' is not a .npy array inside the archive")
    if not (np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer)):
        raise RaysFileError(f"{path}: '{name}' must be float32 {shape_text}, got dtype {a.dtype}")
    if a.ndim != ndim or (ndim == 2 and a.shape[1] != 3) or (n is not None and a.shape[0] != n):
        raise RaysFileError(f"{path}: '{name}' must have shape {shape_text}, got {a.shape}")
    with np.errstate(over="ignore", invalid="ignore"):  # too large -> inf, reported below
        return a.astype(np.float32)


def load_rays(path) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """(origins, directions, tmax or None) from a ``.npz`` file, or a :class:`RaysFileError`."""
    path = Path(path)
    if not path.is_file():
        raise RaysFileError(f"{path}: no such rays file")
    try:
        archive = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        raise RaysFileError(f"{path}: not a NumPy .npz archive ({exc})") from exc
    if not isinstance(archive, np.lib.npyio.NpzFile):
        raise RaysFileError(f"{path}: a single .npy array, expected an .npz archive with "
                            "'origins' and 'directions'")
    with archive:
        for name in ("origins", "directions"):
            if name not in archive.files:
                raise RaysFileError(
                    f"{path}: missing array '{name}' (float32 [N, 3]); found: "
                    f"{', '.join(archive.files) or 'nothing'}"
                )
        origins = _float_array(path, archive, "origins", "[N, 3]", 2)
        n = origins.shape[0]
        directions = _float_array(path, archive, "directions", f"[{n}, 3] like origins", 2, n)
        tmax = None
        if "tmax" in archive.files:
            tmax = _float_array(path, archive, "tmax", f"[{n}]", 1, n)
    for name, a in (("origins", origins), ("directions", directions)):
        bad = ~np.isfinite(a).all(axis=1)
        if bad.any():
            row = int(np.flatnonzero(bad)[0])
            raise RaysFileError(
                f"{path}: '{name}' has {int(bad.sum())} rows with NaN or infinite values "
                f"(first: row {row} = {a[row].tolist()}); all must be finite"
            )
    # The library's rule for the rest (a direction's length), in its words.
    problem = engine.describe_bad_ray(origins, directions,
                                      np.zeros(len(origins), np.float32))
    if problem is not None:
        raise RaysFileError(f"{path}: {problem}")
    if tmax is not None and (np.isnan(tmax).any() or (tmax <= 0).any()):
        row = int(np.flatnonzero(np.isnan(tmax) | (tmax <= 0))[0])
        raise RaysFileError(
            f"{path}: 'tmax' must be > 0 (inf for no limit); row {row} is {tmax[row]}"
        )
    return origins, directions, tmax


def save_hits(path, **arrays) -> Path:
    """Write the arrays to ``path`` (``.npz`` added if missing)."""
    path = Path(path)
    if path.suffix != ".npz":
        path = path.with_suffix(path.suffix + ".npz")
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(path, **{k: np.asarray(v) for k, v in arrays.items()})
    return path
