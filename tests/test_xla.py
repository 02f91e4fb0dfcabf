"""The XLA:CPU flags jrt sets before JAX starts (jrt._xla)."""

import os
import resource
import subprocess
import sys

import numpy as np
import pytest

from jrt import _xla

ZEN4 = "processor\t: 0\nflags\t\t: fpu sse2 avx2 fma avx512f avx512dq avx512vl\n"
SKYLAKE_CLIENT = "processor\t: 0\nflags\t\t: fpu sse2 avx2 fma avx512_vnni_fake\n"


def test_avx512_is_read_from_the_cpu_flags():
    assert _xla._has_avx512(ZEN4)
    # A flag that only starts like avx512f, or the word outside the flags line, is not it.
    assert not _xla._has_avx512(SKYLAKE_CLIENT)
    assert not _xla._has_avx512("model name\t: avx512f lookalike\nflags\t\t: sse2 avx2\n")
    assert not _xla._has_avx512("")


@pytest.mark.parametrize("avx512", [True, False])
def test_apply_sets_the_vector_width_only_with_avx512(monkeypatch, avx512):
    monkeypatch.setattr(_xla, "_has_avx512", lambda: avx512)
    monkeypatch.setenv("XLA_FLAGS", "")
    monkeypatch.setenv("JRT_CPU_DEVICES", "3")
    _xla.apply()
    flags = os.environ["XLA_FLAGS"].split()
    assert "--xla_force_host_platform_device_count=3" in flags
    assert ("--xla_cpu_prefer_vector_width=512" in flags) == avx512


def test_apply_keeps_a_flag_the_user_set(monkeypatch):
    monkeypatch.setattr(_xla, "_has_avx512", lambda: True)
    monkeypatch.setenv("XLA_FLAGS", "--xla_cpu_prefer_vector_width=256")
    monkeypatch.delenv("JRT_CPU_DEVICES", raising=False)
    _xla.apply()
    flags = os.environ["XLA_FLAGS"].split()
    assert "--xla_cpu_prefer_vector_width=256" in flags
    assert "--xla_cpu_prefer_vector_width=512" not in flags


def test_apply_compiles_every_while_loop_whole(monkeypatch):
    monkeypatch.setenv("XLA_FLAGS", "")
    _xla.apply()
    flags = os.environ["XLA_FLAGS"].split()
    assert ("--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold="
            f"{_xla.SMALL_WHILE_LOOP_BYTES}") in flags


def test_apply_keeps_the_users_backend_extra_options(monkeypatch):
    monkeypatch.setenv("XLA_FLAGS", "--xla_backend_extra_options=xla_cpu_fold_all_constants")
    _xla.apply()
    flags = [f for f in os.environ["XLA_FLAGS"].split() if "backend_extra" in f]
    assert flags == ["--xla_backend_extra_options=xla_cpu_fold_all_constants"]


def test_the_traversal_loop_is_compiled_as_one_call():
    """The flag reaches XLA: the engine's loop is hoisted into a small call (one function)."""
    import jax
    import jax.numpy as jnp

    import accel
    from jrt import bvh, engine

    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)
    s = accel.build("bvh", v, np.array([[0, 1, 2]]))
    # 256 rays on 64 lanes: the loop's buffers are far above XLA's default threshold.
    o = jnp.zeros((256, 3), jnp.float32)
    d = jnp.tile(jnp.asarray([[0.0, 0.0, 1.0]]), (256, 1))
    text = engine._traverse.lower(
        s.arrays, o, d, jnp.full(256, jnp.inf), traversal=bvh.traversal(s), kernel="watertight",
        any_hit=False, lanes=64, stack_size=8, counters=False,
        devices=tuple(jax.local_devices()[:1])).compile().as_text()
    # Every loop (the engine's, the winners' pass, the scatters XLA expands into loops) is
    # hoisted into a computation of its own, called as one function; with XLA's default
    # threshold the engine's loop and the winners' stay in the entry computation.
    computation, holders = None, set()
    for line in text.splitlines():
        if line[:1] not in ("", " ") and line.rstrip().endswith("{"):
            computation = line.split()[0]
        if " while(" in line:
            holders.add(computation)
    assert holders and all(name.endswith("_computation") for name in holders), holders


