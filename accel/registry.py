"""The structure registry: one declaration per acceleration structure.

A structure kind is a :class:`StructureKind`, declared once, at the bottom of its builder's
module (``accel/bvh.py``'s ``KIND``, ...): its name, its builder, the arrays and layout keys
its record holds, where its traversal step lives, and the decoders that code outside the
builder needs (the planes the structure stores, for the stability suite's plane rays).
Everything else derives from the registry: ``accel.build``'s names and parameters,
``jrt``'s check of a record before tracing it and its choice of traversal, the command
line's choices, the benchmarks' and the report's lists, the conformance tests.

A new structure registers itself with :func:`register` (see ``docs/adding-a-structure.md``);
no other module needs an edit. This module never imports JAX: the traversal is named as
``"module:function"`` (imported by ``jrt`` when it traces) or given as the function itself.
"""

from __future__ import annotations

import dataclasses
import difflib
import importlib
from collections.abc import Callable

import numpy as np

from accel.structure import Structure

#: The structures that come with accel, in the order every list shows them (brute force,
#: the baseline, first). Each module ``accel.<name>`` declares its ``KIND``.
BUILTIN_MODULES: tuple[str, ...] = ("accel.brute", "accel.bvh", "accel.kdtree",
                                    "accel.octree", "accel.bsp", "accel.grid")


@dataclasses.dataclass(frozen=True)
class StructureKind:
    """What a structure kind declares.

    Attributes:
        name: the kind's name (``Structure.kind``, ``accel.build(name, ...)``).
        build: ``build(vertices, faces, **params) -> Structure`` (float32 [V, 3] finite
            vertices, int32 [F, 3] faces, checked by ``accel.build``); its keyword
            arguments and their defaults are the kind's parameters.
        arrays: the names of the arrays its records hold (checked before tracing).
        layout: the keys of its records' static layout.
        traversal: its step for the traversal engine (``jrt.engine.Traversal``): a
            ``"module:function"`` name or the function ``traversal(structure)`` itself;
            ``None`` for brute force, which ``jrt`` runs without the engine.
        planes: ``planes(structure) -> [x_planes, y_planes, z_planes]``: per axis, the
            float32 plane coordinates (world frame) that the structure stores (node box
            faces, split planes, cell walls): where rays that start on them test its
            traversal's tie rules. ``None`` when it stores none.
        summary: one line for listings (``jrt bench --help``, the docs).
        rows: the arrays whose rows the traversal reaches only through indices that the
            structure itself stores (nodes, leaf references, triangles), never by their
            count: ``jrt`` may pad them at the end, where no index points, so that
            structures of similar sizes share one compiled traversal
            (``jrt.trace.padded_structure``). Empty (the default): nothing is padded.
        refit: ``refit(structure, triangles) -> Structure``: the structure for new
            triangle rows (the same faces, moved; ``triangles`` float32 [T, 3, 3] in the
            structure's row order), a pure JAX function (``jrt.refit`` calls it): a
            ``"module:function"`` name or the function. ``None`` (the default) when the
            kind cannot be refit exactly (its cells or planes were chosen for the old
            positions): ``jrt.refit`` then says to rebuild it with ``accel.build``.
    """

    name: str
    build: Callable[..., Structure]
    arrays: frozenset[str]
    layout: frozenset[str] = frozenset()
    traversal: str | Callable | None = None
    planes: Callable[[Structure], list[np.ndarray]] | None = None
    summary: str = ""
    rows: frozenset[str] = frozenset()
    refit: str | Callable | None = None

    def __post_init__(self):
        if not (isinstance(self.name, str) and self.name.isidentifier()):
            raise ValueError(f"a structure kind's name must be an identifier, got {self.name!r}")
        if not callable(self.build):
            raise TypeError(f"kind {self.name!r}: build must be callable, got {self.build!r}")
        needed = {"triangles", "triangle_ids"}
        if not needed <= set(self.arrays):
            raise ValueError(f"kind {self.name!r}: arrays must include {sorted(needed)} (the "
                             f"triangles every query reads), got {sorted(self.arrays)}")
        for field in ("traversal", "refit"):
            value = getattr(self, field)
            if isinstance(value, str) and ":" not in value:
                raise ValueError(f"kind {self.name!r}: {field} {value!r} must be "
                                 "'module:function' or a function")
        object.__setattr__(self, "arrays", frozenset(self.arrays))
        object.__setattr__(self, "layout", frozenset(self.layout))
        object.__setattr__(self, "rows", frozenset(self.rows))
        if not self.rows <= self.arrays:
            raise ValueError(f"kind {self.name!r}: rows {sorted(self.rows - self.arrays)} are "
                             f"not among its arrays {sorted(self.arrays)}")

    @property
    def engine(self) -> bool:
        """Whether the traversal engine steps it (every kind but brute force)."""
        return self.traversal is not None

    def traversal_function(self) -> Callable:
        """The function ``traversal(structure)`` (imported on first use)."""
        if callable(self.traversal):
            return self.traversal
        if self.traversal is None:
            raise ValueError(f"structure kind {self.name!r} has no engine traversal")
        return _named_function(self.traversal)

    def refit_function(self) -> Callable | None:
        """The function ``refit(structure, triangles)`` (imported on first use), or None
        when the kind cannot be refit."""
        return None if self.refit is None else _named_function(self.refit)


