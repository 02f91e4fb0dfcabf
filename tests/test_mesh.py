"""jrt.mesh: validation errors of mesh_from_arrays / load_mesh, degenerate triangles, formats."""

from __future__ import annotations

import gzip
import re
import warnings

import numpy as np
import pytest
import trimesh

import accel
import jrt
from jrt.mesh import SUFFIXES, Mesh, MeshError, MeshWarning, load_mesh, mesh_from_arrays

# A right triangle in the z=0 plane, well away from the origin-centred degenerate ones below.
TRIANGLE_V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float64)
TRIANGLE_F = np.array([[0, 1, 2]], np.int64)

# A tetrahedron with exactly representable, non-trivial coordinates (binary fractions).
TET_V = np.array(
    [[0.5, -1.25, 2.0], [3.0, -1.25, 2.0], [0.5, 1.75, 2.0], [0.5, -1.25, 4.5]], np.float64
)
TET_F = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]], np.int64)


def _valid(vertices=TRIANGLE_V, faces=TRIANGLE_F, name="tri"):
    return mesh_from_arrays(vertices, faces, name=name)


# --------------------------------------------------------------------------------------
# mesh_from_arrays: one test per validation error
# --------------------------------------------------------------------------------------


def test_valid_triangle_is_accepted_with_float32_and_int32():
    mesh = _valid()
    assert isinstance(mesh, Mesh)
    assert mesh.vertices.dtype == np.float32 and mesh.vertices.shape == (3, 3)
    assert mesh.faces.dtype == np.int32 and mesh.faces.shape == (1, 3)
    assert mesh.degenerate.shape == (0,)
    np.testing.assert_array_equal(mesh.vertices, TRIANGLE_V)
    np.testing.assert_array_equal(mesh.faces, TRIANGLE_F)
    assert mesh.summary() == "tri: 3 vertices, 1 triangles"
    assert "degenerate" not in mesh.summary()


def test_mesh_error_is_a_value_error():
    # Callers that catch ValueError (e.g. the CLI) also catch MeshError.
    assert issubclass(MeshError, ValueError)


def test_zero_vertices_is_an_empty_mesh():
    with pytest.raises(
        MeshError,
        match=r"tri: empty mesh \(0 vertices, 1 faces\).*at least one "
        r"triangle is needed",
    ):
        _valid(vertices=np.zeros((0, 3)))


def test_zero_faces_is_an_empty_mesh():
    with pytest.raises(
        MeshError,
        match=r"tri: empty mesh \(3 vertices, 0 faces\).*at least one "
        r"triangle is needed",
    ):
        _valid(faces=np.zeros((0, 3), np.int64))


def test_zero_faces_as_a_plain_empty_list_is_an_empty_mesh():
    with pytest.raises(MeshError, match=r"empty mesh \(3 vertices, 0 faces\)"):
        _valid(faces=[])


def test_vertices_of_wrong_shape():
    with pytest.raises(MeshError, match=re.escape("vertices must have shape [V, 3], got (3, 2)")):
        _valid(vertices=TRIANGLE_V[:, :2])


def test_complex_vertices_are_rejected():
    with pytest.raises(MeshError, match=r"vertices must be real numbers, got dtype complex128"):
        _valid(vertices=TRIANGLE_V.astype(np.complex128))


@pytest.mark.parametrize(
    ("row", "column", "value", "shown"),
    [
        (1, 2, np.nan, r"vertex 1 = \[1\.0, 0\.0, nan\]"),
        (2, 0, np.inf, r"vertex 2 = \[inf, 1\.0, 0\.0\]"),
    ],
    ids=["nan", "positive_inf"],
)
def test_non_finite_vertex(row, column, value, shown):
    v = TRIANGLE_V.copy()
    v[row, column] = value
    with pytest.raises(
        MeshError,
        match=r"1 vertices have NaN or infinite coordinates.*" + shown
        + r".*all coordinates must be finite",
    ):
        _valid(vertices=v)


def test_float64_vertex_too_large_for_float32_becomes_inf():
    # 1e39 is finite in float64 but beyond float32's max (~3.4e38): inf once stored.
    assert 1e39 > float(np.finfo(np.float32).max)
    v = TRIANGLE_V.copy()
    v[0, 1] = 1e39
    with pytest.raises(
        MeshError,
        match=r"NaN or infinite coordinates \(in float32\).*vertex 0.*1e\+39"
        r".*all coordinates must be finite",
    ):
        _valid(vertices=v)


