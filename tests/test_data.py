"""jrt.data and the packaged meshes: what the resolver returns with and without ``JRT_DATA``,
what it says when a mesh is not where ``JRT_DATA`` points, and that the compressed copies
shipped in ``jrt/meshes`` load to exactly the original files' vertices and faces."""

from __future__ import annotations

import gzip
import re
from pathlib import Path

import numpy as np
import pytest

import jrt
from jrt import cli
from jrt.data import ENV_VAR, GZ, MESHES, PACKAGE_DIR, camel_path, data_dir, has_camel, mesh_path
from jrt.mesh import MeshError, load_mesh

#: The originals the packaged copies were compressed from, where a checkout keeps them beside
#: the project (absent in a user's clone: the comparison is then skipped).
ORIGINALS = Path(__file__).resolve().parents[2] / "shared" / "data"

#: One triangle, in OFF: a stand-in mesh that only a JRT_DATA folder can provide.
FAKE_OFF = "OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n"


@pytest.fixture
def no_env(monkeypatch, tmp_path):
    """JRT_DATA unset, and the working directory somewhere unrelated to the project."""
    monkeypatch.delenv(ENV_VAR, raising=False)
    monkeypatch.chdir(tmp_path)


@pytest.fixture(scope="module")
def packaged():
    """name -> the packaged mesh loaded through the resolver with JRT_DATA unset."""
    with pytest.MonkeyPatch.context() as mp:
        mp.delenv(ENV_VAR, raising=False)
        return {name: load_mesh(mesh_path(name)) for name in MESHES}


def _readme_triangles() -> dict[str, int]:
    """The triangle counts of the provenance table in jrt/meshes/README.md."""
    text = (PACKAGE_DIR / "README.md").read_text()
    rows = re.findall(r"^\| `([^`]+)` \| ([\d,]+) \|", text, flags=re.M)
    return {file: int(count.replace(",", "")) for file, count in rows}


# --------------------------------------------------------------------------- the packaged copies


def test_every_mesh_resolves_to_the_package_without_jrt_data(no_env):
    for name, file in MESHES.items():
        path = mesh_path(name)
        assert path == PACKAGE_DIR / (file + GZ), name
        assert path.is_file() and path.stat().st_size > 0, name
        assert has_camel(name), name
    assert camel_path() == mesh_path("camel") == PACKAGE_DIR / "camel.off.gz"
    assert data_dir() == PACKAGE_DIR
    assert jrt.mesh_path is mesh_path


def test_the_package_folder_holds_the_five_meshes_and_their_provenance():
    shipped = sorted(p.name for p in PACKAGE_DIR.iterdir() if p.suffix == GZ)
    assert shipped == sorted(file + GZ for file in MESHES.values())
    assert set(_readme_triangles()) == set(MESHES.values())


def test_packaged_meshes_have_the_documented_triangle_counts(packaged):
    """Each loads and validates, with the count of the provenance table (independent of the
    loader: written from the original files)."""
    documented = _readme_triangles()
    for name, mesh in packaged.items():
        assert len(mesh.faces) == documented[MESHES[name]], name
        assert mesh.vertices.dtype == np.float32 and mesh.faces.dtype == np.int32


@pytest.mark.skipif(not ORIGINALS.is_dir(), reason=f"no originals to compare with ({ORIGINALS})")
@pytest.mark.parametrize("name", list(MESHES))
def test_packaged_mesh_equals_the_original_file(name, packaged):
    original = ORIGINALS / MESHES[name]
    compressed = PACKAGE_DIR / (MESHES[name] + GZ)
    assert gzip.decompress(compressed.read_bytes()) == original.read_bytes()
    plain = load_mesh(original)
    np.testing.assert_array_equal(packaged[name].vertices, plain.vertices)
    np.testing.assert_array_equal(packaged[name].faces, plain.faces)
    np.testing.assert_array_equal(packaged[name].degenerate, plain.degenerate)


def test_cli_accepts_every_shipped_name(no_env, packaged):
    for name in MESHES:
        mesh = cli._mesh(name)
        np.testing.assert_array_equal(mesh.faces, packaged[name].faces)
    assert cli._mesh(None).name == str(PACKAGE_DIR / "camel.off.gz")


def test_unknown_name_lists_every_shipped_mesh():
    with pytest.raises(ValueError, match="allowed: camel, camel-19k, bunny, teapot, fandisk"):
        mesh_path("dragon")


# --------------------------------------------------------------------------- JRT_DATA


def test_jrt_data_pointing_to_a_missing_folder_is_an_error(tmp_path, monkeypatch):
    missing = tmp_path / "nowhere"
    monkeypatch.setenv(ENV_VAR, str(missing))
    with pytest.raises(FileNotFoundError) as info:
        mesh_path("camel")
    message = str(info.value)
    assert "$JRT_DATA" in message and str(missing) in message and "does not exist" in message
    assert "unset it" in message
    assert not has_camel()  # no fallback to the packaged copy
    with pytest.raises(FileNotFoundError, match="does not exist"):
        data_dir()


