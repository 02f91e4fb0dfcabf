"""``jax.grad`` of a render (``jrt.wavefront.renderer(..., differentiable=True)``).

What the derivative is: the derivative of the image with the hit triangles held fixed
(``docs/gradients.md``). Where the image is linear in a parameter (albedo, lamp intensity,
ambient share) it must equal a finite difference of any step; where it is smooth (the glass's
Cauchy A and B through a flat slab, the lamp's position on a diffuse floor) a central
difference; where a change moves a silhouette (the camera's eye on the camel) it must not,
and that test says why.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import trimesh

from jrt import wavefront

SLAB = """\
name = "slab"

[camera]
eye = [0.6, 0.5, 3.0]
target = [0.0, 0.0, 0.0]
up = [0.0, 1.0, 0.0]
vfov = 12.0
width = 12
height = 12

[settings]
max_depth = 3
samples = 8
threshold = 0.0
accel = "bvh"
background = "sky"
ambient = 0.2

[materials.glass]
kind = "dielectric"
cauchy = [1.5046, 0.0042]

[materials.white]
kind = "diffuse"
albedo = [0.8, 0.7, 0.6]

[[lamps]]
position = [1.0, 4.0, -2.0]
spectrum = "D65"

[[objects]]                 # a glass slab 0.2 thick, faces at z = +-0.1
mesh = "slab.off"
material = "glass"

[floor]
material = "white"
"""


def _replace(params, path, value):
    out = jax.tree.map(lambda x: x, params)
    node = out
    for key in path[:-1]:
        node = node[key]
    node[path[-1]] = value
    return out


def _leaf(params, path):
    for key in path:
        params = params[key]
    return params


def _weighted_loss(render, seed=0):
    shape = np.asarray(render(render.params)).shape
    weights = jnp.asarray(np.random.default_rng(seed).uniform(0.5, 1.5, shape), jnp.float32)
    return lambda p: jnp.sum(weights * render(p))


def _central(loss, params, path, step, component=None):
    """float64 central difference of the float32 loss along one leaf (or component)."""
    x = np.asarray(_leaf(params, path), np.float32)

    def at(delta):
        y = x.copy()
        if component is None:
            y = np.float32(y + delta)
        else:
            y[component] += delta
        return float(loss(_replace(params, path, jnp.asarray(y))))

    return (at(step) - at(-step)) / (2 * step)


@pytest.fixture(scope="module")
def glass_camel():
    render, params = wavefront.renderer("glass-camel", width=24, height=18, max_depth=3,
                                        differentiable=True)
    loss = _weighted_loss(render)
    return render, params, loss, jax.grad(loss)(params)


def test_every_leaf_has_a_finite_gradient_and_the_image_is_the_renderers(glass_camel):
    render, params, _, grad = glass_camel
    assert jax.tree.structure(grad) == jax.tree.structure(params)
    for path, value in jax.tree_util.tree_flatten_with_path(grad)[0]:
        assert np.isfinite(np.asarray(value)).all(), jax.tree_util.keystr(path)
    assert np.abs(np.asarray(grad["materials"]["glass"]["A"])) > 0
    plain, _ = wavefront.renderer("glass-camel", width=24, height=18, max_depth=3)
    want = np.asarray(plain(params))
    np.testing.assert_allclose(np.asarray(render(params)), want, rtol=1e-5,
                               atol=1e-6 * np.abs(want).max())


@pytest.mark.parametrize("path,step,component,tolerance", [
    (("materials", "floor", "albedo"), 0.1, 0, 1e-4),   # linear: any step
    (("lamps", 0, "intensity"), 1.0, None, 1e-4),       # linear
    (("settings", "ambient"), 0.01, None, 1e-3),        # linear
    (("lamps", 0, "position"), 0.01, 1, 1e-2),          # smooth shading of the floor
], ids=["albedo", "intensity", "ambient", "lamp-position"])
def test_linear_and_smooth_parameters_match_finite_differences(glass_camel, path, step,
                                                               component, tolerance):
    _, params, loss, grad = glass_camel
    got = np.asarray(_leaf(grad, path))
    got = float(got if component is None else got[component])
    want = _central(loss, params, path, step, component)
    assert abs(got - want) <= tolerance * abs(want), (got, want)


@pytest.fixture(scope="module")
def slab(tmp_path_factory):
    folder = tmp_path_factory.mktemp("slab")
    box = trimesh.creation.box(extents=(2.0, 2.0, 0.2))
    box.unmerge_vertices()  # flat faces
    box.export(folder / "slab.off")
    (folder / "slab.toml").write_text(SLAB)
    render, params = wavefront.renderer(str(folder / "slab.toml"), differentiable=True)
    loss = _weighted_loss(render, seed=1)
    return params, loss, jax.grad(loss)(params)


@pytest.mark.parametrize("name,step", [("A", 2e-3), ("B", 2e-3)])
def test_cauchy_coefficients_match_central_differences_through_a_slab(slab, name, step):
    """Through a flat slab every ray keeps its triangles as the index moves: the loss is
    smooth in A and B, and the gradient is its derivative."""
    params, loss, grad = slab
    got = float(grad["materials"]["glass"][name])
    want = _central(loss, params, ("materials", "glass", name), step)
    assert abs(got) > 0 and abs(got - want) <= 2e-2 * abs(want), (got, want)


def test_a_moving_silhouette_is_not_in_the_derivative(glass_camel):
    """Moving the eye moves the camel's silhouette across pixels: those pixels jump from
    sky to camel (or back), a step that a derivative holding the hit triangles fixed does
    not contain. The central difference sees the jumps, whatever its step; the gradient
    does not, and the two disagree."""
    _, params, loss, grad = glass_camel
    got = float(grad["camera"]["eye"][0])
    wants = [_central(loss, params, ("camera", "eye"), step, 0) for step in (1e-2, 1e-3)]
    assert np.isfinite(got)
    assert all(abs(got - want) > 0.1 * abs(want) for want in wants), (got, wants)
