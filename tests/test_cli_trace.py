"""`jrt trace` through jrt.cli.main: rays-file validation and end-to-end results on a square."""

from __future__ import annotations

import re
import zipfile

import numpy as np
import pytest

from jrt.cli import main
from jrt.kernels import KERNELS

# The unit square [0, 1]^2 in the z=0 plane as two triangles sharing the diagonal (0,0)-(1,1):
# face 0 = (0,0) (1,0) (1,1) below the diagonal, face 1 = (0,0) (1,1) (0,1) above it.
SQUARE_OFF = "OFF\n4 2 0\n0 0 0\n1 0 0\n1 1 0\n0 1 0\n3 0 1 2\n3 0 2 3\n"

DOWN = [0.0, 0.0, -1.0]
UP = [0.0, 0.0, 1.0]


@pytest.fixture
def square(tmp_path):
    path = tmp_path / "square.off"
    path.write_text(SQUARE_OFF)
    return path


def _rays(tmp_path, name="rays.npz", **arrays):
    path = tmp_path / name
    np.savez(path, **arrays)
    return path


def _good(n=2):
    origins = np.tile(np.float32([0.25, 0.25, 1.0]), (n, 1))
    directions = np.tile(np.float32(DOWN), (n, 1))
    return origins, directions


def _trace_error(capsys, square, rays, tmp_path, *extra):
    """Run `jrt trace`, expect exit status 2; return the stderr text."""
    out = tmp_path / "hits.npz"
    code = main(["trace", str(square), str(rays), "-o", str(out), *extra])
    err = capsys.readouterr().err
    assert code == 2, err
    assert err.startswith("jrt trace: error: "), err
    assert not out.exists()
    return err


def _trace(capsys, square, rays, out, *extra):
    code = main(["trace", str(square), str(rays), "-o", str(out), *extra])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    return captured.out


# --------------------------------------------------------------------------------------
# Input validation: exit status 2 and one clear line on stderr
# --------------------------------------------------------------------------------------


def test_missing_rays_file(capsys, square, tmp_path):
    rays = tmp_path / "absent.npz"
    err = _trace_error(capsys, square, rays, tmp_path)
    assert f"{rays}: no such rays file" in err


def test_missing_mesh_file(capsys, tmp_path):
    origins, directions = _good()
    rays = _rays(tmp_path, origins=origins, directions=directions)
    err = _trace_error(capsys, tmp_path / "absent.off", rays, tmp_path)
    assert "absent.off: no such mesh file" in err


@pytest.mark.parametrize(
    "content",
    [b"hello, these are not rays\n", b"PK\x03\x04 truncated zip", b"\x93NUMPY garbage"],
    ids=["text", "broken-zip", "broken-npy"],
)
def test_file_that_is_not_an_npz(capsys, square, tmp_path, content):
    rays = tmp_path / "rays.npz"
    rays.write_bytes(content)
    err = _trace_error(capsys, square, rays, tmp_path)
    assert f"{rays}: not a NumPy .npz archive" in err


def test_empty_file_is_not_an_npz(capsys, square, tmp_path):
    rays = tmp_path / "rays.npz"
    rays.write_bytes(b"")
    err = _trace_error(capsys, square, rays, tmp_path)
    assert f"{rays}: not a NumPy .npz archive" in err


def test_zip_whose_members_are_not_npy_arrays(capsys, square, tmp_path):
    rays = tmp_path / "rays.npz"
    with zipfile.ZipFile(rays, "w") as archive:
        archive.writestr("origins.npy", b"not an array")
        archive.writestr("directions.npy", b"not an array")
    err = _trace_error(capsys, square, rays, tmp_path)
    assert str(rays) in err and "origins" in err


def test_bare_npy_file(capsys, square, tmp_path):
    origins, _ = _good()
    rays = tmp_path / "rays.npy"
    np.save(rays, origins)
    err = _trace_error(capsys, square, rays, tmp_path)
    assert "a single .npy array, expected an .npz archive with 'origins' and 'directions'" in err


