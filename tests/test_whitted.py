"""The Whitted renderer (jrt.whitted) against closed forms, conservation laws and itself.

Small images and few wavelength samples: the machine is small. The synthetic scenes are
TOML files written into tmp_path with box meshes from trimesh; the camel scenes use the
19k-triangle camel. Every check computes its expectation independently of the renderer
(Fresnel's normal-incidence R by hand, the sky from its documented formula).
"""

from __future__ import annotations

import collections
import dataclasses

import jax
import numpy as np
import pytest
import trimesh
from skimage import io

from jrt import host_tree, optics, wavefront, whitted
from jrt.cli import main
from jrt.scene import BUILTIN_SCENES, builtin_toml, parse_scene
from jrt.sky import SKY_BOTTOM, SKY_TOP
from jrt.spectral import rgb_to_reflectance, spectrum_to_xyz

CHUNK = 4096  # rays per compiled call in these tests: small images


def sky_rgb(d):
    """The documented "sky": (1 - w) SKY_TOP + w SKY_BOTTOM, w = (1 - d_y) / 2."""
    w = np.clip((1 - np.asarray(d, np.float64)[..., 1]) / 2, 0, 1)[..., None]
    return np.asarray(SKY_TOP) * (1 - w) + np.asarray(SKY_BOTTOM) * w


def camel_scene(name="glass-camel", **replace):
    """A built-in scene on the 19k camel, with text replacements in its TOML."""
    text = builtin_toml(name).replace('mesh = "camel"', 'mesh = "camel-19k"')
    for old, new in replace.items():
        assert old in text, old
        text = text.replace(old, new)
    return parse_scene(text, source=f"test {name}")


def primary_kinds(setup, width, height):
    """Kind code hit by each pixel's camera ray (-1: background), [H, W]."""
    rays = host_tree.camera_level(setup, setup.camera(width, height))
    level = host_tree.shade_level(setup, rays, chunk=CHUNK)
    copies = setup.channels if setup.spectral else 1
    return level.kinds[::copies].reshape(height, width)


# --------------------------------------------------------------------------- fixtures


@pytest.fixture(scope="module")
def glass19k():
    """The glass camel (BK7, dispersion) on the 19k camel, 4 wavelength samples."""
    return whitted.prepare(camel_scene(), samples=4)


def test_the_host_tree_is_reached_from_jrt_whitted():
    from jrt.whitted import host_radiance

    assert host_radiance is host_tree.host_radiance
    for name in host_tree.__all__:
        assert getattr(whitted, name) is getattr(host_tree, name)
    with pytest.raises(AttributeError, match="no_such_name"):
        whitted.no_such_name  # noqa: B018


# --------------------------------------------------------------------------- what is compiled


def test_opaque_scene_compiles_no_optics_and_matches_the_general_path(monkeypatch):
    scene = camel_scene("camel")
    setup = whitted.prepare(scene)
    assert not setup.features.dielectric and not setup.features.mirror
    program = host_tree.chunk_program(setup)
    for name in ("refract", "fresnel", "cauchy", "reflect"):
        assert f"name={name}" not in program
    general = dataclasses.replace(setup.features, dielectric=True, mirror=True)
    assert "name=refract" in host_tree.chunk_program(
        dataclasses.replace(setup, features=general))

    def boom(*args, **kwargs):
        raise AssertionError("an opaque scene traced optics code")

    with monkeypatch.context() as m:
        for name in ("refract", "fresnel", "fresnel_sp", "cauchy", "reflect",
                     "interface_indices"):
            m.setattr(optics, name, boom)
        m.setattr(wavefront, "_COMPILED", {})  # the renderer's programs and renderers
        m.setattr(wavefront, "_RENDERERS", collections.OrderedDict())
        jax.clear_caches()  # trace afresh, with the raising optics
        image, stats = whitted.render_scene(setup, width=48, height=36)
    assert stats.channels == 3 and stats.mode == "tree"
    assert stats.rays_per_level == (48 * 36,) and stats.shadow_rays > 0

    forced, forced_stats = whitted.render_scene(setup, width=48, height=36,
                                                features=general)
    assert forced_stats.channels == 3
    np.testing.assert_allclose(forced, image, atol=1e-6)
    kinds = primary_kinds(setup, 48, 36)
    assert (kinds == 0).mean() > 0.3  # the camel and the floor are in the picture