def test_jrt_data_pointing_to_a_file_is_an_error(tmp_path, monkeypatch):
    file = tmp_path / "camel.off"
    file.write_text(FAKE_OFF)
    monkeypatch.setenv(ENV_VAR, str(file))
    with pytest.raises(FileNotFoundError, match=r"is not a folder"):
        mesh_path("camel")


def test_jrt_data_folder_without_the_mesh_is_an_error(tmp_path, monkeypatch):
    (tmp_path / "camel-19k.off").write_text(FAKE_OFF)
    monkeypatch.setenv(ENV_VAR, str(tmp_path))
    assert mesh_path("camel-19k") == tmp_path.resolve() / "camel-19k.off"
    with pytest.raises(FileNotFoundError) as info:
        mesh_path("teapot")
    message = str(info.value)
    assert "$JRT_DATA" in message and str(tmp_path.resolve()) in message
    assert "teapot.obj" in message and "teapot.obj.gz" in message
    assert not has_camel("camel")


def test_jrt_data_copy_is_used_plain_or_compressed(tmp_path, monkeypatch):
    (tmp_path / "camel.off").write_text(FAKE_OFF)
    (tmp_path / "camel-19k.off.gz").write_bytes(gzip.compress(FAKE_OFF.encode()))
    monkeypatch.setenv(ENV_VAR, str(tmp_path))
    assert data_dir() == tmp_path.resolve()
    for name, file in (("camel", "camel.off"), ("camel-19k", "camel-19k.off.gz")):
        path = mesh_path(name)
        assert path == tmp_path.resolve() / file
        mesh = load_mesh(path)  # the stand-in, not the packaged camel
        assert mesh.faces.tolist() == [[0, 1, 2]]
        assert mesh.vertices.tolist() == [[0, 0, 0], [1, 0, 0], [0, 1, 0]]
    # Both forms present: the plain file is taken.
    (tmp_path / "camel.off.gz").write_bytes(b"not read")
    assert mesh_path("camel") == tmp_path.resolve() / "camel.off"


def test_jrt_data_with_tilde_is_expanded(tmp_path, monkeypatch):
    home = tmp_path / "home"
    (home / "meshes").mkdir(parents=True)
    (home / "meshes" / "fandisk.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    monkeypatch.setenv("HOME", str(home))
    monkeypatch.setenv(ENV_VAR, "~/meshes")
    assert mesh_path("fandisk") == (home / "meshes" / "fandisk.obj").resolve()


def test_empty_jrt_data_counts_as_unset(monkeypatch):
    monkeypatch.setenv(ENV_VAR, "")
    assert mesh_path("teapot") == PACKAGE_DIR / "teapot.obj.gz"


# --------------------------------------------------------------------------- reading .gz


def test_gz_loader_errors_name_the_path(tmp_path):
    bad = tmp_path / "broken.off.gz"
    bad.write_bytes(b"OFF but not gzip")
    with pytest.raises(MeshError, match=re.escape(f"{bad}: not a readable gzip file")):
        load_mesh(bad)
    truncated = tmp_path / "cut.off.gz"
    truncated.write_bytes(gzip.compress(FAKE_OFF.encode())[:-12])
    with pytest.raises(MeshError, match=re.escape(f"{truncated}: not a readable gzip file")):
        load_mesh(truncated)
    wrong = tmp_path / "notes.txt.gz"
    wrong.write_bytes(gzip.compress(b"hello"))
    with pytest.raises(MeshError, match=re.escape(f"{wrong}: unsupported mesh format '.txt.gz'")):
        load_mesh(wrong)
    bare = tmp_path / "mesh.gz"
    bare.write_bytes(gzip.compress(FAKE_OFF.encode()))
    with pytest.raises(MeshError, match=re.escape(f"{bare}: unsupported mesh format '.gz'")):
        load_mesh(bare)
    with pytest.raises(MeshError, match=re.escape(f"{tmp_path / 'gone.obj.gz'}: no such mesh")):
        load_mesh(tmp_path / "gone.obj.gz")
    garbage = tmp_path / "garbage.off.gz"
    garbage.write_bytes(gzip.compress(b"OFF\n3 1 0\n0 0\n"))
    with pytest.raises(MeshError, match=re.escape(str(garbage))):
        load_mesh(garbage)


def test_gz_and_plain_of_the_same_file_load_the_same(tmp_path):
    """Upper-case suffixes too: the format is read from the suffix before .GZ."""
    text = "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\nf 1 2 3\nf 2 4 3\n"
    plain = tmp_path / "quad.obj"
    plain.write_text(text)
    packed = tmp_path / "QUAD.OBJ.GZ"
    packed.write_bytes(gzip.compress(text.encode()))
    a, b = load_mesh(plain), load_mesh(packed)
    np.testing.assert_array_equal(a.vertices, b.vertices)
    np.testing.assert_array_equal(a.faces, b.faces)
    assert b.name == str(packed)
