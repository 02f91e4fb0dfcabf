"""The ``jrt`` command's on-disk compilation cache: compile once per machine, not per run.

``jrt render`` and ``jrt trace`` turn on JAX's persistent compilation cache when they start
(:func:`enable`, called by ``jrt.cli.main``), so a second run in a new process loads its XLA
programs from disk instead of compiling them again. Importing :mod:`jrt` changes nothing:
a library user turns the cache on as JAX documents it (``jax_compilation_cache_dir``).
``jrt bench`` and ``jrt study`` leave it off: they measure compile times.

The folder (:func:`cache_dir`):

* ``JRT_CACHE_DIR`` if set: a folder, or ``0``, ``off``, ``none`` or an empty value to run
  without the cache;
* otherwise ``$XDG_CACHE_HOME/jrt/jax`` (when ``XDG_CACHE_HOME`` is an absolute path), else
  ``~/.cache/jrt/jax``;
* if ``JAX_COMPILATION_CACHE_DIR`` is set, JAX's own setting wins and jrt changes nothing.

JAX does not store a program that makes a host callback (``jax.debug.callback``): such a
program compiles in every run. The renderer's programs have none (the traversal's status
and the levels' overflow come out as values and are checked on the host), so a scene render
is stored whole: a 96x72 glass camel's first frame in a new process compiled 2.2 s
instead of 15 s (mostly loading the stored program).

A folder that cannot be created or written to costs one note on stderr; the command runs
without the cache. Delete the folder to empty it (JAX keys each entry by the program, the
compile options, ``XLA_FLAGS`` and the jaxlib version, so an upgrade or new
flags add entries beside the old ones).
"""

from __future__ import annotations

import os
import sys
from collections.abc import Mapping
from pathlib import Path

#: The environment variable that names the folder, or turns the cache off.
ENV = "JRT_CACHE_DIR"
#: Values of ``JRT_CACHE_DIR`` (case and surrounding spaces ignored) that turn it off.
OFF = frozenset({"", "0", "off", "none"})
#: JAX's own variable: when set, the user chose (or refused) a cache and jrt stays out.
JAX_ENV = "JAX_COMPILATION_CACHE_DIR"


def cache_dir(env: Mapping[str, str]) -> Path | None:
    """The folder the ``jrt`` command caches compiled programs in, for the environment
    ``env``, or None when jrt sets no cache (turned off, or ``JAX_COMPILATION_CACHE_DIR``
    set). Pure: reads ``env`` only (``HOME`` included; ``~`` only when it lacks one)."""
    if JAX_ENV in env:
        return None
    if ENV in env:
        value = env[ENV].strip()
        if value.lower() in OFF:
            return None
        return _expand(value, env)
    xdg = env.get("XDG_CACHE_HOME", "").strip()
    base = Path(xdg) if xdg and os.path.isabs(xdg) else _home(env) / ".cache"
    return base / "jrt" / "jax"


def _home(env: Mapping[str, str]) -> Path:
    home = env.get("HOME", "").strip()
    return Path(home) if home else Path.home()


def _expand(value: str, env: Mapping[str, str]) -> Path:
    """``~`` and ``~/...`` against ``env``'s HOME; other paths as given."""
    if value == "~" or value.startswith("~/"):
        return _home(env) / value[2:]
    return Path(value).expanduser()


def enable(env: Mapping[str, str] | None = None, *, command: str = "jrt") -> Path | None:
    """Turn JAX's persistent compilation cache on in :func:`cache_dir`'s folder (created if
    missing), caching every program however short its compile; return the folder, or None
    when the cache was left alone or the folder is unusable (one note on stderr, then the
    command goes on without it). Call before the first compile."""
    folder = cache_dir(os.environ if env is None else env)
    if folder is None:
        return None
    try:
        folder.mkdir(parents=True, exist_ok=True)
        if not os.access(folder, os.W_OK | os.X_OK):
            raise PermissionError("not writable")
    except OSError as exc:
        reason = exc.strerror or str(exc)
        print(f"{command}: note: no compilation cache: cannot use {folder} ({reason}); "
              f"every run compiles (set {ENV} to another folder, or to 0 to skip the cache)",
              file=sys.stderr)
        return None
    import jax

    jax.config.update("jax_compilation_cache_dir", str(folder))
    # Every program, however short its compile (JAX's default skips those under 1 s), and
    # entries of any size.
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", -1)
    return folder
