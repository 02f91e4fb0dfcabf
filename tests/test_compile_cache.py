"""The ``jrt`` command's on-disk compilation cache (jrt.compile_cache): where it goes for a
given environment, that an unusable folder costs a note and not the run, and that a
``jrt render`` in a new process fills the folder (or, turned off, leaves it empty)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from jrt.compile_cache import cache_dir, enable

ROOT = Path(__file__).resolve().parents[1]
HOME = {"HOME": "/home/u"}


@pytest.mark.parametrize("env, expected", [
    (HOME, "/home/u/.cache/jrt/jax"),
    ({**HOME, "XDG_CACHE_HOME": "/var/cache/u"}, "/var/cache/u/jrt/jax"),
    ({**HOME, "XDG_CACHE_HOME": ""}, "/home/u/.cache/jrt/jax"),
    # The XDG spec: a relative XDG_CACHE_HOME is invalid and ignored.
    ({**HOME, "XDG_CACHE_HOME": "rel/cache"}, "/home/u/.cache/jrt/jax"),
    ({**HOME, "JRT_CACHE_DIR": "/tmp/jc"}, "/tmp/jc"),
    ({**HOME, "JRT_CACHE_DIR": "/tmp/jc", "XDG_CACHE_HOME": "/x"}, "/tmp/jc"),
    ({**HOME, "JRT_CACHE_DIR": "~/jc"}, "/home/u/jc"),
    ({**HOME, "JRT_CACHE_DIR": "rel/jc"}, "rel/jc"),
])
def test_cache_dir(env, expected):
    assert cache_dir(env) == Path(expected)


@pytest.mark.parametrize("value", ["0", "off", "OFF", "none", "None", "", "  ", " off "])
def test_jrt_cache_dir_off(value):
    assert cache_dir({**HOME, "JRT_CACHE_DIR": value, "XDG_CACHE_HOME": "/x"}) is None


@pytest.mark.parametrize("env", [
    {**HOME, "JAX_COMPILATION_CACHE_DIR": "/mine"},
    {**HOME, "JAX_COMPILATION_CACHE_DIR": "/mine", "JRT_CACHE_DIR": "/tmp/jc"},
    {**HOME, "JAX_COMPILATION_CACHE_DIR": ""},
])
def test_jax_own_setting_wins(env):
    assert cache_dir(env) is None


def test_cache_dir_reads_only_its_argument(monkeypatch):
    monkeypatch.setenv("JRT_CACHE_DIR", "/from/os/environ")
    monkeypatch.setenv("XDG_CACHE_HOME", "/from/os/environ")
    assert cache_dir(HOME) == Path("/home/u/.cache/jrt/jax")


def test_unusable_folder_is_a_note_not_an_error(tmp_path, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    assert enable({"JRT_CACHE_DIR": str(blocker / "jax")}, command="jrt render") is None
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("jrt render: note: no compilation cache")
    assert str(blocker / "jax") in err and "JRT_CACHE_DIR" in err


def test_enable_leaves_jax_alone_when_off(capsys):
    import jax

    before = jax.config.values["jax_compilation_cache_dir"]
    assert enable({"JRT_CACHE_DIR": "0"}) is None
    assert enable({"JAX_COMPILATION_CACHE_DIR": "/mine", "JRT_CACHE_DIR": "/x"}) is None
    assert jax.config.values["jax_compilation_cache_dir"] == before
    assert capsys.readouterr().err == ""


def _render(tmp_path: Path, cache_value: str) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k != "JAX_COMPILATION_CACHE_DIR"}
    env["JRT_CACHE_DIR"] = cache_value
    env["XDG_CACHE_HOME"] = str(tmp_path / "xdg")  # the default folder, were it used
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT), env.get("PYTHONPATH")]))
    out = tmp_path / "out.png"
    done = subprocess.run(
        [sys.executable, "-c", "import sys; from jrt.cli import main; sys.exit(main())",
         "render", "camel-19k", "--width", "32", "--height", "24", "-o", str(out)],
        env=env, cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    assert out.is_file()
    return done


def test_render_fills_the_cache_in_a_new_process(tmp_path):
    cache = tmp_path / "cache"
    done = _render(tmp_path, str(cache))
    assert "note:" not in done.stderr
    assert not (tmp_path / "xdg").exists()
    files = [p for p in cache.rglob("*") if p.is_file()]
    assert files, f"nothing cached in {cache}"


def test_render_with_the_cache_off_writes_nothing(tmp_path):
    cache = tmp_path / "cache"
    cache.mkdir()
    _render(tmp_path, "0")
    assert not any(cache.iterdir())
    # nor in the default folder, nor in a folder named "0"
    assert not (tmp_path / "xdg").exists()
    assert not (tmp_path / "0").exists()
