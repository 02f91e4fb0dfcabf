"""jrt.params: the scene's parameters as a pytree, and back to the renderer's arrays.

Every reference is the NumPy side of jrt.whitted: ``prepare``'s arrays for the scene as
loaded, ``_scene_arrays`` of an edited Scene for an edited parameter, ``camera_rays`` of
the resolved camera; gradients are checked against central differences.
"""

from __future__ import annotations

import copy
import dataclasses
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jrt.camera import camera_rays
from jrt.params import (
    camera_from_parameters,
    check_parameters,
    scene_arrays,
    scene_constants,
    scene_parameters,
)
from jrt.scene import BUILTIN_SCENES
from jrt.whitted import SceneArrays, _scene_arrays, prepare

#: camel: RGB, diffuse; glass-camel: spectral, Cauchy glass; mirror-camel: RGB, mirror.
SCENES = tuple(BUILTIN_SCENES)
FLOAT_FIELDS = ("albedo", "reflectance", "cauchy", "lamp_positions", "lamp_radiance", "ambient")


@pytest.fixture(scope="module")
def setups():
    """Each built-in scene prepared once (a BVH over the camel each, about 2 s)."""
    return {name: prepare(name) for name in SCENES}


def _assert_arrays_equal(found: SceneArrays, expected: SceneArrays) -> None:
    """Field by field: the same shape and dtype, values within 1e-6 of the field's scale
    (jit may fuse the reflectance basis's matmul differently: a float32 ulp or so)."""
    for field in SceneArrays._fields:
        a, b = np.asarray(getattr(found, field)), np.asarray(getattr(expected, field))
        assert a.shape == b.shape, (field, a.shape, b.shape)
        assert a.dtype == b.dtype, (field, a.dtype, b.dtype)
        scale = float(np.abs(b).max()) if b.size else 0.0
        np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-6 * scale, err_msg=field)


def _edited(setup, *, materials=None, lamps=None, ambient=None):
    """(setup, reference arrays) of the scene edited as a Scene: the reference is
    jrt.whitted's NumPy path (_scene_arrays) on the edited scene and geometry, over the
    setup's own channel tables (the structure is left as it was: only arrays change)."""
    scene, geometry = setup.scene, setup.geometry
    if materials is not None:
        scene = dataclasses.replace(scene, materials=materials)
        geometry = dataclasses.replace(geometry, materials=materials)
    if lamps is not None:
        geometry = dataclasses.replace(geometry, lamps=lamps)
    if ambient is not None:
        scene = dataclasses.replace(
            scene, settings=dataclasses.replace(scene.settings, ambient=ambient))
    edited = dataclasses.replace(setup, scene=scene, geometry=geometry)
    return edited, _scene_arrays(scene, geometry, setup.tables, setup.spectral)


def _replace_material(setup, name, **changes):
    return tuple(dataclasses.replace(m, **changes) if m.name == name else m
                 for m in setup.geometry.materials)


# ------------------------------------------------------------------------- reproduction


@pytest.mark.parametrize("name", SCENES)
def test_scene_arrays_reproduce_prepare(setups, name):
    setup = setups[name]
    params, constants = scene_parameters(setup), scene_constants(setup)
    _assert_arrays_equal(scene_arrays(params, constants), setup.arrays)
    _assert_arrays_equal(jax.jit(scene_arrays)(params, constants), setup.arrays)


@pytest.mark.parametrize("name", SCENES)
def test_layout_follows_the_scene_file(setups, name):
    setup = setups[name]
    params = scene_parameters(setup)
    assert list(params["materials"]) == [m.name for m in setup.scene.materials]
    for mat in setup.scene.materials:
        entry = params["materials"][mat.name]
        keys = {"diffuse": {"albedo"}, "mirror": {"reflectance"}}.get(mat.kind, {"A", "B"})
        assert set(entry) == keys
    lamp = params["lamps"][0]
    np.testing.assert_array_equal(lamp["position"], setup.geometry.lamps[0].position)
    assert all(leaf.dtype == jnp.float32 for leaf in jax.tree.leaves(params))


@pytest.mark.parametrize("name", SCENES)
def test_camera_rays_at_another_size(setups, name):
    setup = setups[name]
    width, height = (40, 50) if name == "glass-camel" else (40, 30)  # other aspects too
    params = scene_parameters(setup, width, height)
    origins, directions = camera_from_parameters(params["camera"], width, height)
    ref_origins, ref_directions = camera_rays(setup.camera(width, height))
    assert origins.shape == ref_origins.shape == (width * height, 3)
    # Bit for bit: a glass tree magnifies a one-ulp change of a camera ray.
    np.testing.assert_array_equal(origins, ref_origins)
    np.testing.assert_array_equal(directions, ref_directions)


# ------------------------------------------------------------------------- edited scenes