@pytest.mark.parametrize("missing", ["origins", "directions"])
def test_missing_array(capsys, square, tmp_path, missing):
    origins, directions = _good()
    arrays = {"origins": origins, "directions": directions, "extra": np.zeros(2)}
    del arrays[missing]
    rays = _rays(tmp_path, **arrays)
    err = _trace_error(capsys, square, rays, tmp_path)
    assert f"missing array '{missing}' (float32 [N, 3])" in err
    # Lists what the file does hold.
    assert "found: " in err and "extra" in err


def test_empty_archive_says_it_found_nothing(capsys, square, tmp_path):
    rays = _rays(tmp_path)
    err = _trace_error(capsys, square, rays, tmp_path)
    assert "missing array 'origins'" in err and "found: nothing" in err


@pytest.mark.parametrize("name", ["origins", "directions"])
@pytest.mark.parametrize("shape", [(2, 2), (2,), (2, 3, 1), (2, 4)])
def test_wrong_shape(capsys, square, tmp_path, name, shape):
    origins, directions = _good()
    arrays = {"origins": origins, "directions": directions}
    arrays[name] = np.zeros(shape, np.float32)
    rays = _rays(tmp_path, **arrays)
    err = _trace_error(capsys, square, rays, tmp_path)
    expected = "[N, 3]" if name == "origins" else "[2, 3] like origins"
    assert f"'{name}' must have shape {expected}, got {shape}" in err


def test_mismatched_ray_counts(capsys, square, tmp_path):
    origins, _ = _good(3)
    _, directions = _good(2)
    rays = _rays(tmp_path, origins=origins, directions=directions)
    err = _trace_error(capsys, square, rays, tmp_path)
    assert "'directions' must have shape [3, 3] like origins, got (2, 3)" in err


@pytest.mark.parametrize("name", ["origins", "directions"])
@pytest.mark.parametrize(
    "dtype", [np.complex128, np.bool_, np.str_], ids=["complex128", "bool", "str"]
)
def test_non_float_dtype(capsys, square, tmp_path, name, dtype):
    origins, directions = _good()
    arrays = {"origins": origins, "directions": directions}
    arrays[name] = arrays[name].astype(dtype)
    rays = _rays(tmp_path, **arrays)
    err = _trace_error(capsys, square, rays, tmp_path)
    shape = "[N, 3]" if name == "origins" else "[2, 3] like origins"
    assert f"'{name}' must be float32 {shape}, got dtype {arrays[name].dtype}" in err


def test_object_dtype_names_the_file(capsys, square, tmp_path):
    origins, directions = _good()
    rays = _rays(tmp_path, origins=origins.astype(object), directions=directions)
    err = _trace_error(capsys, square, rays, tmp_path)
    assert str(rays) in err and "'origins'" in err


def test_integer_rays_are_accepted_as_float(capsys, square, tmp_path):
    # The documented check is "float [N, 3] (stored as float32)"; integer arrays convert exactly.
    rays = _rays(tmp_path, origins=np.array([[0, 0, 1]]), directions=np.array([[0, 0, -1]]))
    out = tmp_path / "hits.npz"
    _trace(capsys, square, rays, out)
    with np.load(out) as hits:
        assert hits["t"][0] == pytest.approx(1.0, abs=1e-6)
        assert hits["triangle"][0] in (0, 1)  # (0, 0) is a corner of both faces


@pytest.mark.parametrize(
    "name, row, value, shown",
    [
        ("origins", 1, [0.25, np.nan, 1.0], "[0.25, nan, 1.0]"),
        ("origins", 0, [np.inf, 0.0, 1.0], "[inf, 0.0, 1.0]"),
        ("directions", 1, [0.0, 0.0, -np.inf], "[0.0, 0.0, -inf]"),
        ("directions", 0, [np.nan, 0.0, 0.0], "[nan, 0.0, 0.0]"),
    ],
)
def test_non_finite_values(capsys, square, tmp_path, name, row, value, shown):
    origins, directions = _good(3)
    arrays = {"origins": origins, "directions": directions}
    arrays[name][row] = value
    rays = _rays(tmp_path, **arrays)
    err = _trace_error(capsys, square, rays, tmp_path)
    assert (
        f"'{name}' has 1 rows with NaN or infinite values (first: row {row} = {shown}); "
        "all must be finite"
    ) in err


