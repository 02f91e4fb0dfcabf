"""Scenes: built-ins, features, the TOML schema's round trip, error messages, assembly,
and the package's layering (no renderer imported by the scene layer)."""

from __future__ import annotations

import math
import shutil
import subprocess
import sys
import types
from importlib import resources

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jrt  # noqa: F401  (XLA flags before JAX starts)
from jrt.camera import Camera
from jrt.mesh import mesh_from_arrays
from jrt.scene import (
    BUILTIN_SCENES,
    Features,
    SceneError,
    assemble,
    builtin_toml,
    load_scene,
    parse_scene,
)
from jrt.scene.assembly import default_lamp

# Cauchy A, B (µm²): used only if jrt.optics (the catalogue's home) is absent.
_FALLBACK_GLASSES = {
    "fused silica": (1.44826, 0.003506), "BK7": (1.50459, 0.004202),
    "K5": (1.50910, 0.004615), "BaK4": (1.55328, 0.005360),
    "BaF10": (1.64806, 0.007588), "SF10": (1.68746, 0.014139),
}


@pytest.fixture(autouse=True)
def glasses(monkeypatch):
    """The glass catalogue: jrt.optics.GLASSES, or a stand-in module when it is absent."""
    try:
        from jrt.optics import GLASSES
    except ModuleNotFoundError:
        stub = types.ModuleType("jrt.optics")
        stub.GLASSES = _FALLBACK_GLASSES
        monkeypatch.setitem(sys.modules, "jrt.optics", stub)
        return _FALLBACK_GLASSES
    return GLASSES


def write_off(path, vertices, faces):
    lines = ["OFF", f"{len(vertices)} {len(faces)} 0"]
    lines += [" ".join(repr(float(x)) for x in v) for v in vertices]
    lines += ["3 " + " ".join(str(i) for i in f) for f in faces]
    path.write_text("\n".join(lines) + "\n")
    return path


TRIANGLE = [(0.0, 0.0, 0.0), (1.0, 0.0, 0.0), (0.0, 1.0, 0.0)]
TETRA = [(0.0, 0.0, 0.0), (1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)]
TETRA_FACES = [(0, 2, 1), (0, 1, 3), (0, 3, 2), (1, 2, 3)]


@pytest.fixture
def tri(tmp_path):
    return write_off(tmp_path / "tri.off", TRIANGLE, [(0, 1, 2)])


@pytest.fixture
def tetra(tmp_path):
    return write_off(tmp_path / "tetra.off", TETRA, TETRA_FACES)


def scene_file(tmp_path, text, name="scene.toml"):
    path = tmp_path / name
    path.write_text(text)
    return path


# --------------------------------------------------------------------------- built-ins

EXPECTED = {
    "camel": dict(diffuse=True, mirror=False, dielectric=False, dispersion=False, lamps=1,
                  shadows=True, max_depth=1),
    "glass-camel": dict(diffuse=True, mirror=False, dielectric=True, dispersion=True,
                        lamps=1, shadows=True, max_depth=8),
    "mirror-camel": dict(diffuse=True, mirror=True, dielectric=False, dispersion=False,
                         lamps=1, shadows=True, max_depth=5),
}


@pytest.mark.parametrize("name", list(BUILTIN_SCENES))
def test_builtin_features(name):
    scene = load_scene(name)
    assert scene.name == name and scene.source == f"built-in scene {name}"
    assert scene.features() == Features(**EXPECTED[name])
    assert scene.features(counters=True).counters
    assert scene.floor is not None and scene.camera.auto and len(scene.objects) == 1
    assert scene.objects[0].mesh == "camel"
    # The built-in's TOML is an example a user can copy: it parses to the same scene.
    assert parse_scene(builtin_toml(name), default_name=name) == scene


def test_builtin_glass_is_bk7_with_dispersion(glasses):
    glass = load_scene("glass-camel").material("glass")
    assert glass.kind == "dielectric" and glass.glass == "BK7" and glass.dispersion
    a, b = glasses["BK7"]
    assert glass.cauchy == (a, b)
    # Cauchy's law, λ in µm: n(589 nm) = A + B / 0.589².
    assert glass.index_at(589.0) == pytest.approx(a + b / 0.589**2)
    n = glass.index_at(np.array([400.0, 700.0]))
    assert n[0] > n[1] > 1.5  # normal dispersion: blue bends more