def _edit_case(setups, case):
    """(params, constants, reference arrays, the field that must change) for one edit."""
    if case in ("albedo", "glass A, B", "index", "ambient"):
        setup = setups["glass-camel"]
    elif case == "reflectance":
        setup = setups["mirror-camel"]
    else:
        setup = setups["camel"]
    params = copy.deepcopy(scene_parameters(setup))
    constants = scene_constants(setup)
    lamp = setup.geometry.lamps[0]
    if case == "albedo":  # a colour, not a grey: the spectral basis's three columns
        edited, ref = _edited(setup, materials=_replace_material(
            setup, "floor", albedo=(0.2, 0.5, 0.9)))
        params["materials"]["floor"]["albedo"] = jnp.float32([0.2, 0.5, 0.9])
        field = "albedo"
    elif case == "reflectance":
        edited, ref = _edited(setup, materials=_replace_material(
            setup, "mirror", reflectance=(0.3, 0.6, 0.1)))
        params["materials"]["mirror"]["reflectance"] = jnp.float32([0.3, 0.6, 0.1])
        field = "reflectance"
    elif case == "glass A, B":
        edited, ref = _edited(setup, materials=_replace_material(
            setup, "glass", cauchy=(1.62, 0.009)))
        params["materials"]["glass"].update(A=jnp.float32(1.62), B=jnp.float32(0.009))
        field = "cauchy"
    elif case == "index":  # another structure: the parameters come from the edited setup
        edited, ref = _edited(setup, materials=_replace_material(
            setup, "glass", glass=None, cauchy=None, index=1.45))
        params, constants = scene_parameters(edited), scene_constants(edited)
        assert set(params["materials"]["glass"]) == {"index"}
        field = "cauchy"
    elif case == "intensity":
        edited, ref = _edited(setup, lamps=(dataclasses.replace(lamp, intensity=2.5),))
        params["lamps"][0]["intensity"] = jnp.float32(2.5)
        field = "lamp_radiance"
    elif case == "position":
        edited, ref = _edited(setup, lamps=(dataclasses.replace(lamp, position=(-1, 4, 2)),))
        params["lamps"][0]["position"] = jnp.float32([-1, 4, 2])
        field = "lamp_positions"
    elif case == "ambient":
        edited, ref = _edited(setup, ambient=0.4)
        params["settings"]["ambient"] = jnp.float32(0.4)
        field = "ambient"
    elif case == "no lamp":
        edited, ref = _edited(setup, lamps=())
        params, constants = scene_parameters(edited), scene_constants(edited)
        assert params["lamps"] == []
        field = "lamp_radiance"
    return setup, params, constants, ref, field


EDITS = ("albedo", "reflectance", "glass A, B", "index", "intensity", "position", "ambient",
         "no lamp")


@pytest.mark.parametrize("case", EDITS)
def test_an_edited_parameter_changes_the_arrays_as_the_edited_scene(setups, case):
    setup, params, constants, ref, field = _edit_case(setups, case)
    before, after = np.asarray(getattr(setup.arrays, field)), np.asarray(getattr(ref, field))
    assert before.shape != after.shape or not np.array_equal(before, after)  # not vacuous
    _assert_arrays_equal(jax.jit(scene_arrays)(params, constants), ref)


def test_a_new_material_order_keeps_the_rows(setups):
    """Material rows follow the scene's order, whatever order the dict arrives in (JAX
    flattens dicts sorted by key: 'floor' sorts before 'glass', the reverse of the rows)."""
    setup = setups["glass-camel"]
    params = scene_parameters(setup)
    params["materials"] = dict(reversed(params["materials"].items()))
    _assert_arrays_equal(scene_arrays(params, scene_constants(setup)), setup.arrays)


# ------------------------------------------------------------------------- gradients


def _central_differences(f, params, step):
    """d f / d leaf for every component of every leaf of params, (f(x + h) - f(x - h)) / 2h."""
    leaves, treedef = jax.tree.flatten(params)
    grads = []
    for i, leaf in enumerate(leaves):
        leaf = np.asarray(leaf, np.float32)
        g = np.zeros(leaf.shape, np.float64)
        for index in np.ndindex(leaf.shape):
            values = []
            for sign in (1, -1):
                moved = leaf.copy()
                moved[index] += sign * step
                values.append(float(f(treedef.unflatten(
                    [*leaves[:i], jnp.asarray(moved), *leaves[i + 1:]]))))
            g[index] = (values[0] - values[1]) / (2 * step)
        grads.append(g)
    return treedef.unflatten(grads)