@pytest.mark.filterwarnings("ignore:overflow encountered in cast:RuntimeWarning")
def test_float64_origin_too_large_for_float32(capsys, square, tmp_path):
    origins, directions = _good()
    origins = origins.astype(np.float64)
    origins[0, 0] = 1e39
    rays = _rays(tmp_path, origins=origins, directions=directions)
    err = _trace_error(capsys, square, rays, tmp_path)
    assert "'origins' has 1 rows with NaN or infinite values" in err


@pytest.mark.parametrize("scale", [0.0, 9e-7, 1e-30, 1.1e6, 1e30])
def test_direction_length_out_of_range(capsys, square, tmp_path, scale):
    """The library's rule (jrt.engine.DIRECTION_LENGTHS), in the library's words."""
    origins, directions = _good(3)
    directions[2] *= np.float32(scale)
    rays = _rays(tmp_path, origins=origins, directions=directions)
    err = _trace_error(capsys, square, rays, tmp_path)
    assert (f"directions of ray 2 is {directions[2].tolist()} "
            f"(length {abs(float(directions[2, 2])):.6g}; 1 such rays of 3); allowed: a "
            "length within [1e-06, 1e+06] (t is in units of that length)") in err


@pytest.mark.parametrize("scale", [2.0**-19, 1e-3, 0.5, 0.9991, 1.002, 3.0, 2.0**19])
def test_non_unit_direction_measures_t_in_its_length(capsys, square, tmp_path, scale):
    """As the library: any length within [1e-6, 1e6], t in units of it (1 / scale here,
    a distance of 1), tmax too."""
    origins, directions = _good(3)
    directions[1:] *= np.float32(scale)
    tmax = np.float32([np.inf, np.inf, 0.5 / scale])  # ray 2 stops halfway: a miss
    rays = _rays(tmp_path, origins=origins, directions=directions, tmax=tmax)
    out = tmp_path / "hits.npz"
    _trace(capsys, square, rays, out)
    with np.load(out) as hits:
        np.testing.assert_allclose(hits["t"], [1.0, 1.0 / np.float32(scale), np.inf],
                                   rtol=1e-6)
        np.testing.assert_array_equal(hits["triangle"] >= 0, [True, True, False])


@pytest.mark.parametrize("shape", [(2, 1), (3,), (1,), ()])
def test_tmax_wrong_shape(capsys, square, tmp_path, shape):
    origins, directions = _good()
    rays = _rays(tmp_path, origins=origins, directions=directions, tmax=np.ones(shape, np.float32))
    err = _trace_error(capsys, square, rays, tmp_path)
    assert f"'tmax' must have shape [2], got {shape}" in err


@pytest.mark.parametrize(
    "bad, shown", [(0.0, "0.0"), (-1.0, "-1.0"), (-np.inf, "-inf"), (np.nan, "nan")]
)
def test_tmax_not_positive(capsys, square, tmp_path, bad, shown):
    origins, directions = _good(3)
    rays = _rays(tmp_path, origins=origins, directions=directions, tmax=np.float32([1.0, bad, 2.0]))
    err = _trace_error(capsys, square, rays, tmp_path)
    assert f"'tmax' must be > 0 (inf for no limit); row 1 is {shown}" in err


def test_tmax_non_float_dtype(capsys, square, tmp_path):
    origins, directions = _good()
    rays = _rays(tmp_path, origins=origins, directions=directions, tmax=np.array([1 + 0j, 2 + 0j]))
    err = _trace_error(capsys, square, rays, tmp_path)
    assert "'tmax' must be float32 [2], got dtype complex128" in err


# --------------------------------------------------------------------------------------
# End to end on the unit square
# --------------------------------------------------------------------------------------

