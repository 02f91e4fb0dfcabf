"""The caches of compiled programs that jrt keeps, and the one call that empties them all.

JAX keeps every jitted function's compiled programs (``jax.clear_caches`` drops them); the
renderers keep their ahead-of-time compiled programs in caches of their own, made by
:func:`program_cache`, so that a second render of the same shapes compiles nothing.
:func:`clear_caches` empties both. Each compiled program holds memory and mappings of its
machine code (XLA:CPU's JIT): a long-lived process that compiles for many shapes, scenes
or structures reaches the kernel's limit on a process's mappings (``vm.max_map_count``,
65,530 by default on Linux), where the next compile fails ("LLVM compilation error: Cannot
allocate memory"). ``jrt study`` calls :func:`clear_caches` after each of its steps.

The query functions (the engine's traversal, brute force's, ``jrt.all_hits``' record) are
jitted functions whose programs JAX keeps (up to 2,048 each); registered with
:func:`bounded_jit`, they are dropped together once they hold more than
:data:`MAX_QUERY_PROGRAMS` (:func:`trim_programs`, after each query): a camel traversal
program held about 195 mappings, so a process that traces many meshes of different sizes
(each a program of its own) stays near 31,000 instead of failing at the limit.

The renderers' caches are also bounded (:class:`ProgramCache`, the least recently used
program goes first beyond ``maxsize``), so that a process that renders many shapes without
calling :func:`clear_caches` holds a fixed number of them: a glass camel's renderer
program (32x24 to 48x24 pixels, depth 3) held about 650 mappings, so a cache of
:data:`DEFAULT_MAXSIZE` of them stays near 10,000.
"""

from __future__ import annotations

import collections
import gc
import threading

import jax

_CACHES: list = []

#: Programs a renderer's cache keeps before it drops the least recently used.
DEFAULT_MAXSIZE = 16


class ProgramCache(collections.OrderedDict):
    """A dict of compiled programs that keeps the ``maxsize`` most recently used: reading
    an entry (``cache[key]``, ``cache.get(key)``) makes it the newest, storing one beyond
    ``maxsize`` drops the oldest (whose program goes when nothing else holds it). A lock
    keeps a read and its move to the end one step, for renders from several threads."""

    def __init__(self, maxsize: int = DEFAULT_MAXSIZE):
        if isinstance(maxsize, bool) or not isinstance(maxsize, int) or maxsize < 1:
            raise ValueError(f"maxsize must be a positive integer, not {maxsize!r}")
        super().__init__()
        self.maxsize = maxsize
        self._lock = threading.RLock()

    def __getitem__(self, key):
        with self._lock:
            value = super().__getitem__(key)
            self.move_to_end(key)
            return value

    def get(self, key, default=None):
        with self._lock:
            return self[key] if key in self else default

    def __setitem__(self, key, value):
        with self._lock:
            super().__setitem__(key, value)
            self.move_to_end(key)
            while len(self) > self.maxsize:
                self.popitem(last=False)


#: Compiled programs the functions registered with :func:`bounded_jit` may hold together.
MAX_QUERY_PROGRAMS = 160

_JITTED: list = []


def bounded_jit(fn):
    """Registers ``fn`` (a ``jax.jit`` function) with :func:`trim_programs`; returns it."""
    _JITTED.append(fn)
    return fn


def trim_programs(limit: int | None = None) -> bool:
    """Drops the compiled programs of every :func:`bounded_jit` function (their next calls
    compile again) when they hold more than ``limit`` (default
    :data:`MAX_QUERY_PROGRAMS`) together; True when it did. All at once, not the least
    recently used: JAX keeps no order of use, and a process reaches the bound only after
    that many compiles (minutes of them), so a drop costs little against them."""
    limit = MAX_QUERY_PROGRAMS if limit is None else limit
    if sum(fn._cache_size() for fn in _JITTED) <= limit:  # (as jrt.engine.compiled_programs)
        return False
    for fn in _JITTED:
        fn.clear_cache()
    return True


def program_cache(maxsize: int = DEFAULT_MAXSIZE) -> ProgramCache:
    """A new :class:`ProgramCache` of ``maxsize`` programs, registered for
    :func:`clear_caches`."""
    cache = ProgramCache(maxsize)
    _CACHES.append(cache)
    return cache


def clear_caches() -> None:
    """Drop every compiled program this process holds: JAX's caches and the renderers'
    (the next call of each compiles again). A program in a reference cycle goes with the
    garbage collection that follows."""
    for cache in _CACHES:
        cache.clear()
    jax.clear_caches()
    gc.collect()
