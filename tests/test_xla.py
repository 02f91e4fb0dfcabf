"""The XLA:CPU flags jrt sets before JAX starts (jrt._xla)."""

import os

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


def test_bad_device_count_is_refused(monkeypatch):
    monkeypatch.setenv("JRT_CPU_DEVICES", "zero")
    with pytest.raises(ValueError, match="JRT_CPU_DEVICES must be a positive integer"):
        _xla._device_count()
