"""jrt.data: where the camel meshes are looked for, and what is said when they are not found."""

from __future__ import annotations

import re

import pytest

import jrt.data
from jrt.data import ENV_VAR, MESHES, camel_path, data_dir, has_camel

FAKE_OFF = "OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n"


def _folder_with(path, *names):
    path.mkdir(parents=True, exist_ok=True)
    for name in names:
        (path / name).write_text(FAKE_OFF)
    return path


@pytest.fixture
def isolated(tmp_path, monkeypatch):
    """No candidate holds anything: JRT_DATA unset, project root and cwd in empty tmp dirs.

    Returns (project_root, work_dir); the candidates are ``<parent>/shared/data`` of each.
    """
    project = tmp_path / "proj" / "repo"
    work = tmp_path / "work" / "cwd"
    project.mkdir(parents=True)
    work.mkdir(parents=True)
    monkeypatch.delenv(ENV_VAR, raising=False)
    monkeypatch.setattr(jrt.data, "PROJECT_ROOT", project)
    monkeypatch.chdir(work)
    return project, work


def test_env_var_name_and_mesh_names():
    assert ENV_VAR == "JRT_DATA"
    assert MESHES == {"camel": "camel.off", "camel-19k": "camel-19k.off"}


def test_jrt_data_folder_wins(tmp_path, isolated, monkeypatch):
    project, work = isolated
    env = _folder_with(tmp_path / "env", "camel.off")
    # The other two candidates hold a camel too: JRT_DATA comes first.
    _folder_with(project.parent / "shared" / "data", "camel.off")
    _folder_with(work.parent / "shared" / "data", "camel.off")
    monkeypatch.setenv(ENV_VAR, str(env))
    assert camel_path() == (env / "camel.off").resolve()
    assert data_dir() == env.resolve()
    assert has_camel()


def test_jrt_data_with_tilde_is_expanded(tmp_path, isolated, monkeypatch):
    home = tmp_path / "home"
    _folder_with(home / "meshes", "camel.off")
    monkeypatch.setenv("HOME", str(home))
    monkeypatch.setenv(ENV_VAR, "~/meshes")
    assert camel_path() == (home / "meshes" / "camel.off").resolve()


def test_camel_19k_resolves_to_its_own_file(tmp_path, isolated, monkeypatch):
    env = _folder_with(tmp_path / "env", "camel.off", "camel-19k.off")
    monkeypatch.setenv(ENV_VAR, str(env))
    assert camel_path("camel-19k") == (env / "camel-19k.off").resolve()
    assert camel_path("camel") == (env / "camel.off").resolve()


def test_project_root_candidate_when_jrt_data_lacks_the_file(tmp_path, isolated, monkeypatch):
    project, work = isolated
    env = _folder_with(tmp_path / "env")  # empty
    shared = _folder_with(project.parent / "shared" / "data", "camel.off")
    _folder_with(work.parent / "shared" / "data", "camel.off")
    monkeypatch.setenv(ENV_VAR, str(env))
    assert camel_path() == (shared / "camel.off").resolve()


def test_working_directory_candidate_comes_last(isolated):
    project, work = isolated
    shared = _folder_with(work.parent / "shared" / "data", "camel.off")
    assert camel_path() == (shared / "camel.off").resolve()


def test_a_folder_is_chosen_per_file(tmp_path, isolated, monkeypatch):
    # JRT_DATA holds only camel.off; camel-19k.off is found in the project-root candidate.
    project, _ = isolated
    env = _folder_with(tmp_path / "env", "camel.off")
    shared = _folder_with(project.parent / "shared" / "data", "camel-19k.off")
    monkeypatch.setenv(ENV_VAR, str(env))
    assert camel_path("camel") == (env / "camel.off").resolve()
    assert camel_path("camel-19k") == (shared / "camel-19k.off").resolve()


def test_not_found_with_jrt_data_pointing_at_an_empty_folder(tmp_path, isolated, monkeypatch):
    project, work = isolated
    env = _folder_with(tmp_path / "env")
    monkeypatch.setenv(ENV_VAR, str(env))
    with pytest.raises(FileNotFoundError) as info:
        camel_path()
    message = str(info.value)
    assert "cannot find camel.off" in message
    # Names the variable and every folder searched, in order.
    assert f"$JRT_DATA: {env}" in message
    beside_root = str(project.parent / "shared" / "data")
    beside_cwd = str(work.resolve().parent / "shared" / "data")
    assert f"beside the project root: {beside_root}" in message
    assert f"beside the working directory: {beside_cwd}" in message
    assert message.index(str(env)) < message.index(beside_root) < message.index(beside_cwd)
    # Tells what to do.
    assert re.search(r"Set JRT_DATA to the folder that holds camel\.off", message)
    assert "export JRT_DATA=" in message
    assert "not part of the repository" in message
    assert not has_camel()


def test_not_found_with_jrt_data_unset_says_so(isolated):
    with pytest.raises(FileNotFoundError, match=r"\$JRT_DATA: \(not set\)"):
        camel_path()
    assert not has_camel()


def test_empty_jrt_data_counts_as_unset(isolated, monkeypatch):
    monkeypatch.setenv(ENV_VAR, "")
    with pytest.raises(FileNotFoundError, match=r"\$JRT_DATA: \(not set\)"):
        camel_path()


def test_not_found_names_the_requested_file(isolated):
    with pytest.raises(FileNotFoundError, match=r"cannot find camel-19k\.off"):
        camel_path("camel-19k")
    assert not has_camel("camel-19k")


def test_a_folder_named_like_the_mesh_does_not_count(tmp_path, isolated, monkeypatch):
    env = tmp_path / "env"
    (env / "camel.off").mkdir(parents=True)
    monkeypatch.setenv(ENV_VAR, str(env))
    assert not has_camel()


@pytest.mark.parametrize("name", ["dragon", "Camel", "camel.off", ""])
def test_unknown_mesh_name(name, isolated):
    with pytest.raises(
        ValueError,
        match=rf"unknown mesh name {re.escape(repr(name))}; "
        r"allowed: camel, camel-19k",
    ):
        camel_path(name)


def test_has_camel_true_and_false(tmp_path, isolated, monkeypatch):
    env = _folder_with(tmp_path / "env", "camel-19k.off")
    monkeypatch.setenv(ENV_VAR, str(env))
    assert has_camel("camel-19k")
    assert not has_camel("camel")
    assert not has_camel()  # default name is "camel"
