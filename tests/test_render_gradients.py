"""``jax.grad`` of a render (``jrt.wavefront.renderer(..., differentiable=True)``).

What the derivative is: the derivative of the image with the hit triangles held fixed
(``docs/gradients.md``). The scene: a glass slab (flat faces, Cauchy dispersion) over a
white floor under a lamp, seen from above at an angle, 16x16 pixels, 8 wavelength samples,
depth 3, its vertices parameters too (``geometry=True``: the BVH refit on every render). On
its centre pixels (seen through the slab's large faces: no ray there changes triangles or
crosses a shadow edge when a parameter moves a little) the image is smooth in every
parameter, and the gradient must equal a central difference, to the differences' own float32
precision: exactly (any step) where the image is linear (albedo, lamp intensity, ambient
share). On the whole image the slab's edges (a silhouette) and its shadow's edge move with
the camera and the lamp: the image jumps there, the derivative does not contain the jumps,
and the two disagree; that test says why.
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
vfov = 40.0
width = 16
height = 16

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
def slab(tmp_path_factory):
    """(render, params, losses, gradients): the weighted sum of the whole image and of its
    centre 6x6 pixels, and their gradients."""
    folder = tmp_path_factory.mktemp("slab")
    box = trimesh.creation.box(extents=(2.0, 2.0, 0.2))
    box.unmerge_vertices()  # flat faces
    box.export(folder / "slab.off")
    (folder / "slab.toml").write_text(SLAB)
    render, params = wavefront.renderer(str(folder / "slab.toml"), differentiable=True,
                                        geometry=True)
    image = np.asarray(render(params))  # sizes the levels
    weights = np.random.default_rng(1).uniform(0.5, 1.5, image.shape).astype(np.float32)
    centre = np.zeros(image.shape, np.float32)
    centre[5:11, 5:11] = 1
    # One compiled gradient for both losses: the weights are an argument, not a constant.
    gradient = jax.jit(jax.grad(lambda p, w: jnp.sum(w * render(p))))
    losses, grads = {}, {}
    for name, mask in (("whole", 1.0), ("centre", centre)):
        w = jnp.asarray(weights * mask)
        losses[name] = lambda p, w=w: jnp.sum(w * render(p))
        grads[name] = gradient(params, w)
    return render, params, losses, grads


def test_every_leaf_has_a_finite_gradient_and_the_image_is_the_renderers(slab, tmp_path):
    render, params, _, grads = slab
    for grad in grads.values():
        assert jax.tree.structure(grad) == jax.tree.structure(params)
        for path, value in jax.tree_util.tree_flatten_with_path(grad)[0]:
            assert np.isfinite(np.asarray(value)).all(), jax.tree_util.keystr(path)
    plain, _ = wavefront.renderer(render.setup)
    plain.capacities = render.capacities  # sized already: one compile, not two
    want = np.asarray(plain({k: v for k, v in params.items() if k != "geometry"}))
    np.testing.assert_allclose(np.asarray(render(params)), want, rtol=1e-5,
                               atol=1e-6 * np.abs(want).max())


@pytest.mark.parametrize("path,step,component,tolerance", [
    (("materials", "glass", "A"), 2e-3, None, 2e-3),
    (("materials", "glass", "B"), 2e-3, None, 2e-3),
    (("materials", "white", "albedo"), 0.1, 0, 1e-4),   # linear: any step
    (("lamps", 0, "intensity"), 1.0, None, 1e-4),       # linear
    (("settings", "ambient"), 0.01, None, 1e-3),        # linear
    (("lamps", 0, "position"), 0.01, 1, 1e-2),
    (("camera", "eye"), 0.01, 0, 1e-2),
], ids=["A", "B", "albedo", "intensity", "ambient", "lamp-position", "eye"])
def test_every_parameter_matches_central_differences_where_the_image_is_smooth(
        slab, path, step, component, tolerance):
    _, params, losses, grads = slab
    got = np.asarray(_leaf(grads["centre"], path))
    got = float(got if component is None else got[component])
    want = _central(losses["centre"], params, path, step, component)
    assert got != 0 and abs(got - want) <= tolerance * abs(want), (got, want)


@pytest.mark.parametrize("path", [("camera", "eye"), ("lamps", 0, "position")],
                         ids=["silhouette", "shadow-edge"])
def test_moving_edges_are_not_in_the_derivative(slab, path):
    """Moving the eye moves the slab's edges across pixels, moving the lamp moves its
    shadow's edge on the floor: those pixels jump (sky to glass, lit to shadowed), a step
    that a derivative holding the hit triangles fixed does not contain. A central
    difference sees the jumps; the gradient does not, and the two disagree (by 19 % and
    99 % for the eye's steps 1e-2 and 1e-3, 53 % for the lamp's 1e-2: the smaller the
    step, the larger a jump's share of the difference quotient)."""
    _, params, losses, grads = slab
    component = 0 if path[0] == "camera" else 1
    got = float(np.asarray(_leaf(grads["whole"], path))[component])
    want = _central(losses["whole"], params, path, 1e-2, component)
    assert np.isfinite(got) and abs(got - want) > 0.1 * abs(want), (got, want)
    # The same parameter on the centre pixels, where nothing jumps: they agree (above).


#: The slab's vertices (the box's 36, unmerged) come first in the scene's, the floor's 4 last.
SLAB_VERTICES = 36


@pytest.mark.parametrize("move", ["thickness", "tilt"])
def test_moving_vertices_matches_central_differences(slab, move):
    """The derivative along a motion of the slab's vertices: its front face (z = +0.1)
    pushed toward the camera, or tilted about the y axis (each front vertex moved along
    z by its x). Seen through the front face, the centre pixels refract through a moved
    surface (the path in the glass and the floor point behind it move): smooth, so the
    gradient must equal a central difference of the refit render (summed in float64: the
    float32 loss's own rounding is a few per cent of the difference quotient here)."""
    render, params, _, grads = slab
    vertices = np.asarray(params["geometry"]["vertices"])
    assert vertices.shape == (SLAB_VERTICES + 4, 3)
    front = np.flatnonzero(vertices[:SLAB_VERTICES, 2] > 0)
    assert len(front) == 18  # the corners at z = +0.1 of the front face and the sides
    direction = np.zeros_like(vertices)
    direction[front, 2] = 1.0 if move == "thickness" else vertices[front, 0]
    got = float(np.sum(np.asarray(grads["centre"]["geometry"]["vertices"]) * direction))
    image = np.asarray(render(params))
    weights = np.random.default_rng(1).uniform(0.5, 1.5, image.shape)  # the fixture's
    weights[:5], weights[11:], weights[:, :5], weights[:, 11:] = 0, 0, 0, 0  # centre 6x6
    step = 4e-3

    def at(h):
        moved = _replace(params, ("geometry", "vertices"),
                         jnp.asarray(vertices + np.float32(h) * direction))
        return float(np.sum(weights * np.asarray(render(moved), np.float64)))

    want = (at(step) - at(-step)) / (2 * step)
    assert got != 0 and abs(got - want) <= 2e-3 * abs(want), (got, want)


def test_vertices_as_parameters_need_a_structure_that_refits(tmp_path):
    folder = tmp_path
    trimesh.creation.box(extents=(2.0, 2.0, 0.2)).export(folder / "slab.off")
    (folder / "slab.toml").write_text(SLAB.replace('accel = "bvh"', 'accel = "kdtree"'))
    with pytest.raises(ValueError, match=r"a kdtree cannot be refit; set the scene's "
                       r"settings.accel to one of brute, bvh"):
        wavefront.renderer(str(folder / "slab.toml"), geometry=True)