def _named_function(name: str | Callable) -> Callable:
    """A ``"module:function"`` name's function (imported), or the function itself."""
    if callable(name):
        return name
    module, _, function = name.partition(":")
    return getattr(importlib.import_module(module), function)


_KINDS: dict[str, StructureKind] = {}
_LOADED = {"builtin": False}


def _load_builtin() -> None:
    if _LOADED["builtin"]:
        return
    _LOADED["builtin"] = True
    for module in BUILTIN_MODULES:
        kind = importlib.import_module(module).KIND
        _KINDS.setdefault(kind.name, kind)


def register(kind: StructureKind, *, replace: bool = False) -> StructureKind:
    """Add ``kind`` to the registry (a name already taken is an error unless ``replace``)."""
    if not isinstance(kind, StructureKind):
        raise TypeError(f"register takes an accel.StructureKind, got {type(kind).__name__}")
    _load_builtin()
    if kind.name in _KINDS and not replace and _KINDS[kind.name] is not kind:
        raise ValueError(f"a structure kind named {kind.name!r} is registered already; pass "
                         "replace=True to replace it")
    _KINDS[kind.name] = kind
    return kind


def unregister(name: str) -> None:
    """Remove the kind ``name`` (a built-in one too, for a test)."""
    _load_builtin()
    _KINDS.pop(name, None)


def kinds() -> tuple[StructureKind, ...]:
    """Every registered kind, the built-in ones first, then in order of registration."""
    _load_builtin()
    return tuple(_KINDS.values())


def names(*, engine: bool | None = None) -> tuple[str, ...]:
    """The registered kinds' names (``engine=True``: only those the traversal engine steps,
    i.e. all but brute force; ``engine=False``: only the others)."""
    return tuple(k.name for k in kinds() if engine is None or k.engine == engine)


def kind(name: str) -> StructureKind:
    """The registered kind ``name``, or a ValueError listing the allowed names."""
    _load_builtin()
    found = _KINDS.get(name) if isinstance(name, str) else None
    if found is None:
        allowed = tuple(_KINDS)
        close = difflib.get_close_matches(str(name), allowed, n=1)
        hint = f" (did you mean {close[0]!r}?)" if close else ""
        raise ValueError(f"unknown acceleration structure {name!r}{hint}; allowed: "
                         f"{', '.join(allowed)}")
    return found


def planes(structure: Structure) -> list[np.ndarray]:
    """Per axis, the sorted unique float32 plane coordinates (world frame) that
    ``structure`` stores (its kind's ``planes`` decoder; three empty arrays if it has none)."""
    decoder = kind(structure.kind).planes
    if decoder is None:
        return [np.zeros(0, np.float32) for _ in range(3)]
    return [np.unique(np.asarray(p, np.float32)) for p in decoder(structure)]


def world_planes(structure: Structure, local: list) -> list[np.ndarray]:
    """``local`` per-axis plane values moved from the record's local frame (its ``frame``
    array, the origin its coordinates are relative to) to world coordinates, in float32
    as the traversal computes them."""
    frame = np.asarray(structure.arrays.get("frame", np.zeros(3, np.float32)), np.float32)
    return [np.asarray(p, np.float32) + frame[a] for a, p in enumerate(local)]