def test_dispersion_decides_the_channels(glass19k):
    assert glass19k.features.dispersion and glass19k.spectral
    _, stats = whitted.render_scene(glass19k, width=16, height=12, max_depth=2)
    # One camera ray per pixel carries the 4 samples; the host tree traces one per sample.
    assert stats.channels == 4 and stats.rays_per_level[0] == 16 * 12
    _, host = host_tree.host_radiance(glass19k, width=16, height=12, max_depth=2)
    assert host.channels == 4 and host.rays_per_level[0] == 16 * 12 * 4
    assert stats.rays_per_level[1] == host.rays_per_level[1]  # they part at the glass


# --------------------------------------------------------------------------- closed forms

SYNTHETIC = """\
name = "synthetic"

[camera]
eye = {eye}
target = {target}
up = {up}
vfov = {vfov}
width = {size}
height = {size}

[settings]
max_depth = {depth}
samples = 8
threshold = 0.0
accel = "brute"
background = "sky"
ambient = 0.2

[materials.glass]
kind = "dielectric"
glass = "BK7"

[materials.mirror]
kind = "mirror"
reflectance = [0.9, 0.5, 0.2]

[materials.black]
kind = "diffuse"
albedo = [0.0, 0.0, 0.0]

[materials.white]
kind = "diffuse"
albedo = [1.0, 1.0, 1.0]

[[lamps]]
position = [0.0, -10.0, -10.0]
spectrum = "D65"

[[objects]]                 # a BK7 slab 0.2 thick, faces at z = +-0.1
mesh = "slab.off"
material = "glass"

[[objects]]                 # a mirror plate at x = 10, its mirror face at z = -10.05
mesh = "plate.off"
material = "mirror"
translate = [10.0, 0.0, -10.0]

[[objects]]                 # a black wall behind the slab's camera: takes its reflections
mesh = "wall.off"
material = "black"
translate = [0.0, 0.0, 8.0]

[floor]                     # y = -20.x, white, under the lamp at (0, -10, -10)
material = "white"
"""


@pytest.fixture(scope="module")
def synthetic(tmp_path_factory):
    """Write the meshes; return a function (camera, depth) -> RenderSetup."""
    folder = tmp_path_factory.mktemp("synthetic")
    for name, extents in (("slab", (2.0, 2.0, 0.2)), ("plate", (2.0, 2.0, 0.1)),
                          ("wall", (40.0, 40.0, 1.0))):
        box = trimesh.creation.box(extents=extents)
        # Flat faces: no shared vertices, so each vertex normal is its face's normal (a
        # box's shared corners would average three faces into a rounded shading normal).
        box.unmerge_vertices()
        box.export(folder / f"{name}.off")

    def setup(eye, target, up=(0.0, 1.0, 0.0), vfov=10.0, size=9, depth=3):
        path = folder / "scene.toml"
        path.write_text(SYNTHETIC.format(eye=list(eye), target=list(target), up=list(up),
                                         vfov=vfov, size=size, depth=depth))
        return whitted.prepare(path)

    return setup


#: The two routes to a tree's image: the renderer (every level on the device, spectral camera
#: rays as bundles of every wavelength sample) and the host-stepped reference; the analytic
#: values below hold for both. Value: (radiance function, camera rays per pixel and
#: wavelength sample in rays_per_level[0]: a bundle counts once).
TREES = {
    "device": (lambda setup, **kw: whitted.render_radiance(setup, **kw), "bundles"),
    "host": (lambda setup, **kw: host_tree.host_radiance(setup, chunk=CHUNK, **kw), "rays"),
}