def test_bad_device_count_is_refused(monkeypatch):
    monkeypatch.setenv("JRT_CPU_DEVICES", "zero")
    with pytest.raises(ValueError, match="JRT_CPU_DEVICES must be a positive integer"):
        _xla._device_count()


# A 48 MB block (above glibc's largest mmap threshold, 32 MB) allocated, written, freed
# and allocated again: the page faults of the second round tell whether the process kept
# the memory (jrt's malloc settings) or gave it back to the kernel (glibc's defaults).
SECOND_ROUND_FAULTS = """
import ctypes, resource, sys, threading
import jrt
if "--tune" in sys.argv:
    jrt.tune_malloc()
if "--benchmarks" in sys.argv:
    import benchmarks  # the benchmarks tune it, as the jrt command does
libc = ctypes.CDLL("libc.so.6")
libc.malloc.restype = ctypes.c_void_p
def touch(size):
    block = libc.malloc(size)
    ctypes.memset(block, 1, size)
    return block
def twice():
    kept = touch(24 << 20)  # a 64 MB heap of a thread arena cannot also hold 48 MB
    libc.free(ctypes.c_void_p(touch(48 << 20)))
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    libc.free(ctypes.c_void_p(touch(48 << 20)))
    print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
# In a thread, which has an arena of its own (as XLA's device threads), then in the main one.
thread = threading.Thread(target=twice)
thread.start()
thread.join()
twice()
"""


def _second_round_faults(tuning: str | None, call: bool = False,
                         benchmarks: bool = False) -> int:
    env = dict(os.environ)
    env.pop("JRT_MALLOC_TUNING", None)
    if tuning is not None:
        env["JRT_MALLOC_TUNING"] = tuning
    command = ([sys.executable, "-c", SECOND_ROUND_FAULTS] + (["--tune"] if call else [])
               + (["--benchmarks"] if benchmarks else []))
    out = subprocess.run(command, env=env, check=True, capture_output=True, text=True)
    return max(int(count) for count in out.stdout.split())


@pytest.mark.skipif(_xla._glibc() is None, reason="glibc's mallopt only")
def test_malloc_tuning_keeps_large_blocks_for_the_next_call():
    pages = (48 << 20) // resource.getpagesize()
    # glibc's defaults (importing jrt changes nothing): the block is an mmap given back at
    # free, and every page faults again.
    assert _second_round_faults(None) > pages // 2
    # jrt.tune_malloc(), or JRT_MALLOC_TUNING=1 at import: the block comes from the
    # thread's heap, which keeps it (in a thread arena and in the main one).
    assert _second_round_faults(None, call=True) < pages // 20
    assert _second_round_faults("1") < pages // 20
    assert _second_round_faults(None, benchmarks=True) < pages // 20
    # JRT_MALLOC_TUNING=0 refuses it, even when asked.
    assert _second_round_faults("0", call=True) > pages // 2


def test_malloc_tuning_sets_each_parameter_and_can_be_turned_off(monkeypatch):
    calls = []

    class FakeLibc:
        def mallopt(self, param, value):
            calls.append((param.value, value.value))
            return 1

    monkeypatch.delenv("JRT_MALLOC_TUNING", raising=False)
    assert _xla.tune_malloc(FakeLibc())
    assert dict(calls) == _xla.MALLOC_SETTINGS
    calls.clear()
    monkeypatch.setenv("JRT_MALLOC_TUNING", "0")
    assert not _xla.tune_malloc(FakeLibc())
    assert calls == []


def test_malloc_tuning_reports_a_refused_setting(monkeypatch):
    class RefusingLibc:
        def mallopt(self, param, value):
            return 0

    monkeypatch.delenv("JRT_MALLOC_TUNING", raising=False)
    assert not _xla.tune_malloc(RefusingLibc())