def test_largest_float32_vertex_is_still_accepted():
    v = TRIANGLE_V.copy()
    v[0, 1] = float(np.finfo(np.float32).max)
    mesh = _valid(vertices=v)
    assert np.isfinite(mesh.vertices).all()


def test_quad_faces_are_rejected():
    square = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float)
    with pytest.raises(
        MeshError,
        match=r"faces must be triangles, shape \[F, 3\]; got 4 corners per face "
        r"\(shape \(1, 4\)\).*triangulate",
    ):
        _valid(vertices=square, faces=np.array([[0, 1, 2, 3]]))


def test_flat_face_list_is_rejected():
    with pytest.raises(MeshError, match=r"faces must be triangles, shape \[F, 3\]"):
        _valid(faces=np.array([0, 1, 2]))


def test_non_integer_face_index():
    with pytest.raises(MeshError, match=r"face indices must be integers, got dtype float64"):
        _valid(faces=np.array([[0, 0.5, 2]]))


def test_nan_face_index():
    with pytest.raises(MeshError, match=r"face indices must be integers, got dtype float64"):
        _valid(faces=np.array([[0, np.nan, 2]]))


def test_whole_float_face_indices_are_accepted_as_integers():
    mesh = _valid(faces=np.array([[0.0, 1.0, 2.0]]))
    assert mesh.faces.dtype == np.int32
    np.testing.assert_array_equal(mesh.faces, [[0, 1, 2]])


def test_negative_face_index():
    with pytest.raises(
        MeshError,
        match=re.escape(
            "face 0 = [0, -1, 2] refers to a vertex out of range; allowed indices are 0..2"
        ),
    ):
        _valid(faces=np.array([[0, -1, 2]]))


def test_face_index_equal_to_vertex_count():
    faces = np.array([[0, 1, 2], [1, 2, 3]])
    with pytest.raises(
        MeshError,
        match=re.escape(
            "face 1 = [1, 2, 3] refers to a vertex out of range; allowed indices are 0..2"
        ),
    ):
        _valid(faces=faces)


def test_all_faces_degenerate():
    collinear = np.array([[0, 0, 0], [1, 1, 1], [2, 2, 2]], float)
    with pytest.raises(MeshError, match=r"tri: all 2 triangles are degenerate \(zero area\)"):
        _valid(vertices=collinear, faces=np.array([[0, 1, 2], [0, 0, 1]]))


def test_all_faces_degenerate_message_states_the_rule():
    collinear = np.array([[0, 0, 0], [1, 1, 1], [2, 2, 2]], float)
    with pytest.raises(MeshError, match=r"(?i)at least one|non-?zero area|positive area"):
        _valid(vertices=collinear, faces=np.array([[0, 1, 2]]))


# --------------------------------------------------------------------------------------
# load_mesh: file-level errors
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["mesh.txt", "mesh.glb", "mesh"])
def test_unsupported_suffix(tmp_path, name):
    path = tmp_path / name
    path.write_text("OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n")
    with pytest.raises(
        MeshError,
        match=r"unsupported mesh format.*allowed: \.off, \.obj, "
        r"\.ply, \.stl",
    ):
        load_mesh(path)


def test_unsupported_suffix_names_the_suffix(tmp_path):
    with pytest.raises(MeshError, match=r"unsupported mesh format '\.txt'"):
        load_mesh(tmp_path / "mesh.txt")


def test_suffix_check_ignores_case(tmp_path):
    path = tmp_path / "tri.OFF"
    path.write_text("OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n")
    assert load_mesh(path).faces.tolist() == [[0, 1, 2]]


def test_missing_file(tmp_path):
    path = tmp_path / "nowhere.off"
    with pytest.raises(MeshError, match=rf"{re.escape(str(path))}: no such mesh file"):
        load_mesh(path)


@pytest.mark.parametrize("name", ["folder.off", "folder"])
def test_directory_is_not_a_mesh_file(tmp_path, name):
    folder = tmp_path / name
    folder.mkdir()
    with pytest.raises(MeshError, match=rf"^{re.escape(str(folder))}: is a directory, not a "
                       "mesh file$"):
        load_mesh(folder)


@pytest.mark.parametrize("content", ["shopping list\nmilk\n", ""])
def test_text_file_named_obj_is_not_a_mesh(tmp_path, content):
    path = tmp_path / "notes.obj"
    path.write_text(content)
    with pytest.raises(MeshError, match=r"notes\.obj: not a mesh: no vertex \('v x y z'\) or "
                       r"face \('f i j k'\) lines found"):
        load_mesh(path)