@pytest.mark.parametrize("tree", TREES)
def test_slab_at_normal_incidence_transmits_t_squared(synthetic, tree):
    """Centre pixel through the BK7 slab, along -z: the transmitted light is T² of the sky
    behind it (depth 3: in, out, seen), T = 1 - ((n - 1)/(n + 1))² per wavelength; the
    reflections go back to the black wall. Deep, the internal reflections add up to
    T² / (1 - R²) = (1 - R) / (1 + R)."""
    setup = synthetic(eye=(0, 0, 5), target=(0, 0, 0), depth=3)
    assert setup.spectral and setup.channels == 8
    n = np.asarray(optics.GLASSES["BK7"][0] + optics.GLASSES["BK7"][1]
                   / (np.asarray(setup.tables.wavelengths, np.float64) * 1e-3) ** 2)
    r = ((n - 1) / (n + 1)) ** 2
    t = 1 - r
    direction = np.array([0.0, 0.0, -1.0])
    sky = (np.asarray(rgb_to_reflectance(sky_rgb(direction), setup.tables), np.float64)
           * np.asarray(setup.tables.illuminant, np.float64))
    radiance_of, camera = TREES[tree]
    radiance, stats = radiance_of(setup)
    centre = radiance[4, 4]
    np.testing.assert_allclose(centre, t**2 * sky, rtol=1e-4)
    assert stats.rays_per_level[0] == 81 * (1 if camera == "bundles" else 8)
    assert stats.rays_per_level[1] == 81 * 8 * 2  # each sample: reflected, refracted
    assert stats.truncated_weight > 0

    deep, _ = radiance_of(setup, max_depth=16)
    np.testing.assert_allclose(deep[4, 4], (1 - r) / (1 + r) * sky, rtol=1e-4)
    assert np.all(deep[4, 4] > centre * (1 + 0.5 * r**2))  # the second pass is there


@pytest.mark.parametrize("tree", TREES)
def test_schlick_is_an_option_of_the_scene(synthetic, tree):
    """settings.fresnel = "schlick": Schlick's R equals R0 = ((n-1)/(n+1))² at normal
    incidence, so the slab's centre pixel is the same T² of the sky; at the slab's edges
    (oblique incidence through the 10° view) the two models differ, by less than Schlick's
    largest error for glass (0.036 in R)."""
    exact = synthetic(eye=(0, 0, 5), target=(0, 0, 0), depth=3)
    settings = dataclasses.replace(exact.scene.settings, fresnel="schlick")
    schlick = whitted.prepare(dataclasses.replace(exact.scene, settings=settings))
    radiance_of, _ = TREES[tree]
    want, _ = radiance_of(exact)
    got, _ = radiance_of(schlick)
    np.testing.assert_allclose(got[4, 4], want[4, 4], rtol=1e-5)
    scale = np.abs(want).max()
    assert np.abs(got - want).max() > 0  # a different model was compiled
    assert np.abs(got - want).max() < 0.036 * scale


def test_mirror_reflects_the_sky_times_its_reflectance(synthetic):
    """A mirror plate facing the camera (-z): every reflected ray keeps its d_y, so sees the
    sky of the camera ray's own direction, times the mirror's reflectance spectrum."""
    size = 15
    setup = synthetic(eye=(10, 0, -15), target=(10, 0, -10), vfov=30.0, size=size, depth=2)
    rays = host_tree.camera_level(setup, setup.camera())
    level = host_tree.shade_level(setup, rays, chunk=CHUNK)
    mirror = (level.kinds == whitted.KIND_CODES["mirror"]).reshape(size * size, -1)[:, 0]
    directions = rays.directions[:: setup.channels]
    upper = mirror & (directions[:, 1] >= 0)  # reflections that never reach the floor
    assert mirror.sum() > 0.3 * size * size and upper.sum() > 10
    rho = np.asarray(rgb_to_reflectance(np.array([0.9, 0.5, 0.2]), setup.tables), np.float64)
    sky = (np.asarray(rgb_to_reflectance(sky_rgb(directions), setup.tables), np.float64)
           * np.asarray(setup.tables.illuminant, np.float64))
    radiance, _ = host_tree.host_radiance(setup, chunk=CHUNK)
    radiance = radiance.reshape(size * size, -1)
    np.testing.assert_allclose(radiance[upper], rho * sky[upper], rtol=1e-4, atol=1e-7)
    # Around the plate the camera sees the black wall: nothing.
    wall = level.kinds.reshape(size * size, -1)[:, 0] == whitted.KIND_CODES["diffuse"]
    assert wall.sum() > 0 and np.all(radiance[wall] == 0)


@pytest.mark.parametrize("tree", TREES)
def test_white_floor_under_a_d65_lamp_is_white(synthetic, tree):
    """Looking straight down at the floor right under the lamp: n·l = 1, a white albedo, a
    D65 lamp of intensity 1: Y = 1 and R = G = B (white) after encoding, in spectral mode."""
    setup = synthetic(eye=(0, -10, -10), target=(0, -25, -10), up=(0, 0, -1), depth=2)
    assert setup.spectral
    radiance_of, camera = TREES[tree]
    radiance, stats = radiance_of(setup)
    # every pixel sees the lit floor (a bundle casts one shadow ray for its samples)
    assert stats.shadow_rays == 81 * (1 if camera == "bundles" else 8)
    xyz = np.asarray(spectrum_to_xyz(radiance[4, 4].astype(np.float32), setup.tables))
    assert abs(xyz[1] - 1) < 1e-4
    image = whitted.to_srgb(radiance, setup)
    centre = image[4, 4]
    assert np.all(centre > 0.98) and np.ptp(centre) < 0.01, centre