# (origin, direction, expected t, triangle, u, v); the hit point is
# (1-u-v) v0 + u v1 + v v2 of the face, worked out by hand.
CASES = [
    # Inside face 0 (0,0)(1,0)(1,1): (0.75, 0.25) = 0.25*(0,0) + 0.5*(1,0) + 0.25*(1,1).
    ([0.75, 0.25, 1.0], DOWN, 1.0, 0, 0.5, 0.25),
    # Inside face 1 (0,0)(1,1)(0,1): (0.25, 0.75) = 0.25*(0,0) + 0.25*(1,1) + 0.5*(0,1).
    ([0.25, 0.75, 1.0], DOWN, 1.0, 1, 0.25, 0.5),
    # On the shared diagonal: both faces at t=1, the lower face index wins (tie rule).
    ([0.25, 0.25, 1.0], DOWN, 1.0, 0, 0.0, 0.25),
    # From below (no back-face culling), from farther away.
    ([0.75, 0.25, -2.5], UP, 2.5, 0, 0.5, 0.25),
    # Outside the square: a miss.
    ([1.5, 0.5, 1.0], DOWN, np.inf, -1, 0.0, 0.0),
    # Pointing away from the square: a miss.
    ([0.75, 0.25, 1.0], UP, np.inf, -1, 0.0, 0.0),
    # Parallel to the plane, above it: a miss.
    ([-1.0, 0.5, 0.5], [1.0, 0.0, 0.0], np.inf, -1, 0.0, 0.0),
    # A 3-4-5 slanted ray from (0.75-0.6, 0.25, 0.8) to (0.75, 0.25, 0): t = 1.
    ([0.15, 0.25, 0.8], [0.6, 0.0, -0.8], 1.0, 0, 0.5, 0.25),
]


@pytest.fixture
def case_rays(tmp_path):
    origins = np.array([c[0] for c in CASES], np.float32)
    directions = np.array([c[1] for c in CASES], np.float32)
    return _rays(tmp_path, "cases.npz", origins=origins, directions=directions)


def _expected(field):
    index = {"t": 2, "triangle": 3, "u": 4, "v": 5}[field]
    return np.array([c[index] for c in CASES])


@pytest.mark.parametrize("accel", ("brute", "bvh"))
@pytest.mark.parametrize("kernel", tuple(KERNELS))
def test_closest_hits_match_hand_worked_values(capsys, square, case_rays, tmp_path, kernel,
                                               accel):
    out = tmp_path / "hits.npz"
    stdout = _trace(capsys, square, case_rays, out, "--kernel", kernel, "--accel", accel)
    assert "square.off: 4 vertices, 2 triangles" in stdout
    assert f"{len(CASES)} rays, 5 hits" in stdout
    with np.load(out) as hits:
        assert set(hits.files) == {"t", "triangle", "u", "v"}
        assert hits["t"].dtype == np.float32 and hits["triangle"].dtype == np.int32
        assert hits["u"].dtype == np.float32 and hits["v"].dtype == np.float32
        np.testing.assert_array_equal(hits["triangle"], _expected("triangle"))
        t = hits["t"]
        miss = _expected("triangle") == -1
        assert np.isposinf(t[miss]).all()
        np.testing.assert_allclose(t[~miss], _expected("t")[~miss], atol=1e-6)
        np.testing.assert_allclose(hits["u"], _expected("u"), atol=1e-6)
        np.testing.assert_allclose(hits["v"], _expected("v"), atol=1e-6)
        # A miss is exactly (inf, -1, 0, 0).
        assert (hits["u"][miss] == 0).all() and (hits["v"][miss] == 0).all()


def test_every_kernel_gives_the_same_result(capsys, square, case_rays, tmp_path):
    results = {}
    for kernel in KERNELS:
        out = tmp_path / f"hits_{kernel}.npz"
        _trace(capsys, square, case_rays, out, "--kernel", kernel)
        with np.load(out) as hits:
            results[kernel] = {k: hits[k] for k in hits.files}
    first = results[next(iter(KERNELS))]
    for kernel, result in results.items():
        np.testing.assert_array_equal(result["triangle"], first["triangle"], err_msg=kernel)
        for key in ("t", "u", "v"):
            np.testing.assert_allclose(result[key], first[key], atol=1e-6, err_msg=kernel)


