"""Process settings for XLA:CPU: the flags jrt needs, applied before JAX starts its CPU
backend, and an opt-in tuning of glibc's malloc for XLA's per-call temporaries.

``--xla_cpu_use_fusion_emitters=false``: XLA:CPU's newer fusion emitters compile the
triangle-test fusions inside ``lax.scan``/``while_loop`` bodies to code 4-6x slower than
the classic emitter (measured on the camel, jax 0.10.2: Möller–Trumbore brute force at 120
vs 790 M tests/s on one core). Flags are read when the backend starts, so this only takes
effect if jrt is imported before the first JAX computation; an explicit setting of the
same flag in ``XLA_FLAGS`` is left as it is. jaxlib 0.11 removed the flag (an unknown
XLA flag aborts the first computation), so it is set only for jaxlib < 0.11.

``--xla_force_host_platform_device_count=K``: one XLA CPU device per core (K =
``os.cpu_count()``, or ``JRT_CPU_DEVICES`` when set). A ``while_loop`` runs on one thread
and XLA's own intra-op threading does not split it, so the traversal engine splits its
rays over these devices (``shard_map``): 1.7-2x faster on two cores than one device.
Computations that do not shard still run on device 0 as before.

``--xla_cpu_prefer_vector_width=512``, on a CPU with AVX-512 only: LLVM then vectorises
XLA's loops 16 floats wide instead of 8. The BVH traversal ran 5-8 % faster on this
machine's AMD EPYC (Zen 4; interleaved A/B runs, 300k camel rays a set, 2 devices).

``--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold=2^40``: XLA:CPU's
thunk runtime runs a program as a sequence of thunks, one for every fusion, gather and
scatter, and a ``while_loop`` body as such a sequence on every iteration; its
``SmallWhileLoopHoistingPass`` compiles a loop whose buffers are below this many bytes
(1024 by default) into one function instead. jrt raises the threshold so that every
loop is compiled whole: the traversal engine's loop runs some 40 thunks an iteration,
which bounded its speed at a few thousand lanes. On the camel (1M rays a set, 2 devices,
interleaved processes) the flag alone gave 5-7 % on the BVH and every other structure,
brute force's triangle loop ran 1.6-1.9x faster, and the engine's best lane count fell
from 2048 to 512 (see ``jrt.engine.DEFAULT_LANES``). A user's own
``--xla_backend_extra_options`` is left as it is.

**glibc malloc** (:func:`tune_malloc`, Linux with glibc only; opt-in: the ``jrt`` command
and the benchmarks call it, a program calls ``jrt.tune_malloc()`` or sets
``JRT_MALLOC_TUNING=1``; ``JRT_MALLOC_TUNING=0`` refuses it everywhere). XLA:CPU allocates
all the temporaries of an execution in one block per device (45 MB a device for 1M camel
rays on two devices). glibc serves a block above its mmap threshold (32 MB at most) with
``mmap`` and gives it back with ``munmap``, so every call touches fresh pages: some 23,000
page faults a call on 1M rays, 40-60 ms of system time. The tuning sets, with
``mallopt``: no ``mmap`` for large blocks (they come from the thread's arena), no trimming
of a heap's top, and a top pad of 64 MB, without which a thread arena deletes a heap as
soon as all of it is free (glibc's ``heap_trim`` keeps it only when the heap before it
cannot take the pad). The process then keeps the memory of its largest call for the next
one, as tcmalloc or jemalloc would. One arena for all threads would also do it, but XLA's
two device threads then wait on its lock (hundreds of context switches a call, slower
than the page faults). 1M camel rays a call, processes with and without alternating (4
pairs of 10 calls): 0 page faults a call against 23,000-24,500, and the median call
1.10-1.29x faster on camera rays, 0.98-1.25x on incoherent rays.

It is not applied on import because it changes ``malloc`` for the whole process: Embree
called from threads started anew for every batch (embreex's outputs allocated in them)
ran 10-25 % slower beside jrt with it (camel, 1M-ray batches); from threads that are kept,
as the benchmarks' peer now does, it did not.

**Import order.** XLA reads ``XLA_FLAGS`` once, when JAX starts its backends (at the first
computation or ``jax.devices()``, not at ``import jax``). A program that starts them before
importing jrt keeps XLA's defaults: one CPU device, so the traversal runs on one core. jrt
cannot undo that, so on import it checks (without starting a backend itself) and warns
once with an :class:`ImportOrderWarning` that says how to fix it.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import importlib.metadata
import os
import platform
import re
import sys
import warnings


def _jaxlib_before(major: int, minor: int) -> bool:
    """Whether the installed jaxlib is older than ``major.minor`` (True if unknown)."""
    try:
        version = importlib.metadata.version("jaxlib")
    except importlib.metadata.PackageNotFoundError:
        return True
    found = re.match(r"(\d+)\.(\d+)", version)
    return found is None or (int(found[1]), int(found[2])) < (major, minor)


_FLAGS = ("--xla_cpu_use_fusion_emitters=false",) if _jaxlib_before(0, 11) else ()


def _has_avx512(cpuinfo: str | None = None) -> bool:
    """Whether the CPU has AVX-512F, from ``/proc/cpuinfo``'s flags (False where unknown)."""
    if cpuinfo is None:
        try:
            with open("/proc/cpuinfo", encoding="utf-8", errors="replace") as f:
                cpuinfo = f.read()
        except OSError:
            return False
    return any(line.startswith("flags") and "avx512f" in line.split()
               for line in cpuinfo.splitlines())