@pytest.mark.parametrize(
    "name, content",
    [
        # Header promises 3 vertices and 1 face; the file stops after two vertices.
        ("truncated.off", b"OFF\n3 1 0\n0 0 0\n1 0 0\n"),
        ("garbage.off", b"garbage\n1 2\n"),
        ("broken.ply", b"ply\nformat nonsense\n"),
    ],
)
def test_corrupt_file(tmp_path, name, content):
    path = tmp_path / name
    path.write_bytes(content)
    with pytest.raises(MeshError, match=rf"{re.escape(name)}: trimesh could not read it"):
        load_mesh(path)


def test_off_file_without_faces_is_an_empty_mesh(tmp_path):
    path = tmp_path / "points.off"
    path.write_text("OFF\n3 0 0\n0 0 0\n1 0 0\n0 1 0\n")
    with pytest.raises(MeshError, match=r"points\.off: empty mesh \(3 vertices, 0 faces\)"):
        load_mesh(path)


def test_file_errors_name_the_file_in_mesh_errors(tmp_path):
    path = tmp_path / "collinear.off"
    path.write_text("OFF\n3 1 0\n0 0 0\n1 0 0\n2 0 0\n3 0 1 2\n")
    with pytest.raises(
        MeshError,
        match=rf"^{re.escape(str(path))}: all 1 triangles are "
        r"degenerate",
    ):
        load_mesh(path)


# --------------------------------------------------------------------------------------
# Degenerate triangles: kept, listed, warned about, reported, never hit
# --------------------------------------------------------------------------------------

# Face 0: collinear corners on the x axis; face 1: a proper triangle around (10, 10, 0);
# face 2: a repeated vertex index (two corners the same point).
DEGEN_V = np.array(
    [[0, 0, 0], [1, 0, 0], [2, 0, 0], [10, 10, 0], [11, 10, 0], [10, 11, 0]], np.float64
)
DEGEN_F = np.array([[0, 1, 2], [3, 4, 5], [1, 1, 2]], np.int64)


@pytest.fixture
def degenerate_mesh():
    with pytest.warns(
        MeshWarning,
        match=r"deg: 2 degenerate \(zero-area\) triangles kept but "
        r"never hit \(first: face 0\)",
    ):
        return mesh_from_arrays(DEGEN_V, DEGEN_F, name="deg")


def test_degenerate_triangles_are_kept_and_listed(degenerate_mesh):
    np.testing.assert_array_equal(degenerate_mesh.faces, DEGEN_F)
    assert degenerate_mesh.degenerate.dtype == np.int32
    np.testing.assert_array_equal(degenerate_mesh.degenerate, [0, 2])


def test_degenerate_triangles_in_summary(degenerate_mesh):
    assert degenerate_mesh.summary() == (
        "deg: 6 vertices, 3 triangles, 2 degenerate (zero area, never hit)"
    )


def test_no_warning_without_degenerate_triangles():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        _valid()


def test_brute_structure_leaves_degenerate_triangles_out(degenerate_mesh):
    structure = accel.build("brute", degenerate_mesh.vertices, degenerate_mesh.faces)
    np.testing.assert_array_equal(structure["triangle_ids"], [1])
    assert structure.num_triangles == 1
    assert structure.stats["degenerate_skipped"] == 2
    np.testing.assert_array_equal(structure["triangles"][0], DEGEN_V[DEGEN_F[1]])


@pytest.mark.parametrize("kernel", tuple(jrt.KERNELS))
def test_rays_at_degenerate_triangles_miss(degenerate_mesh, kernel):
    structure = accel.build("brute", degenerate_mesh.vertices, degenerate_mesh.faces)
    origins = np.array(
        [
            [1.0, 0.0, 1.0],  # straight down onto (1, 0, 0): a corner of both degenerate faces
            [1.5, 0.0, 1.0],  # straight down onto (1.5, 0, 0): inside the collinear "segment"
            [10.25, 10.25, 1.0],  # straight down into the good triangle (face 1)
        ],
        np.float32,
    )
    directions = np.tile(np.float32([0, 0, -1]), (3, 1))
    hits = jrt.closest_hit(structure, origins, directions, kernel=kernel)
    np.testing.assert_array_equal(np.asarray(hits.triangle), [-1, -1, 1])
    t = np.asarray(hits.t)
    assert np.isposinf(t[:2]).all()
    assert t[2] == pytest.approx(1.0, abs=1e-6)