def test_unknown_accel_is_refused_with_the_allowed_names(capsys, square, case_rays, tmp_path):
    with pytest.raises(SystemExit) as exc:
        main(["trace", str(square), str(case_rays), "-o", str(tmp_path / "h.npz"),
              "--accel", "octree9"])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "octree9" in err and "bvh" in err and "brute" in err


def test_default_kernel_is_accepted_without_the_option(capsys, square, case_rays, tmp_path):
    out = tmp_path / "hits.npz"
    _trace(capsys, square, case_rays, out)
    with np.load(out) as hits:
        np.testing.assert_array_equal(hits["triangle"], _expected("triangle"))


def test_tmax_shorter_than_the_hit_makes_a_miss(capsys, square, tmp_path):
    # Four rays straight down onto (0.75, 0.25) from z=1: the hit is at t=1.
    origins = np.tile(np.float32([0.75, 0.25, 1.0]), (4, 1))
    directions = np.tile(np.float32(DOWN), (4, 1))
    tmax = np.float32([0.5, 0.999, 1.001, np.inf])
    rays = _rays(tmp_path, origins=origins, directions=directions, tmax=tmax)
    out = tmp_path / "hits.npz"
    stdout = _trace(capsys, square, rays, out)
    assert "4 rays, 2 hits" in stdout
    with np.load(out) as hits:
        np.testing.assert_array_equal(hits["triangle"], [-1, -1, 0, 0])
        assert np.isposinf(hits["t"][:2]).all()
        np.testing.assert_allclose(hits["t"][2:], 1.0, atol=1e-6)
        np.testing.assert_array_equal(hits["u"][:2], 0)
        np.testing.assert_array_equal(hits["v"][:2], 0)


@pytest.mark.parametrize("kernel", tuple(KERNELS))
def test_any_hit_writes_occluded(capsys, square, tmp_path, kernel):
    origins = np.float32(
        [
            [0.75, 0.25, 1.0],  # hits at t=1, no limit: occluded
            [0.75, 0.25, 1.0],  # hits at t=1 but tmax 0.5: not occluded
            [0.75, 0.25, 1.0],  # hits at t=1, tmax 1.5: occluded
            [1.5, 0.5, 1.0],  # misses the square: not occluded
            [0.25, 0.75, -1.0],  # from below, upwards: occluded
        ]
    )
    directions = np.float32([DOWN, DOWN, DOWN, DOWN, UP])
    tmax = np.float32([np.inf, 0.5, 1.5, np.inf, np.inf])
    rays = _rays(tmp_path, origins=origins, directions=directions, tmax=tmax)
    out = tmp_path / "occ.npz"
    stdout = _trace(capsys, square, rays, out, "--any-hit", "--kernel", kernel)
    assert "5 rays, 3 occluded" in stdout
    with np.load(out) as result:
        assert result.files == ["occluded"]
        assert result["occluded"].dtype == np.bool_
        np.testing.assert_array_equal(result["occluded"], [True, False, True, False, True])


@pytest.mark.parametrize(
    "given, written", [("hits", "hits.npz"), ("hits.dat", "hits.dat.npz"), ("hits.npz", "hits.npz")]
)
def test_npz_suffix_is_added_when_missing(capsys, square, case_rays, tmp_path, given, written):
    stdout = _trace(capsys, square, case_rays, tmp_path / given)
    path = tmp_path / written
    assert path.is_file()
    assert stdout.rstrip().endswith(f"-> {path}")
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
        {"square.off", "cases.npz", written}
    )
    with np.load(path) as hits:
        np.testing.assert_array_equal(hits["triangle"], _expected("triangle"))


def test_output_folder_is_created(capsys, square, case_rays, tmp_path):
    out = tmp_path / "new" / "sub" / "hits"
    _trace(capsys, square, case_rays, out)
    assert (tmp_path / "new" / "sub" / "hits.npz").is_file()