def _device_count() -> int:
    value = os.environ.get("JRT_CPU_DEVICES")
    if value is None:
        return max(1, os.cpu_count() or 1)
    try:
        count = int(value)
    except ValueError:
        count = 0
    if count < 1:
        raise ValueError(f"JRT_CPU_DEVICES must be a positive integer, got {value!r}")
    return count


#: glibc ``mallopt`` parameters (malloc.h) and the values jrt sets.
M_TRIM_THRESHOLD, M_TOP_PAD, M_MMAP_MAX = -1, -2, -4
MALLOC_SETTINGS = {M_MMAP_MAX: 0, M_TRIM_THRESHOLD: 2**31 - 1, M_TOP_PAD: 64 << 20}


def _glibc():
    """The C library as a ctypes handle where it is glibc (None elsewhere)."""
    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        return None
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
    except OSError:
        return None
    return libc if hasattr(libc, "mallopt") else None


def tune_malloc(libc=None) -> bool:
    """Has glibc keep freed memory for the next call (see this module's notes).

    Applies :data:`MALLOC_SETTINGS` with ``mallopt`` to the whole process, at any time
    (they take effect from the next allocation). Returns whether all were taken: False
    with ``JRT_MALLOC_TUNING=0`` or without glibc.
    """
    if os.environ.get("JRT_MALLOC_TUNING", "1").strip() == "0":
        return False
    libc = libc if libc is not None else _glibc()
    if libc is None:
        return False
    # mallopt returns 1 on success, 0 on error; a list, so that every setting is tried.
    return all([libc.mallopt(ctypes.c_int(param), ctypes.c_int(value)) == 1
                for param, value in MALLOC_SETTINGS.items()])


#: Buffer bytes under which XLA:CPU compiles a while loop into one function (2^40: all).
SMALL_WHILE_LOOP_BYTES = 2**40


class ImportOrderWarning(UserWarning):
    """jrt was imported after JAX had started its backends, so XLA runs without jrt's flags
    (one CPU device instead of one per core, among others): import jrt first, or set
    ``XLA_FLAGS`` before Python starts."""


def _backends_started() -> bool:
    """Whether JAX has started its backends already, found without starting them: never
    when JAX is not imported yet; else JAX's own record (False where it cannot be read)."""
    if "jax" not in sys.modules:
        return False
    try:
        from jax._src import xla_bridge
        return bool(xla_bridge.backends_are_initialized())
    except (ImportError, AttributeError):  # a JAX without this (private) function
        return False


def _started_cpu_devices() -> int | None:
    """The CPU device count of JAX's already started CPU backend (None where unknown)."""
    try:
        from jax._src import xla_bridge
        client = xla_bridge._backends.get("cpu")
        return None if client is None else int(client.device_count())
    except Exception:  # private API: a missing or changed record only loses a detail
        return None


def _import_order_message(missing: tuple[str, ...], flags: str) -> str:
    devices = _started_cpu_devices()
    wanted = _device_count()
    found = (f"JAX's CPU backend has {devices} device(s) where jrt asks for {wanted} (one "
             "per core; the traversal splits its rays over them)"
             if devices is not None and devices != wanted else
             f"XLA runs without {', '.join(flag.split('=')[0] for flag in missing)}")
    return (f"jrt was imported after JAX started its backends, so XLA did not read the flags "
            f"jrt sets: {found}. Import jrt before jax (or at least before JAX's first "
            f"computation or jax.devices()), or set them yourself before Python starts: "
            f"XLA_FLAGS='{flags}'")


_WARNED = False


def apply() -> None:
    """Adds jrt's flags to ``XLA_FLAGS`` (a flag already named there is left as it is), and
    warns (:class:`ImportOrderWarning`, once) when JAX's backends started before them."""
    global _WARNED
    current = os.environ.get("XLA_FLAGS", "")
    flags = (*_FLAGS, f"--xla_force_host_platform_device_count={_device_count()}",
             "--xla_backend_extra_options="
             f"xla_cpu_small_while_loop_byte_threshold={SMALL_WHILE_LOOP_BYTES}")
    if _has_avx512():
        flags += ("--xla_cpu_prefer_vector_width=512",)
    missing = tuple(flag for flag in flags if flag.split("=")[0] not in current)
    for flag in missing:
        current = f"{current} {flag}".strip()
    os.environ["XLA_FLAGS"] = current
    if missing and not _WARNED and _backends_started():
        _WARNED = True
        warnings.warn(_import_order_message(missing, current), ImportOrderWarning,
                      stacklevel=_caller_level())


def _caller_level() -> int:
    """The ``stacklevel`` of the first frame outside jrt and the import machinery: the
    line that imported jrt, which the warning then names. (``warnings.warn`` skips the
    import machinery's frames itself, so they are not counted.)"""
    package = os.path.dirname(os.path.abspath(__file__)) + os.sep
    frame, level = sys._getframe(1), 1
    while frame is not None:
        name = frame.f_code.co_filename
        if not name.startswith("<frozen importlib"):
            if not os.path.abspath(name).startswith(package):
                return level
            level += 1
        frame = frame.f_back
    return 1


apply()
if os.environ.get("JRT_MALLOC_TUNING", "").strip() == "1":
    tune_malloc()
