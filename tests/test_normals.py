"""Corner normals (jrt.normals): against analytic normals, across file formats, and in renders.

References are independent of the code under test: a cube's face normals read off its
coordinates (the axis on which a face's three corners agree), a sphere's normal p / r,
the cube's corner direction p / |p| at crease 180 (each cube face spans 90° at each of its
corners, however it is cut into triangles), and the same box written as STL (every triangle
its own vertices) and as OBJ (shared vertices) through trimesh.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import trimesh

import accel
from jrt import frame_mesh, load_mesh, mesh_from_arrays
from jrt.normals import corner_normals, crease_edges
from jrt.render import render_lambert
from jrt.scene import SceneError, assemble, parse_scene


@pytest.fixture(scope="module")
def box_files(tmp_path_factory):
    """A unit cube centred at the origin as (STL mesh, OBJ mesh), loaded by jrt.load_mesh."""
    folder = tmp_path_factory.mktemp("box")
    box = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    box.export(folder / "box.stl")
    box.export(folder / "box.obj")
    stl, obj = load_mesh(folder / "box.stl"), load_mesh(folder / "box.obj")
    # The two files really differ in how they share vertices, not in the surface.
    assert len(stl.vertices) == 36 and len(obj.vertices) == 8
    np.testing.assert_array_equal(stl.vertices[stl.faces], obj.vertices[obj.faces])
    return stl, obj


def _cube_face_normals(corners: np.ndarray) -> np.ndarray:
    """[F, 3] outward normals of an origin-centred cube's triangles [F, 3, 3]: the axis on
    which the three corners agree, signed by the side they lie on."""
    agree = np.all(corners == corners[:, :1], axis=1)  # [F, 3]
    assert np.all(agree.sum(axis=1) == 1)
    return agree * np.sign(corners[:, 0])


def _unit_rows(a: np.ndarray) -> bool:
    return bool(np.all(np.isfinite(a)) and np.allclose(np.linalg.norm(a, axis=-1), 1, atol=1e-6))


def test_cube_from_stl_and_obj_gets_the_analytic_face_normals(box_files):
    stl, obj = box_files
    n_stl = corner_normals(stl.vertices, stl.faces)  # default crease 30°: cube edges are 90°
    n_obj = corner_normals(obj.vertices, obj.faces)
    assert n_stl.shape == (12, 3, 3) and n_stl.dtype == np.float32
    np.testing.assert_array_equal(n_stl, n_obj)
    expected = _cube_face_normals(obj.vertices[obj.faces].astype(np.float64))
    np.testing.assert_allclose(n_obj, np.repeat(expected[:, None], 3, axis=1), atol=1e-7)
    creases, edges, dihedral = crease_edges(obj.vertices, obj.faces, 30.0)
    # 12 cube edges at 90° are creases; the 6 face diagonals are flat.
    assert (creases, edges) == (12, 18)
    np.testing.assert_allclose(np.sort(dihedral), [0.0] * 6 + [90.0] * 12, atol=1e-6)


def test_crease_0_is_flat_and_180_smooths_every_cube_corner(box_files):
    stl, obj = box_files
    p = obj.vertices[obj.faces].astype(np.float64)
    flat = corner_normals(obj.vertices, obj.faces, 0.0)
    np.testing.assert_allclose(flat, np.repeat(_cube_face_normals(p)[:, None], 3, axis=1),
                               atol=1e-7)
    for mesh in (stl, obj):
        smooth = corner_normals(mesh.vertices, mesh.faces, 180.0)
        # Angle weighting: every face of the cube spans 90° at each corner, whether one or
        # two of its triangles meet there, so the three faces weigh alike: p / |p|.
        np.testing.assert_allclose(smooth, p / np.linalg.norm(p, axis=2, keepdims=True),
                                   atol=1e-6)
    # Between 0 and 90 the cube stays flat; above 90 it rounds.
    np.testing.assert_array_equal(corner_normals(obj.vertices, obj.faces, 89.0), flat)
    assert not np.allclose(corner_normals(obj.vertices, obj.faces, 91.0), flat)


def test_fine_sphere_normals_match_position_over_radius():
    r = 2.5
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=r)
    v = np.asarray(sphere.vertices, np.float32)
    f = np.asarray(sphere.faces, np.int32)
    normals = corner_normals(v, f)
    p = v[f].astype(np.float64)
    analytic = p / np.linalg.norm(p, axis=2, keepdims=True)
    cos = (normals * analytic).sum(axis=2)
    assert cos.min() > np.cos(np.radians(0.2))
    # Unmerged (every triangle its own vertices, as in STL): the same normals exactly.
    unmerged = corner_normals(p.reshape(-1, 3).astype(np.float32),
                              np.arange(3 * len(f)).reshape(-1, 3))
    np.testing.assert_array_equal(unmerged, normals)
    assert crease_edges(v, f)[0] == 0


def test_degenerate_faces_give_unit_normals_and_leave_the_others_alone(box_files):
    _, obj = box_files
    v = np.concatenate([obj.vertices, [[5, 5, 5], [6, 6, 6], [7, 7, 7]]]).astype(np.float32)
    # A zero-area face on the cube's corner 0 (two corners at one position), and a
    # collinear one on its own.
    extra = np.array([[0, 0, 7], [8, 9, 10]])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # jrt.mesh warns about degenerate faces
        mesh = mesh_from_arrays(v, np.concatenate([obj.faces, extra]))
    assert len(mesh.degenerate) == 2
    for crease in (0.0, 30.0, 180.0):
        normals = corner_normals(mesh.vertices, mesh.faces, crease)
        assert _unit_rows(normals)
        np.testing.assert_array_equal(normals[:12],
                                      corner_normals(obj.vertices, obj.faces, crease))
    # The face on the cube's corner takes the mean of the faces there: p / |p|.
    p = obj.vertices[0].astype(np.float64)
    np.testing.assert_allclose(normals[12, 0], p / np.linalg.norm(p), atol=1e-6)


def test_bad_crease_angles_are_refused():
    v = np.eye(3, dtype=np.float32)
    f = np.array([[0, 1, 2]])
    for bad in (-1.0, 180.5, float("nan"), "thirty", True):
        with pytest.raises(ValueError, match="crease_angle"):
            corner_normals(v, f, bad)


def test_the_same_box_from_stl_and_obj_renders_alike(box_files):
    """The bar: an STL and an OBJ of one box give the same picture (32x24, Lambert; no
    shadow rays, which do not read the shading normals)."""
    stl, obj = box_files
    camera = frame_mesh(obj.vertices, width=32, height=24)
    images = []
    for mesh in (stl, obj):
        structure = accel.build("bvh", mesh.vertices, mesh.faces)
        image, _ = render_lambert(mesh, structure, camera, shadows=False)
        images.append(image)
    np.testing.assert_allclose(images[0], images[1], atol=1e-6)
    # The box is in the picture, and its shading depends on the normals: smoothing every
    # edge (crease 180) changes it, so the equality above is not of two blank images.
    structure = accel.build("bvh", obj.vertices, obj.faces)
    rounded, _ = render_lambert(obj, structure, camera, crease_angle=180.0,
                                shadows=False)
    assert np.abs(rounded - images[1]).max() > 0.05


SCENE = """
[materials.sand]
kind = "diffuse"
[[objects]]
mesh = "camel-19k"
material = "sand"
crease_angle = {angle}
"""


def test_scene_crease_angle_is_validated_and_used():
    with pytest.raises(SceneError, match=r"objects\[0\]\.crease_angle.*out of range"):
        parse_scene(SCENE.format(angle=181.0))
    with pytest.raises(SceneError, match=r"objects\[0\]\.crease_angle.*wrong type"):
        parse_scene(SCENE.format(angle='"sharp"'))
    scene = parse_scene(SCENE.format(angle=0))
    assert scene.objects[0].crease_angle == 0.0
    assert parse_scene(scene.to_toml()) == scene
    geo = assemble(scene)
    v = geo.vertices[geo.faces].astype(np.float64)
    face = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    face /= np.linalg.norm(face, axis=1, keepdims=True)
    assert geo.normals.shape == (len(geo.faces), 3, 3) and geo.normals.dtype == np.float32
    np.testing.assert_allclose(geo.normals, np.repeat(face[:, None], 3, axis=1), atol=1e-5)


def test_cli_crease_angle_is_checked_and_replaces_the_scenes(monkeypatch, capsys):
    from jrt import whitted
    from jrt.cli import main

    with pytest.raises(SystemExit) as exit_info:
        main(["render", "--crease-angle", "181"])
    assert exit_info.value.code == 2
    assert "--crease-angle" in capsys.readouterr().err

    seen = []

    def prepare(scene, **_):
        seen.append(scene)
        raise ValueError("stop before rendering")

    monkeypatch.setattr(whitted, "prepare", prepare)
    assert main(["render", "--scene", "glass-camel", "--crease-angle", "75"]) == 2
    (scene,) = seen
    assert [o.crease_angle for o in scene.objects] == [75.0]


# ------------------------------------------------------------------------ moving vertices


def _float64_corner_normals(vertices, faces, pairs):
    """The test's own float64 oracle of the sums over the smoothing pairs, a corner at a
    time: the angle of the partner's face at its corner times that face's unit normal."""
    p = np.asarray(vertices, np.float64)[faces]
    total = np.zeros((3 * len(faces), 3))
    for corner, partner in pairs.T:
        f, k = divmod(int(partner), 3)
        a, b, c = p[f, k], p[f, (k + 1) % 3], p[f, (k + 2) % 3]
        n = np.cross(p[f, 1] - p[f, 0], p[f, 2] - p[f, 0])
        e1, e2 = b - a, c - a
        angle = np.arctan2(np.linalg.norm(np.cross(e1, e2)), e1 @ e2)
        total[corner] += angle * n / np.linalg.norm(n)
    return (total / np.linalg.norm(total, axis=1, keepdims=True)).reshape(-1, 3, 3)


@pytest.mark.parametrize("crease", [30.0, 180.0])
def test_normals_of_moved_vertices_and_their_derivative(crease):
    """corner_normals_from_pairs (JAX, float32, crease decisions held fixed): equal to
    corner_normals at the mesh's own vertices, and its forward derivative along a random
    motion equal to a float64 central difference of the test's own oracle. A cylinder
    (its rim a crease at 30°, smoothed at 180°), its vertices jittered."""
    import jax

    from jrt.normals import corner_normals_from_pairs, smoothing_pairs

    mesh = trimesh.creation.cylinder(radius=1.0, height=1.5, sections=12)
    rng = np.random.default_rng(5)
    vertices = (mesh.vertices + rng.normal(0, 0.01, mesh.vertices.shape)).astype(np.float32)
    faces = np.asarray(mesh.faces, np.int64)
    pairs = smoothing_pairs(vertices, faces, crease)
    function = jax.jit(lambda v: corner_normals_from_pairs(v, faces, pairs))
    got = np.asarray(function(vertices))
    np.testing.assert_allclose(got, corner_normals(vertices, faces, crease), atol=2e-6)
    np.testing.assert_allclose(got, _float64_corner_normals(vertices, faces, pairs),
                               atol=2e-6)
    motion = rng.normal(0, 1, vertices.shape).astype(np.float32)
    _, tangent = jax.jvp(function, (vertices,), (motion,))
    h, step = 1e-6, motion.astype(np.float64)
    want = (_float64_corner_normals(vertices + h * step, faces, pairs)
            - _float64_corner_normals(vertices - h * step, faces, pairs)) / (2 * h)
    scale = np.abs(want).max()
    np.testing.assert_allclose(np.asarray(tangent), want, atol=1e-5 * scale)
    gradient = jax.grad(lambda v: function(v).sum())(vertices)
    assert np.isfinite(np.asarray(gradient)).all()