def test_zero_rays(capsys, square, tmp_path):
    rays = _rays(
        tmp_path, origins=np.zeros((0, 3), np.float32), directions=np.zeros((0, 3), np.float32)
    )
    out = tmp_path / "hits.npz"
    stdout = _trace(capsys, square, rays, out)
    assert "0 rays, 0 hits" in stdout
    with np.load(out) as hits:
        assert hits["t"].shape == (0,) and hits["triangle"].shape == (0,)


def test_trace_times_compile_and_trace_apart(capsys, square, case_rays, tmp_path):
    """The printed rate is the file's rays over the timed call (compile timed before it,
    on rays of the same shapes), never a rate with the compile included."""
    stdout = _trace(capsys, square, case_rays, tmp_path / "hits.npz")
    found = re.search(r"(\d+) rays, 5 hits in (\d+\.\d+) s \(([\d.e+-]+) Mrays/s; compiled "
                      r"first, in (\d+\.\d+) s\)", stdout)
    assert found, stdout
    rays, seconds, rate = int(found.group(1)), float(found.group(2)), float(found.group(3))
    assert rays == len(CASES) and rate > 0
    if seconds >= 0.01:  # printed to the millisecond: the quotient is meaningful
        assert rate == pytest.approx(rays / seconds / 1e6, rel=0.1)
    assert "compile included" not in stdout


# --------------------------------------------------------------------------------------
# Meshes: what the command refuses, and what it notes
# --------------------------------------------------------------------------------------


def test_a_directory_given_as_mesh_is_named_a_directory(capsys, case_rays, tmp_path):
    folder = tmp_path / "meshes"
    folder.mkdir()
    err = _trace_error(capsys, folder, case_rays, tmp_path)
    assert f"{folder}: is a directory, not a mesh file" in err
    assert "unsupported mesh format" not in err


def test_a_text_file_named_obj_is_not_a_mesh(capsys, case_rays, tmp_path):
    notes = tmp_path / "notes.obj"
    notes.write_text("shopping list\nmilk\n")
    err = _trace_error(capsys, notes, case_rays, tmp_path)
    assert f"{notes}: not a mesh: no vertex ('v x y z') or face ('f i j k') lines" in err
    assert "empty mesh" not in err


def test_an_off_quad_is_split_with_a_note(capsys, case_rays, tmp_path):
    """The square as one quad: a note says it was split, and the hits (triangle and t)
    are the hand-worked ones of the square's two triangles."""
    quad = tmp_path / "quad.off"
    quad.write_text("OFF\n4 1 0\n0 0 0\n1 0 0\n1 1 0\n0 1 0\n4 0 1 2 3\n")
    out = tmp_path / "hits.npz"
    code = main(["trace", str(quad), str(case_rays), "-o", str(out)])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    assert captured.err == (f"jrt trace: note: {quad}: split 1 quad into 2 triangles (1 face "
                            "in the file, 2 triangles: face indices count the triangles)\n")
    assert "quad.off: 4 vertices, 2 triangles" in captured.out
    with np.load(out) as hits:
        np.testing.assert_array_equal(hits["triangle"], _expected("triangle"))
        np.testing.assert_allclose(hits["t"], _expected("t"), atol=1e-6)


def test_a_degenerate_face_is_a_note_without_a_source_line(capsys, case_rays, tmp_path):
    """The square with a third, zero-area face: one note line on stderr (no Python
    warning category, no source line), and the face is never hit."""
    path = tmp_path / "sliver.off"
    path.write_text(SQUARE_OFF.replace("4 2 0", "4 3 0") + "3 0 1 1\n")
    out = tmp_path / "hits.npz"
    code = main(["trace", str(path), str(case_rays), "-o", str(out)])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    assert captured.err == (f"jrt trace: note: {path}: 1 degenerate (zero-area) triangle "
                            "kept but never hit (first: face 2)\n")
    with np.load(out) as hits:
        np.testing.assert_array_equal(hits["triangle"], _expected("triangle"))