def test_degenerate_face_loaded_from_file_is_kept_with_file_indices(tmp_path):
    path = tmp_path / "deg.off"
    path.write_text(
        "OFF\n6 3 0\n0 0 0\n1 0 0\n2 0 0\n10 10 0\n11 10 0\n10 11 0\n3 0 1 2\n3 3 4 5\n3 1 1 2\n"
    )
    with pytest.warns(MeshWarning, match=r"2 degenerate"):
        mesh = load_mesh(path)
    np.testing.assert_array_equal(mesh.faces, DEGEN_F)
    np.testing.assert_array_equal(mesh.degenerate, [0, 2])


# --------------------------------------------------------------------------------------
# File formats
# --------------------------------------------------------------------------------------


def test_quad_off_file_is_fan_triangulated(tmp_path):
    path = tmp_path / "quad.off"
    path.write_text("OFF\n4 1 0\n0 0 0\n1 0 0\n1 1 0\n0 1 0\n4 0 1 2 3\n")
    with pytest.warns(MeshWarning, match=r"quad\.off: split 1 quad into 2 triangles \(1 face "
                      r"in the file, 2 triangles: face indices count the triangles\)"):
        mesh = load_mesh(path)
    assert mesh.faces.shape == (2, 3)
    assert mesh.degenerate.shape == (0,)
    # Every triangle lies in the square; together they cover its area (1) exactly once.
    corners = mesh.vertices[mesh.faces].astype(np.float64)
    areas = 0.5 * np.linalg.norm(
        np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1
    )
    np.testing.assert_allclose(areas, [0.5, 0.5])
    assert set(mesh.faces.ravel().tolist()) == {0, 1, 2, 3}
    # Orientation is kept: both normals point along +z like the quad's (0, 1, 2, 3) order.
    normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    assert (normals[:, 2] > 0).all()


@pytest.mark.parametrize("suffix", SUFFIXES)
def test_formats_load_as_float32_int32_with_the_same_geometry(tmp_path, suffix):
    assert suffix in (".off", ".obj", ".ply", ".stl")
    path = tmp_path / f"tet{suffix}"
    trimesh.Trimesh(TET_V, TET_F, process=False).export(path)
    mesh = load_mesh(path)
    assert mesh.name == str(path)
    assert mesh.vertices.dtype == np.float32
    assert mesh.faces.dtype == np.int32
    assert mesh.faces.shape == (4, 3)
    assert mesh.degenerate.shape == (0,)
    # STL stores three corners per face (no shared vertices), so compare the triangles'
    # corners, in face order and corner order (orientation kept).
    np.testing.assert_array_equal(mesh.vertices[mesh.faces], TET_V[TET_F])


def test_bounds_and_diagonal_of_loaded_mesh(tmp_path):
    path = tmp_path / "tet.off"
    trimesh.Trimesh(TET_V, TET_F, process=False).export(path)
    mesh = load_mesh(path)
    lo, hi = mesh.bounds
    np.testing.assert_array_equal(lo, [0.5, -1.25, 2.0])
    np.testing.assert_array_equal(hi, [3.0, 1.75, 4.5])
    assert mesh.diagonal == pytest.approx(np.sqrt(2.5**2 + 3.0**2 + 2.5**2))


def test_degenerate_warning_is_a_mesh_warning_and_a_user_warning():
    assert issubclass(MeshWarning, UserWarning)
    with pytest.warns(MeshWarning, match=r"deg: 1 degenerate \(zero-area\) triangle kept"):
        mesh_from_arrays(DEGEN_V, DEGEN_F[1:], name="deg")


# A quad (unit square, z=0) and a regular-ish pentagon (z=1) in one file, and a triangle.
POLY_V = [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0],
          [0, 0, 1], [2, 0, 1], [3, 1, 1], [1, 2, 1], [-1, 1, 1], [5, 5, 5], [6, 5, 5],
          [5, 6, 5]]
POLY_FACES = [[0, 1, 2, 3], [4, 5, 6, 7, 8], [9, 10, 11]]