def test_builtin_scenes_are_the_shipped_files(tmp_path):
    """Each jrt/scene/builtin/NAME.toml is the built-in NAME, and a copy of it loaded as a
    user's file is the same scene (mesh names stay shipped names, not paths)."""
    folder = resources.files("jrt.scene").joinpath("builtin")
    files = sorted(f.name for f in folder.iterdir() if f.name.endswith(".toml"))
    assert files == [f"{name}.toml" for name in sorted(BUILTIN_SCENES)]
    assert list(BUILTIN_SCENES) == sorted(BUILTIN_SCENES)  # the order error messages list
    for name in BUILTIN_SCENES:
        text = folder.joinpath(f"{name}.toml").read_text(encoding="utf-8")
        assert builtin_toml(name) == text
        with resources.as_file(folder.joinpath(f"{name}.toml")) as path:
            copy = shutil.copy(path, tmp_path / f"{name}.toml")
        assert load_scene(copy) == load_scene(name)


def test_scene_layer_imports_no_renderer():
    """jrt.scene sits below the renderers: importing it loads none of them."""
    renderers = ("jrt.render", "jrt.whitted", "jrt.wavefront", "jrt.batch")
    code = ("import sys, jrt.scene; "
            f"print(' '.join(m for m in {renderers!r} if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True)
    assert out.stdout.strip() == ""


def test_default_lamp_closed_form():
    # Box centre at the origin, eye on +z at distance d = 10: forward = (0, 0, -10),
    # forward x up = (10, 0, 0), so the lamp is eye - 0.6 d x + 1.2 d y = (-6, 12, 10).
    mesh = mesh_from_arrays([(-1.0, -1.0, -1.0), (1.0, -1.0, -1.0), (-1.0, 1.0, -1.0),
                             (1.0, 1.0, 1.0)], TETRA_FACES)
    camera = Camera(eye=(0.0, 0.0, 10.0), target=(0.0, 0.0, 0.0), width=8, height=8)
    lamp = default_lamp(mesh, camera)
    assert lamp.dtype == np.float32
    np.testing.assert_allclose(lamp, [-6.0, 12.0, 10.0], rtol=1e-6)
    import jrt.render  # the Lambert renderer uses the same function

    assert jrt.render.default_lamp is default_lamp


def test_features_are_static_jit_arguments():
    features = load_scene("glass-camel").features()
    assert hash(features) == hash(load_scene("glass-camel").features())

    def f(x, features):
        return x * features.max_depth if features.dispersion else x

    g = jax.jit(f, static_argnames="features")
    assert float(g(jnp.float32(2.0), features=features)) == 16.0


def test_unknown_builtin_and_missing_file(tmp_path):
    for spec in ("camle", str(tmp_path / "nope.toml")):
        with pytest.raises(SceneError) as err:
            load_scene(spec)
        message = str(err.value)
        assert spec in message
        assert all(name in message for name in BUILTIN_SCENES)
    with pytest.raises(SceneError, match="glass-camel"):
        builtin_toml("glass")


def test_assemble_builtins():
    for name in BUILTIN_SCENES:
        scene = load_scene(name)
        geo = assemble(scene)
        assert geo.vertices.dtype == np.float32 and geo.faces.dtype == np.int32
        assert geo.material_of_face.dtype == np.int32
        assert geo.normals.shape == (len(geo.faces), 3, 3) and geo.normals.dtype == np.float32
        camel_faces, floor_faces = geo.object_faces
        assert camel_faces == (0, 69_092) and floor_faces == (69_092, 69_094)
        first, last = (geo.materials[i].name for i in geo.material_of_face[[0, -1]])
        assert (first, last) == (scene.objects[0].material, scene.floor.material)
        floor_y = geo.vertices[geo.faces[-2:]][..., 1]
        assert np.all(floor_y < geo.vertices[: 34_546, 1].min())
        assert isinstance(geo.camera, Camera) and geo.camera.width == 640
        assert geo.lamp_positions.shape == (1, 3) and np.all(np.isfinite(geo.lamp_positions))
        assert geo.features == scene.features()


# --------------------------------------------------------------------------- the schema

FULL = """\
name = "everything"

[camera]
eye = [4.0, 3.0, 5.0]
target = [0.0, 0.5, 0.0]
up = [0.0, 1.0, 0.0]
vfov = 40.0
width = 320
height = 200

[settings]
max_depth = 7
samples = 24
threshold = 0.01
kernel = "moller_trumbore"
accel = "kdtree"
background = "sky"
ambient = 0.2

[materials.paint]
kind = "diffuse"
albedo = [0.2, 0.4, 0.6]

[materials.chrome]
kind = "mirror"
reflectance = [0.95, 0.9, 0.85]

[materials.flint]
kind = "dielectric"
glass = "sf10"

[materials.water]
kind = "dielectric"
index = 1.333

[materials.custom]
kind = "dielectric"
cauchy = [1.5, 0.005]

[[lamps]]
position = [1.0, 10.0, 2.0]
intensity = 2.5
spectrum = "A"

[[lamps]]
position = "auto"

[[objects]]
mesh = "tri.off"
material = "paint"
scale = 2.0
rotate = [10.0, 20.0, 30.0]
translate = [1.0, 2.0, 3.0]

[[objects]]
mesh = "tetra.off"
material = "flint"

[floor]
material = "chrome"
extent = 2.0
gap = 0.01
"""


def test_full_file_round_trips(tmp_path, tri, tetra, glasses):
    path = scene_file(tmp_path, FULL)
    scene = load_scene(path)
    assert scene.source == str(path) and scene.name == "everything"
    assert scene.camera.eye == (4.0, 3.0, 5.0) and scene.camera.vfov == 40.0
    assert (scene.camera.width, scene.camera.height) == (320, 200)
    s = scene.settings
    assert (s.max_depth, s.samples, s.threshold, s.kernel, s.accel, s.background,
            s.ambient) == (7, 24, 0.01, "moller_trumbore", "kdtree", "sky", 0.2)
    assert [m.name for m in scene.materials] == ["paint", "chrome", "flint", "water", "custom"]
    assert scene.material("paint").albedo == (0.2, 0.4, 0.6)
    assert scene.material("chrome").reflectance == (0.95, 0.9, 0.85)
    flint = scene.material("flint")
    assert flint.glass == "SF10" and flint.cauchy == tuple(glasses["SF10"])  # any case
    assert scene.material("water").index == 1.333 and not scene.material("water").dispersion
    assert scene.material("custom").cauchy == (1.5, 0.005)
    assert scene.lamps[0].position == (1.0, 10.0, 2.0) and scene.lamps[0].intensity == 2.5
    assert scene.lamps[0].spectrum == "A"
    assert scene.lamps[1].position is None and scene.lamps[1].spectrum == "D65"
    first = scene.objects[0]
    assert first.mesh == str(tri.resolve()) and first.scale == 2.0
    assert first.rotate == (10.0, 20.0, 30.0) and first.translate == (1.0, 2.0, 3.0)
    assert scene.floor.extent == 2.0 and scene.floor.gap == 0.01
    assert scene.features() == Features(diffuse=True, mirror=True, dielectric=True,
                                        dispersion=True, lamps=2, shadows=True, max_depth=7)
    text = scene.to_toml()
    again = parse_scene(text)
    assert again == scene and again.to_toml() == text


def test_defaults_and_unused_materials(tmp_path, tri):
    scene = load_scene(scene_file(tmp_path, """
[materials.paint]
kind = "diffuse"
[materials.unused]
kind = "dielectric"
glass = "BK7"
[[objects]]
mesh = "tri.off"
material = "paint"
"""))
    assert scene.name == "scene" and scene.floor is None and scene.lamps == ()
    assert scene.material("paint").albedo == (0.8, 0.8, 0.8)
    assert scene.settings.max_depth == 5 and scene.settings.background == "black"
    # Only what is used counts; with no specular material, one level is enough.
    assert scene.features() == Features(diffuse=True, mirror=False, dielectric=False,
                                        dispersion=False, lamps=0, shadows=False, max_depth=1)


BASE = """\
name = "test"

[camera]
width = 32
height = 24

[settings]
max_depth = 4

[materials.glass]
kind = "dielectric"
index = 1.5

[materials.paint]
kind = "diffuse"
albedo = [0.5, 0.5, 0.5]

[[lamps]]
position = [0.0, 5.0, 0.0]
intensity = 1.0

[[objects]]
mesh = "tri.off"
material = "paint"
scale = 1.0

[floor]
material = "paint"
"""

OBJECTS = '[[objects]]\nmesh = "tri.off"\nmaterial = "paint"\nscale = 1.0\n'

# (old text in BASE, new text, field path in the message, allowed values in the message)
BAD = {
    "index-range": ("index = 1.5", "index = 0.5", "materials.glass.index", "(1, 5]"),
    "index-nan": ("index = 1.5", "index = nan", "materials.glass.index", "(1, 5]"),
    "glass-name": ("index = 1.5", 'glass = "BK8"', "materials.glass.glass", "BK7, K5"),
    "unknown-key": ("index = 1.5", "indx = 1.5", "materials.glass.indx",
                    "kind, index, glass, cauchy"),
    "two-indices": ("index = 1.5", "index = 1.5\ncauchy = [1.5, 0.004]", "materials.glass",
                    "cauchy = [A, B]"),
    "cauchy-shape": ("index = 1.5", "cauchy = [1.5]", "materials.glass.cauchy", "[A, B]"),
    "kind": ('kind = "dielectric"', 'kind = "metal"', "materials.glass.kind",
             "diffuse, mirror, dielectric"),
    "albedo-range": ("albedo = [0.5, 0.5, 0.5]", "albedo = [0.5, 1.5, 0.5]",
                     "materials.paint.albedo[1]", "[0, 1]"),
    "albedo-type": ("albedo = [0.5, 0.5, 0.5]", 'albedo = "red"', "materials.paint.albedo",
                    "[r, g, b]"),
    "depth-range": ("max_depth = 4", "max_depth = 17", "settings.max_depth", "[1, 16]"),
    "depth-type": ("max_depth = 4", "max_depth = 2.5", "settings.max_depth", "an integer"),
    "kernel": ("max_depth = 4", 'kernel = "fast"', "settings.kernel", "watertight"),
    "accel": ("max_depth = 4", 'accel = "bvhh"', "settings.accel", "kdtree"),
    "background": ("max_depth = 4", 'background = "white"', "settings.background",
                   "black, sky"),
    "undefined-material": ('material = "paint"\nscale', 'material = "gold"\nscale',
                           "objects[0].material", "glass, paint"),
    "floor-material": ('[floor]\nmaterial = "paint"', '[floor]\nmaterial = "stone"',
                       "floor.material", "glass, paint"),
    "no-objects": (OBJECTS, "", "objects", "[[objects]]"),
    "scale": ("scale = 1.0", "scale = -1.0", "objects[0].scale", "> 0"),
    "mesh-missing": ('mesh = "tri.off"', 'mesh = "nope.off"', "objects[0].mesh", "camel-19k"),
    "mesh-format": ('mesh = "tri.off"', 'mesh = "tri.xyz"', "objects[0].mesh", ".off, .obj"),
    "intensity": ("intensity = 1.0", "intensity = 0", "lamps[0].intensity", "> 0"),
    "position": ("position = [0.0, 5.0, 0.0]", "position = [0.0, 5.0]", "lamps[0].position",
                 '[x, y, z], or "auto"'),
    "spectrum": ("intensity = 1.0", 'spectrum = "D66"', "lamps[0].spectrum", "D65, D50"),
    "top-level": ("[[lamps]]", "[[lamp]]", "lamp", "lamps, objects"),
    "vfov": ("width = 32", "width = 32\nvfov = 180", "camera.vfov", "(0, 180)"),
    "width-bool": ("width = 32", "width = true", "camera.width", "an integer"),
    "eye-alone": ("width = 32", "width = 32\neye = [1.0, 2.0, 3.0]", "camera.target",
                  '"auto"'),
}


@pytest.mark.parametrize("case", list(BAD))
def test_error_names_file_field_and_allowed(tmp_path, tri, case):
    old, new, field, allowed = BAD[case]
    assert old in BASE
    path = scene_file(tmp_path, BASE.replace(old, new, 1), name="bad.toml")
    with pytest.raises(SceneError) as err:
        load_scene(path)
    message = str(err.value)
    assert message.startswith(str(path) + ": ")
    assert f" {field}" in message and allowed in message, message
    assert "allowed" in message or "built-in" in message


def test_base_is_valid_and_errors_suggest(tmp_path, tri):
    assert load_scene(scene_file(tmp_path, BASE)).name == "test"
    with pytest.raises(SceneError, match=r"did you mean 'index'"):
        parse_scene(BASE.replace("index = 1.5", "indx = 1.5"), base_dir=tmp_path)
    with pytest.raises(SceneError, match=r"built-in scene camel: settings\.ambient"):
        parse_scene(builtin_toml("camel").replace("ambient = 0.15", "ambient = 2"),
                    source="built-in scene camel")
    with pytest.raises(SceneError, match=r"bad\.toml: not valid TOML"):
        load_scene(scene_file(tmp_path, "[camera\n", name="bad.toml"))


# --------------------------------------------------------------------------- assembly


def _one_object(mesh, transform="", floor=False):
    text = f"""
[camera]
eye = [0.0, 0.0, 10.0]
target = [0.0, 0.0, 0.0]
width = 8
height = 8
[materials.paint]
kind = "diffuse"
[[objects]]
mesh = "{mesh}"
material = "paint"
{transform}
"""
    return text + ('\n[floor]\nmaterial = "paint"\n' if floor else "")


@pytest.mark.parametrize("transform, expected", [
    # scale 2, then 90° about z: (x, y, z) -> (-2y, 2x, 2z); then translate (1, 2, 3).
    ("scale = 2.0\nrotate = [0.0, 0.0, 90.0]\ntranslate = [1.0, 2.0, 3.0]",
     [(1, 2, 3), (1, 4, 3), (-1, 2, 3)]),
    # 90° about x: (x, y, z) -> (x, -z, y).
    ("rotate = [90.0, 0.0, 0.0]", [(0, 0, 0), (1, 0, 0), (0, 0, 1)]),
    # x first, then y: (0, 1, 0) -> (0, 0, 1) -> (1, 0, 0); (1, 0, 0) -> (1, 0, 0) -> (0, 0, -1).
    ("rotate = [90.0, 90.0, 0.0]", [(0, 0, 0), (0, 0, -1), (1, 0, 0)]),
    # 45° about y: (1, 0, 0) -> (cos 45°, 0, -sin 45°).
    ("rotate = [0.0, 45.0, 0.0]\nscale = 3.0",
     [(0, 0, 0), (3 * math.sqrt(0.5), 0, -3 * math.sqrt(0.5)), (0, 3, 0)]),
])
def test_transform_closed_form(tmp_path, tri, transform, expected):
    geo = assemble(parse_scene(_one_object("tri.off", transform), base_dir=tmp_path))
    np.testing.assert_allclose(geo.vertices, np.array(expected, np.float32), atol=1e-6)
    np.testing.assert_array_equal(geo.faces, [[0, 1, 2]])
    assert geo.object_faces == ((0, 1),)


def test_floor_under_lowest_point(tmp_path, tetra):
    scene = parse_scene(_one_object("tetra.off", "rotate = [30.0, 40.0, 50.0]\n"
                                    "translate = [5.0, -2.0, 1.0]", floor=True),
                        base_dir=tmp_path)
    geo = assemble(scene)
    body = geo.vertices[:4].astype(np.float64)
    floor = geo.vertices[geo.faces[-2:]].astype(np.float64)  # [2, 3, 3]
    lo, hi = body.min(axis=0), body.max(axis=0)
    diagonal = np.linalg.norm(hi - lo)
    np.testing.assert_allclose(floor[..., 1], lo[1] - 1e-3 * diagonal, rtol=1e-6)
    assert np.all(floor[..., 1] < lo[1])
    # It covers the objects' footprint (extent 3 around the centre).
    assert floor[..., 0].min() < lo[0] and floor[..., 0].max() > hi[0]
    assert floor[..., 2].min() < lo[2] and floor[..., 2].max() > hi[2]
    # Both triangles face up, and so do their corner normals.
    e = np.cross(floor[:, 1] - floor[:, 0], floor[:, 2] - floor[:, 0])
    assert np.all(e[:, 1] > 0) and np.allclose(e[:, [0, 2]], 0)
    np.testing.assert_allclose(geo.normals[-2:].reshape(-1, 3), [[0, 1, 0]] * 6, atol=1e-6)
    assert geo.object_faces == ((0, 4), (4, 6))


def test_material_of_face_and_lamps(tmp_path, tri, tetra):
    scene = load_scene(scene_file(tmp_path, """
[materials.chrome]
kind = "mirror"
[materials.paint]
kind = "diffuse"
[materials.glass]
kind = "dielectric"
index = 1.5
[[lamps]]
[[lamps]]
position = [0.0, 9.0, 0.0]
[[objects]]
mesh = "tetra.off"
material = "glass"
[[objects]]
mesh = "tri.off"
material = "chrome"
translate = [3.0, 0.0, 0.0]
[[objects]]
mesh = "tetra.off"
material = "glass"
scale = 0.5
[floor]
material = "paint"
"""))
    geo = assemble(scene)
    names = [m.name for m in geo.materials]
    assert names == ["chrome", "paint", "glass"]
    expected = ["glass"] * 4 + ["chrome"] + ["glass"] * 4 + ["paint"] * 2
    assert [names[i] for i in geo.material_of_face] == expected
    assert geo.object_faces == ((0, 4), (4, 5), (5, 9), (9, 11))
    # Faces of later objects point at their own vertices.
    np.testing.assert_array_equal(geo.faces[4], [4, 5, 6])
    np.testing.assert_allclose(geo.vertices[geo.faces[5:9]], 0.5 * geo.vertices[geo.faces[:4]])
    assert len(geo.vertices) == 4 + 3 + 4 + 4 and geo.mesh.faces.shape == (11, 3)
    # The "auto" lamp is resolved, the explicit one kept.
    assert geo.lamps[0].position is not None and geo.lamps[1].position == (0.0, 9.0, 0.0)
    assert geo.lamp_positions.shape == (2, 3) and geo.lamp_intensities.tolist() == [1, 1]


def test_auto_camera_frames_objects_not_floor(tmp_path, tetra):
    text = _one_object("tetra.off", floor=True).replace(
        "eye = [0.0, 0.0, 10.0]\ntarget = [0.0, 0.0, 0.0]\n", "")
    geo = assemble(parse_scene(text, base_dir=tmp_path))
    np.testing.assert_allclose(geo.camera.target, [0.5, 0.5, 0.5], atol=1e-6)
    explicit = assemble(parse_scene(_one_object("tetra.off"), base_dir=tmp_path))
    assert explicit.camera == Camera(eye=(0, 0, 10), target=(0, 0, 0), width=8, height=8,
                                     vfov=30.0)


def test_mesh_paths_relative_to_scene_file(tmp_path, monkeypatch):
    sub = tmp_path / "scenes"
    (sub / "meshes").mkdir(parents=True)
    write_off(sub / "meshes" / "tri.off", TRIANGLE, [(0, 1, 2)])
    path = scene_file(sub, _one_object("meshes/tri.off"))
    monkeypatch.chdir(tmp_path)
    assert load_scene(path).objects[0].mesh == str((sub / "meshes" / "tri.off").resolve())


def test_bad_mesh_file_names_the_field(tmp_path):
    write_off(tmp_path / "flat.off", [(0, 0, 0), (1, 0, 0), (2, 0, 0)], [(0, 1, 2)])
    scene = parse_scene(_one_object("flat.off"), source="flat.toml", base_dir=tmp_path)
    with pytest.raises(SceneError, match=r"flat\.toml: objects\[0\]\.mesh: .*degenerate"):
        assemble(scene)


def test_glass_without_catalogue_says_what_to_do(monkeypatch):
    monkeypatch.setitem(sys.modules, "jrt.optics", None)  # as if jrt.optics were missing
    with pytest.raises(SceneError, match=r"built-in scene glass-camel: materials\.glass\.glass"
                       r" = 'BK7': .*jrt\.optics\.GLASSES.*allowed: index = n or cauchy"):
        load_scene("glass-camel")
    assert not load_scene("camel").features().dielectric  # other scenes do not need it