# --------------------------------------------------------------------------- the glass camel


def test_dielectric_conserves_weight(glass19k):
    """Threshold 0: the children of a dielectric hit weigh R + T = 1 times their parent;
    under total internal reflection one child carries the parent's whole weight."""
    rays = host_tree.camera_level(glass19k, glass19k.camera(24, 18))
    glass = whitted.KIND_CODES["dielectric"]
    seen_tir = 0
    for _ in range(3):
        level = host_tree.shade_level(glass19k, rays, chunk=CHUNK)
        at_glass = level.kinds == glass
        kids = level.children
        total = np.zeros(len(rays))
        np.add.at(total, level.parents, kids.weights[:, 0])
        count = np.bincount(level.parents, minlength=len(rays))
        np.testing.assert_allclose(total[at_glass], rays.weights[at_glass, 0], rtol=1e-5)
        tir = level.tir
        assert np.all(at_glass[tir])
        assert np.all(count[tir] == 1) and np.all(count[at_glass & ~tir] == 2)
        np.testing.assert_array_equal(total[tir], rays.weights[tir, 0])
        assert np.all(count[~at_glass] == 0)  # diffuse floor, sky: no children
        seen_tir += int(tir.sum())
        rays = kids
    assert seen_tir > 0


def test_depth_converges(glass19k):
    images, stats = host_tree.host_radiance(glass19k, width=32, height=24, max_depth=8,
                                            chunk=CHUNK, by_depth=True)
    encoded = whitted.to_srgb(images, glass19k)
    diffs = [float(np.abs(encoded[d + 1] - encoded[d]).mean()) for d in range(7)]
    print("\nmean |I(d+1) - I(d)|, d = 1..7:", " ".join(f"{x:.4f}" for x in diffs))
    print("rays per camera ray by depth:", " ".join(
        f"{x:.3f}" for x in stats.rays_per_pixel_by_depth))
    assert diffs[-1] < diffs[0] / 4
    assert all(r <= 2**d for d, r in enumerate(stats.rays_per_pixel_by_depth))
    # A render at depth 3 is levels 0..2 of the deeper one.
    three, _ = host_tree.host_radiance(glass19k, width=32, height=24, max_depth=3,
                                       chunk=CHUNK)
    np.testing.assert_allclose(three, images[2], rtol=1e-6, atol=1e-9)


def test_dispersion_adds_colour(glass19k):
    """Against the same camel at B = 0, rendered through the same spectral program (the
    glass camel's features forced, 4 samples): with one index for every wavelength the
    samples share their paths, so only dispersion can part them. Pixels whose camera ray
    does not start on the glass are the same in both; on the glass, the colour changes."""
    A = optics.GLASSES["BK7"][0]
    flat = whitted.prepare(camel_scene(**{'glass = "BK7"': f"cauchy = [{A}, 0.0]"}),
                           features=glass19k.features, samples=4)
    assert flat.spectral and flat.channels == glass19k.channels
    size = dict(width=32, height=24, max_depth=4)
    dispersed, _ = whitted.render_scene(glass19k, **size)
    plain, _ = whitted.render_scene(flat, **size)
    on_camel = primary_kinds(flat, 32, 24) == whitted.KIND_CODES["dielectric"]
    assert on_camel.sum() > 50
    np.testing.assert_allclose(dispersed[~on_camel], plain[~on_camel], rtol=0, atol=1e-6)

    def chroma(image):
        rgb = image[on_camel].astype(np.float64)
        return np.stack([rgb[:, 0] - rgb[:, 1], rgb[:, 1] - rgb[:, 2]], axis=-1)

    change = np.abs(chroma(dispersed) - chroma(plain)).sum(axis=-1)
    print(f"\nchroma change on the glass: median {np.median(change):.4f}, "
          f"max {change.max():.4f}, {np.mean(change > 1e-3):.0%} of its pixels above 1e-3")
    assert change.max() > 0.02 and np.mean(change > 1e-3) > 0.1