def _shoelace_area(points) -> float:
    """Area of a planar polygon in a plane z = const (the shoelace formula, float64)."""
    x, y = np.asarray(points, np.float64)[:, 0], np.asarray(points, np.float64)[:, 1]
    return 0.5 * abs(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


# trimesh's OFF reader fails on files mixing faces of five or more corners with others
# (numpy 2 string arithmetic in triangulate_quads); its OBJ reader takes them.
@pytest.mark.parametrize("suffix, faces, note", [
    (".off", [POLY_FACES[0], POLY_FACES[2]], "split 1 quad into 2 triangles \\(2 faces in the "
     "file, 3 triangles"),
    (".obj", POLY_FACES, "split 1 quad and 1 polygon of 5 corners into 5 triangles \\(3 faces "
     "in the file, 6 triangles"),
])
def test_polygons_are_split_with_a_note_that_counts_them(tmp_path, suffix, faces, note):
    """Quads and pentagons become 2 and 3 triangles, the note counts them, and the
    triangles cover each polygon's area (shoelace formula) once, with its orientation."""
    path = tmp_path / f"poly{suffix}"
    if suffix == ".off":
        lines = [f"OFF\n{len(POLY_V)} {len(faces)} 0"]
        lines += [" ".join(map(str, v)) for v in POLY_V]
        lines += [" ".join(map(str, [len(f), *f])) for f in faces]
    else:
        lines = ["v " + " ".join(map(str, v)) for v in POLY_V]
        lines += ["f " + " ".join(str(i + 1) for i in f) for f in faces]
    path.write_text("\n".join(lines) + "\n")
    with pytest.warns(MeshWarning, match=rf"poly{suffix}: {note}"):
        mesh = load_mesh(path)
    assert mesh.faces.shape == (sum(len(f) - 2 for f in faces), 3)
    corners = mesh.vertices[mesh.faces].astype(np.float64)
    cross = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    assert (cross[:, 2] > 0).all()  # every polygon listed counter-clockwise seen from +z
    for face in faces:
        z = POLY_V[face[0]][2]
        mine = corners[:, :, 2].max(axis=1) == z
        assert 0.5 * cross[mine, 2].sum() == pytest.approx(
            _shoelace_area([POLY_V[i] for i in face]), rel=1e-6)


def test_ply_polygons_are_split_with_a_note(tmp_path):
    path = tmp_path / "quad.ply"
    path.write_text("ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\n"
                    "property float y\nproperty float z\nelement face 1\n"
                    "property list uchar int vertex_indices\nend_header\n"
                    "0 0 0\n1 0 0\n1 1 0\n0 1 0\n4 0 1 2 3\n")
    with pytest.warns(MeshWarning, match=r"quad\.ply: split its faces of more than three "
                      r"corners into triangles \(1 face in the file, 2 triangles"):
        mesh = load_mesh(path)
    assert mesh.faces.shape == (2, 3)


@pytest.mark.parametrize("suffix", SUFFIXES)
def test_triangle_files_load_without_a_note(tmp_path, suffix):
    """No polygon note (nor any warning) for a file of triangles, in every format."""
    path = tmp_path / f"tet{suffix}"
    trimesh.Trimesh(TET_V, TET_F, process=False).export(path)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert load_mesh(path).faces.shape == (4, 3)


# --------------------------------------------------------------------------------------
# PLY triangle strips ('tristrips'): read as their triangles
# --------------------------------------------------------------------------------------

# A ribbon of unit squares in z = 0 (vertices 0-5, zig-zag: bottom, top, bottom, ...) and a
# unit square in z = 1 (vertices 6-9), as triangle strips: the ribbon's strip, -1, the
# square's strip; a second row whose only triangles repeat a vertex (a join).
STRIP_V = np.array([[0, 0, 0], [0, 1, 0], [1, 0, 0], [1, 1, 0], [2, 0, 0], [2, 1, 0],
                    [0, 0, 1], [0, 1, 1], [1, 0, 1], [1, 1, 1]], np.float64)
STRIP_ROWS = [[0, 1, 2, 3, 4, 5, -1, 6, 7, 8, 9], [3, 3, 6]]
# Triangle j of a strip: (v_j, v_j+1, v_j+2), its first two swapped for odd j (counted from
# the strip's (re)start), so that all keep one orientation.
STRIP_F = [[0, 1, 2], [2, 1, 3], [2, 3, 4], [4, 3, 5], [6, 7, 8], [8, 7, 9]]


def _strip_ply(fmt: str, vertices=STRIP_V, rows=STRIP_ROWS) -> bytes:
    header = (f"ply\nformat {fmt} 1.0\ncomment triangle strips\n"
              f"element vertex {len(vertices)}\nproperty float x\nproperty float y\n"
              f"property float z\nproperty uchar confidence\n"
              f"element tristrips {len(rows)}\nproperty list int int vertex_indices\n"
              "end_header\n").encode()
    if fmt == "ascii":
        body = "".join(" ".join(f"{x:g}" for x in v) + " 255\n" for v in vertices)
        body += "".join(f"{len(r)} " + " ".join(map(str, r)) + "\n" for r in rows)
        return header + body.encode()
    order = "<" if fmt == "binary_little_endian" else ">"
    body = b"".join(np.asarray(v, order + "f4").tobytes() + b"\xff" for v in vertices)
    body += b"".join(np.array([len(r), *r], order + "i4").tobytes() for r in rows)
    return header + body


def test_strip_triangles_alternate_and_restart():
    faces, skipped = jrt.mesh.strip_triangles(STRIP_ROWS)
    np.testing.assert_array_equal(faces, STRIP_F)
    assert skipped == 1  # (3, 3, 6)
    # A turn inside a strip (a repeated index) keeps the alternation going: triangle 3 of
    # 0 1 2 2 3 4 is odd, so (3, 2, 4); triangles 1 and 2 repeat vertex 2.
    faces, skipped = jrt.mesh.strip_triangles([[0, 1, 2, 2, 3, 4]])
    np.testing.assert_array_equal(faces, [[0, 1, 2], [3, 2, 4]])
    assert skipped == 2
    assert jrt.mesh.strip_triangles([[0, 1], [-1], []])[0].shape == (0, 3)


@pytest.mark.parametrize("fmt", ["ascii", "binary_little_endian", "binary_big_endian"])
def test_ply_triangle_strips_are_read_as_triangles(tmp_path, fmt):
    path = tmp_path / "strips.ply"
    path.write_bytes(_strip_ply(fmt))
    with pytest.warns(MeshWarning, match=r"strips\.ply: read 2 triangle strips \('tristrips'\) "
                      r"as 6 triangles; face indices count them in strip order \(1 triangle "
                      r"with a repeated vertex"):
        mesh = load_mesh(path)
    np.testing.assert_array_equal(mesh.vertices, STRIP_V.astype(np.float32))
    np.testing.assert_array_equal(mesh.faces, STRIP_F)
    # Independently of the strip rule: one orientation (every normal along -z, as the
    # first triangle's), and the triangles cover the 2 x 1 ribbon and the unit square once.
    corners = mesh.vertices[mesh.faces].astype(np.float64)
    normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    np.testing.assert_array_equal(normal[:, :2], 0)
    assert (normal[:, 2] < 0).all()
    lower = corners[:, 0, 2] == 0
    assert -0.5 * normal[lower, 2].sum() == 2.0 and -0.5 * normal[~lower, 2].sum() == 1.0


def test_gzipped_ply_triangle_strips(tmp_path):
    path = tmp_path / "strips.ply.gz"
    path.write_bytes(gzip.compress(_strip_ply("binary_little_endian")))
    with pytest.warns(MeshWarning, match="tristrips"):
        np.testing.assert_array_equal(load_mesh(path).faces, STRIP_F)


@pytest.mark.parametrize("fmt, cut", [("binary_little_endian", 6), ("ascii", 8)])
def test_truncated_ply_triangle_strips_name_what_is_unread(tmp_path, fmt, cut):
    path = tmp_path / "cut.ply"
    path.write_bytes(_strip_ply(fmt)[:-cut])
    with pytest.raises(MeshError, match=r"cut\.ply: PLY with 10 vertices and no 'face' "
                       r"element; its triangle strips \('tristrips'\) could not be read: the "
                       r"file ends inside element 'tristrips'; convert the strips to faces"):
        load_mesh(path)


@pytest.mark.parametrize("faces, shown", [("", "no 'face' element"),
                                          ("element face 0\nproperty list uchar int "
                                           "vertex_indices\n", "an empty 'face' element")])
def test_ply_without_faces_or_strips_says_what_it_has(tmp_path, faces, shown):
    path = tmp_path / "points.ply"
    path.write_text("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\n"
                    f"property float y\nproperty float z\n{faces}end_header\n"
                    "0 0 0\n1 0 0\n0 1 0\n")
    with pytest.raises(MeshError, match=rf"points\.ply: PLY with 3 vertices and {shown} \(its "
                       r"elements: vertex \(3\).*\): no triangles to trace; jrt reads triangles "
                       r"from a 'face' element, or triangle strips from a 'tristrips' element"):
        load_mesh(path)