@pytest.mark.parametrize("name", ["glass-camel", "mirror-camel"])
def test_gradient_matches_central_differences(setups, name):
    """A quadratic of every float field: its central differences are exact up to float32
    rounding, so the tolerance is the rounding of the scalar divided by the step. Each
    entry is weighed by its own size squared, so that every term is about 1 (a spectral
    lamp's channels are about 100, Cauchy's B 0.004) and no gradient hides in the
    rounding of a larger one."""
    setup = setups[name]
    params, constants = scene_parameters(setup), scene_constants(setup)
    rng = np.random.default_rng(0)
    reference = scene_arrays(params, constants)
    weights = {}
    for f in FLOAT_FIELDS:
        size = np.maximum(np.abs(np.asarray(getattr(reference, f))), 1e-3)
        weights[f] = jnp.asarray(rng.uniform(0.5, 1.5, size.shape) / size**2, jnp.float32)

    @jax.jit
    def scalar(p):
        arrays = scene_arrays(p, constants)
        return sum(jnp.sum(weights[f] * getattr(arrays, f) ** 2) for f in FLOAT_FIELDS)

    grad = jax.grad(scalar)(params)
    step = 1e-2
    numeric = _central_differences(scalar, params, step)
    tolerance = 8 * np.finfo(np.float32).eps * abs(float(scalar(params))) / step
    flat_grad = jax.tree_util.tree_flatten_with_path(grad)[0]
    for (path, g), n in zip(flat_grad, jax.tree.leaves(numeric), strict=True):
        g = np.asarray(g)
        assert np.all(np.isfinite(g)), jax.tree_util.keystr(path)
        np.testing.assert_allclose(g, n, rtol=1e-3, atol=tolerance,
                                   err_msg=jax.tree_util.keystr(path))
    # The camera is no input of the scene arrays; everything else is.
    assert not np.any(np.asarray(grad["camera"]["eye"]))
    assert np.all(np.asarray(grad["lamps"][0]["position"]) != 0)
    assert float(grad["settings"]["ambient"]) != 0


def test_camera_gradient_matches_central_differences(setups):
    setup = setups["mirror-camel"]
    camera = scene_parameters(setup, 8, 6)["camera"]
    # Random weights, plus each ray's offset from the mean direction: that term grows with
    # the field of view (random weights alone nearly cancel the vfov's effect).
    directions = camera_from_parameters(camera, 8, 6)[1]
    weights = (jnp.asarray(np.random.default_rng(1).uniform(-1, 1, (48, 3)), jnp.float32)
               + 10 * (directions - directions.mean(axis=0)))

    @jax.jit
    def scalar(cam):
        return jnp.sum(weights * camera_from_parameters(cam, 8, 6)[1])

    grad = jax.grad(scalar)(camera)
    assert all(np.all(np.isfinite(np.asarray(g))) for g in jax.tree.leaves(grad))
    # Nonlinear (normalisation, tan): a step small against the scene, large against rounding.
    numeric = _central_differences(scalar, camera, 1e-2)
    for key in ("eye", "target", "up", "vfov"):
        np.testing.assert_allclose(grad[key], numeric[key], rtol=1e-2, atol=2e-3, err_msg=key)
    assert abs(float(grad["vfov"])) > 0.1


# ------------------------------------------------------------------------- checking


@pytest.fixture(scope="module")
def glass_params(setups):
    return scene_parameters(setups["glass-camel"])


def test_check_parameters_accepts_the_scene_and_other_floats(glass_params):
    check_parameters(glass_params, glass_params)
    loose = jax.tree.map(lambda x: np.asarray(x, np.float64), glass_params)
    loose["settings"]["ambient"] = 0.3  # a Python float
    check_parameters(loose, glass_params)


def _broken(params, edit):
    params = copy.deepcopy(params)
    edit(params)
    return params


@pytest.mark.parametrize("edit, message", [
    (lambda p: p["materials"]["glass"].pop("A"),
     "params['materials']['glass']['A']: missing, expected float32[]"),
    (lambda p: p["camera"].update(eye=np.zeros(4, np.float32)),
     "params['camera']['eye']: found float32[4], expected float32[3]"),
    (lambda p: p["lamps"][0].update(intensity=np.int32(2)),
     "params['lamps'][0]['intensity']: found int32[], expected float32[]"),
    (lambda p: p["materials"]["glass"].update(index=1.5),
     "params['materials']['glass']['index']: not a parameter of this scene"),
    (lambda p: p["lamps"].append(copy.deepcopy(p["lamps"][0])),
     "params['lamps'][1]['position']: not a parameter of this scene (float32[3])"),
    (lambda p: p.pop("settings"),
     "params['settings']['ambient']: missing"),
    (lambda p: p.update(lamps=tuple(p["lamps"])),
     "params: containers differ"),
])
def test_check_parameters_names_the_path(glass_params, edit, message):
    with pytest.raises(ValueError, match=re.escape(message)):
        check_parameters(_broken(glass_params, edit), glass_params)


def test_scene_arrays_refuses_a_material_of_no_kind(setups, glass_params):
    params = _broken(glass_params, lambda p: p["materials"]["glass"].update(index=1.5))
    with pytest.raises(ValueError, match=re.escape("params['materials']['glass']")):
        scene_arrays(params, scene_constants(setups["glass-camel"]))