@pytest.mark.parametrize("scale", [1.0, 1e3])
def test_secondary_rays_leave_their_surface(glass19k, scale):
    """No level-1 ray (reflected or refracted off the camel or the floor) hits the triangle
    it leaves, at the camel's size and scaled by 1000 (the offset has no scene scale)."""
    setup = glass19k if scale == 1.0 else whitted.prepare(
        camel_scene(**{'material = "glass"': f'material = "glass"\nscale = {scale}'}),
        samples=4)
    size = setup.geometry.mesh.diagonal
    rays = host_tree.camera_level(setup, setup.camera(32, 24))
    level1 = host_tree.shade_level(setup, rays, chunk=CHUNK).children
    level0 = host_tree.shade_level(setup, rays, chunk=CHUNK)
    level1 = level0.children
    assert len(level1) > 500
    level2 = host_tree.shade_level(setup, level1, chunk=CHUNK)
    own = level2.triangles == level1.sources
    near = own & (level2.t < 1e-3 * size)
    print(f"\nscale {scale:g}: {len(level1)} level-1 rays, {own.sum()} hit their own "
          f"triangle, {near.sum()} within 1e-3 of the scene size")
    assert own.sum() == 0 and near.sum() == 0
    # The refracted rays (second child of a pair: reflected first, then refracted) went
    # inside the closed camel: they meet the camel again, never the floor or the sky.
    first = np.zeros(len(level1), bool)
    first[np.unique(level0.parents, return_index=True)[1]] = True
    refracted = ~first
    assert refracted.sum() > 250
    assert np.all(level2.kinds[refracted] == whitted.KIND_CODES["dielectric"])


def test_sampled_mode_converges_to_the_tree(glass19k):
    size = dict(width=24, height=18, max_depth=4, chunk=CHUNK, threshold=0.0)
    tree, tree_stats = host_tree.host_radiance(glass19k, **size)
    errors = []
    for spp in (2, 8, 32):
        sampled, stats = host_tree.host_radiance(glass19k, mode="sampled", spp=spp,
                                                 key=jax.random.PRNGKey(spp), **size)
        # A path never branches: each level has at most the rays of the level before.
        levels = stats.rays_per_level
        assert all(b <= a for a, b in zip(levels, levels[1:], strict=False))
        errors.append(float(np.abs(sampled - tree).mean()))
    print("\nmean |sampled - tree|, spp 2, 8, 32:", " ".join(f"{e:.5f}" for e in errors))
    assert errors[0] > errors[1] > errors[2] and errors[2] < errors[0] / 2.5
    assert tree_stats.rays_per_level[1] > 0


def test_every_structure_gives_the_same_image(glass19k):
    base = glass19k.scene
    images = {}
    for name in ("bvh", "grid", "kdtree"):
        scene = dataclasses.replace(base, settings=dataclasses.replace(base.settings,
                                                                       accel=name))
        setup = glass19k if name == "bvh" else whitted.prepare(scene, samples=4)
        assert setup.structure.kind == name
        # The host tree: a smaller program to compile per structure, the same traversals.
        images[name], _ = host_tree.host_radiance(setup, width=24, height=18, max_depth=3)
    np.testing.assert_array_equal(images["grid"], images["bvh"])
    np.testing.assert_array_equal(images["kdtree"], images["bvh"])


# --------------------------------------------------------------------------- the CLI


def test_cli_renders_a_scene(tmp_path, capsys):
    out = tmp_path / "glass.png"
    code = main(["render", "--scene", "glass-camel", "-o", str(out), "--width", "32",
                 "--height", "24", "--depth", "2", "--samples", "4"])
    printed = capsys.readouterr().out
    assert code == 0, printed
    image = io.imread(out)
    assert image.shape == (24, 32, 3) and image.dtype == np.uint8
    assert "32x24" in printed and "rays per level" in printed and "Mrays/s" in printed
    assert "(4 channels)" in printed and "depth 2" in printed


def test_cli_bad_scene_lists_the_builtins(tmp_path, capsys):
    out = tmp_path / "x.png"
    code = main(["render", "--scene", "no-such-scene", "-o", str(out)])
    err = capsys.readouterr().err
    assert code == 2
    assert err.startswith("jrt render: error: ") and "no-such-scene" in err
    assert all(name in err for name in BUILTIN_SCENES)
    assert not out.exists()
