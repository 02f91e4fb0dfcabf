"""The caches of compiled programs that jrt keeps, and the one call that empties them all.

JAX keeps every jitted function's compiled programs (``jax.clear_caches`` drops them); the
renderers keep their ahead-of-time compiled programs in caches of their own, made by
:func:`program_cache`, so that a second render of the same shapes compiles nothing.
:func:`clear_caches` empties both. Each compiled program holds memory and mappings of its
machine code (XLA:CPU's JIT): a long-lived process that compiles for many shapes, scenes
or structures reaches the kernel's limit on a process's mappings (``vm.max_map_count``,
65,530 by default on Linux), where the next compile fails ("LLVM compilation error: Cannot
allocate memory"). ``jrt study`` calls :func:`clear_caches` after each of its steps.
"""

from __future__ import annotations

import gc

import jax

_CACHES: list = []


def program_cache(cache=None):
    """``cache`` (a new dict when None) registered for :func:`clear_caches`."""
    cache = {} if cache is None else cache
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
