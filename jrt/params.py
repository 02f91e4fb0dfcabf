"""A scene's continuous parameters as a pytree, and back to the arrays the renderer reads.

    setup = prepare("glass-camel")
    params = scene_parameters(setup)           # what may vary (and be differentiated)
    constants = scene_constants(setup)         # what may not (geometry, channel tables)
    arrays = scene_arrays(params, constants)   # jrt.whitted.SceneArrays, pure JAX
    origins, directions = camera_from_parameters(params["camera"], 320, 240)

The model is Mitsuba 3's ``mi.traverse(scene)``, nested instead of flat: every continuous
value the scene file sets, under the scene file's own keys, each a float32 ``jnp`` array::

    params["materials"][NAME]   diffuse:    {"albedo": [3]}        linear sRGB
                                mirror:     {"reflectance": [3]}   linear sRGB
                                dielectric: {"A": [], "B": []}     Cauchy n = A + B/λ², µm²
                                            (materials given by ``glass`` or ``cauchy``)
                                        or  {"index": []}          a constant index
    params["lamps"][i]          {"position": [3], "intensity": []}
    params["camera"]            {"eye": [3], "target": [3], "up": [3], "vfov": []}  degrees
    params["settings"]          {"ambient": []}
    params["geometry"]          {"vertices": [V, 3]}   only when asked (geometry=True)

The vertices (every object's, transformed as the scene places them, then the floor's) are a
parameter only on request: a render with them rebuilds the structure's boxes
(:func:`jrt.refit`, brute force and the BVH) and the corner normals
(:func:`jrt.normals.corner_normals_from_pairs`, the crease decisions of the scene as
written held fixed) on every call, which a render of fixed geometry should not pay.

Positions are the resolved ones (an ``"auto"`` lamp or camera holds where
:func:`jrt.scene.assemble` put it). Which entries a material has is part of the pytree's
structure, hence static under ``jax.jit``: a dielectric cannot switch from a constant index
to Cauchy's law in a traced function. Nor can a parameter change what the setup compiled:
the channels (spectral with dispersion, RGB without) were chosen by
:func:`jrt.whitted.prepare` from the scene as written, and the RGB renderer refracts with
``n = A`` alone, so a ``B`` moved off 0 in an RGB setup changes nothing in the image (nor
has it a gradient there).

:class:`SceneConstants` holds the rest, all arrays (no names, no flags): the mesh, the
channel tables, each lamp's spectrum at intensity 1 and the sky. :func:`scene_arrays`
rebuilds :class:`jrt.whitted.SceneArrays` from the two as :func:`jrt.whitted.prepare`
does in NumPy (equal up to a float32 rounding of the reflectance basis's product), and is
differentiable with respect to every
leaf of ``params``. Call :func:`check_parameters` on the host before ``jax.jit``: a
mismatched pytree is named there, path and shape, instead of failing inside the trace.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from jrt.camera import _pinhole, subpixel_offsets
from jrt.normals import corner_normals_from_pairs, smoothing_pairs
from jrt.spectral import SpectralTables, rgb_to_reflectance
from jrt.whitted import RenderSetup, SceneArrays, _lamp_channels

#: The nested dict described in the module's docstring (leaves: float arrays).
Params = dict[str, Any]


class SceneConstants(NamedTuple):
    """What :func:`scene_arrays` needs besides the parameters (a JAX pytree of arrays).

    ``material_rank`` ties the material rows (the scene's order of definition, which
    ``material`` indexes) to ``params["materials"]``: JAX flattens a dict in sorted key
    order, so the rows are gathered from the materials sorted by name, row ``i`` from
    entry ``material_rank[i]``. An array, not the names, so that it passes through jit.
    """

    vertices: Float[Array, "v 3"]
    faces: Int[Array, "f 3"]
    normals: Float[Array, "f 3 3"]
    material: Int[Array, " f"]  # material row of each face
    kind: Int[Array, " m"]  # jrt.whitted.KIND_CODES
    material_rank: Int[Array, " m"]  # row -> position among the names sorted
    lamp_spectra: Float[Array, "l c"]  # each lamp's channels at intensity 1 (Y = 1)
    sky: Float[Array, "2 c"]  # zenith and nadir radiance (zero on a black background)
    tables: SpectralTables  # wavelengths, illuminant and the reflectance basis among them
    # (corner, partner) pairs smoothed together (jrt.normals.smoothing_pairs), for vertices
    # that are parameters; [2, 0] otherwise.
    smoothing: Int[Array, "2 p"]


def _f32(value) -> Array:
    return jnp.asarray(value, jnp.float32)


def scene_parameters(
    setup: RenderSetup, width: int | None = None, height: int | None = None, *,
    geometry: bool = False,
) -> Params:
    """The scene's continuous parameters (see the module's docstring for the layout);
    ``geometry`` adds the vertices.

    The camera is ``setup.camera(width, height)``: at another image size an automatically
    framed camera is refitted, so its ``eye`` depends on the size asked for.
    """
    materials: dict[str, dict[str, Array]] = {}
    for mat in setup.geometry.materials:
        if mat.kind == "diffuse":
            materials[mat.name] = {"albedo": _f32(mat.albedo)}
        elif mat.kind == "mirror":
            materials[mat.name] = {"reflectance": _f32(mat.reflectance)}
        elif mat.cauchy is not None:  # a catalogue glass carries its (A, B) here too
            materials[mat.name] = {"A": _f32(mat.cauchy[0]), "B": _f32(mat.cauchy[1])}
        else:
            materials[mat.name] = {"index": _f32(mat.index)}
    camera = setup.camera(width, height)
    return {
        "materials": materials,
        "lamps": [{"position": _f32(lamp.position), "intensity": _f32(lamp.intensity)}
                  for lamp in setup.geometry.lamps],
        "camera": {"eye": _f32(camera.eye), "target": _f32(camera.target),
                   "up": _f32(camera.up), "vfov": _f32(camera.vfov)},
        "settings": {"ambient": _f32(setup.scene.settings.ambient)},
    } | ({"geometry": {"vertices": _f32(setup.geometry.vertices)}} if geometry else {})


def scene_smoothing_pairs(setup: RenderSetup) -> Int[np.ndarray, "2 p"]:
    """int32 [2, P]: :func:`jrt.normals.smoothing_pairs` of every object with its crease
    angle and of the floor with 0 (as :func:`jrt.scene.assemble` computed the normals), in
    the corners of the assembled mesh."""
    geometry = setup.geometry
    creases = [obj.crease_angle for obj in setup.scene.objects] + [0.0]  # the floor: flat
    pairs = [smoothing_pairs(geometry.vertices, geometry.faces[start:stop], crease)
             + 3 * start
             for (start, stop), crease in zip(geometry.object_faces, creases, strict=False)]
    return np.concatenate(pairs, axis=1).astype(np.int32)


def scene_constants(setup: RenderSetup, *, geometry: bool = False) -> SceneConstants:
    """The setup's non-parameters, as :func:`jrt.whitted.prepare` computed them; with
    ``geometry``, the smoothing pairs that vertices as parameters need."""
    geometry, tables = setup.geometry, setup.tables
    names = [mat.name for mat in geometry.materials]
    rank = {name: i for i, name in enumerate(sorted(names))}
    c = setup.channels
    # Y = 1 per lamp (jrt.whitted._lamp_channels), so intensity scales the luminance.
    spectra = np.asarray([_lamp_channels(lamp.spectrum, tables, setup.spectral)
                          for lamp in geometry.lamps], np.float64).reshape(-1, c)
    arrays = setup.arrays  # what prepare put on the device already: shared, not copied
    return SceneConstants(
        vertices=arrays.vertices, faces=arrays.faces, normals=arrays.normals,
        material=arrays.material, kind=arrays.kind,
        material_rank=jnp.asarray([rank[name] for name in names], jnp.int32),
        lamp_spectra=_f32(spectra), sky=arrays.sky, tables=tables,
        smoothing=jnp.asarray(scene_smoothing_pairs(setup) if geometry
                              else np.zeros((2, 0), np.int32)),
    )


def _material_rows(entry: dict, name) -> tuple[Array, Array, Array]:
    """(albedo rgb [3], reflectance rgb [3], cauchy [2]) of one material's parameters: the
    fields its kind does not use are zero, as in :func:`jrt.whitted.prepare`'s arrays."""
    zero3 = jnp.zeros(3, jnp.float32)
    keys = set(entry)
    if keys == {"albedo"}:
        return _f32(entry["albedo"]), zero3, jnp.zeros(2, jnp.float32)
    if keys == {"reflectance"}:
        return zero3, _f32(entry["reflectance"]), jnp.zeros(2, jnp.float32)
    if keys == {"A", "B"}:
        return zero3, zero3, jnp.stack([_f32(entry["A"]), _f32(entry["B"])])
    if keys == {"index"}:  # a constant index is Cauchy's law with B = 0
        return zero3, zero3, jnp.stack([_f32(entry["index"]), jnp.float32(0.0)])
    raise ValueError(
        f"params['materials'][{name!r}] has keys {sorted(keys)}; expected ['albedo'], "
        "['reflectance'], ['A', 'B'] or ['index']")


def scene_arrays(params: Params, constants: SceneConstants) -> SceneArrays:
    """:class:`jrt.whitted.SceneArrays` from the parameters, in JAX (jit-able and
    differentiable with respect to every leaf of ``params``; the camera is not read).

    Albedo and mirror rows become spectra by :func:`jrt.spectral.rgb_to_reflectance`
    (Mallett & Yuksel 2019; the RGB itself in RGB mode), dielectric rows are ``(A, B)`` or
    ``(index, 0)``, a lamp's radiance is its unit-intensity spectrum times its intensity.
    With ``params["geometry"]``, the vertices are those and the corner normals theirs
    (:func:`jrt.normals.corner_normals_from_pairs` of ``constants.smoothing``).
    """
    names = sorted(params["materials"])
    m = constants.kind.shape[0]
    if len(names) != m:
        raise ValueError(f"params['materials'] has {len(names)} entries, the scene {m}")
    rows = [_material_rows(params["materials"][name], name) for name in names]
    albedo_rgb, reflectance_rgb, cauchy = (
        jnp.stack(column)[constants.material_rank] for column in zip(*rows, strict=True))
    tables = constants.tables
    c = tables.wavelengths.shape[0]

    lamps = params["lamps"]
    count = constants.lamp_spectra.shape[0]
    if len(lamps) != count:
        raise ValueError(f"params['lamps'] has {len(lamps)} entries, the scene {count}")
    if lamps:
        positions = jnp.stack([_f32(lamp["position"]) for lamp in lamps])
        intensities = jnp.stack([_f32(lamp["intensity"]) for lamp in lamps])
    else:  # no lamp: empty arrays of the right shapes (jnp.stack of nothing fails)
        positions, intensities = jnp.zeros((0, 3), jnp.float32), jnp.zeros(0, jnp.float32)
    vertices, normals = constants.vertices, constants.normals
    if "geometry" in params:
        vertices = _f32(params["geometry"]["vertices"])
        if constants.smoothing.shape[1] == 0 and constants.faces.shape[0] > 0:
            raise ValueError("params['geometry'] needs the smoothing pairs: make the "
                             "constants with scene_constants(setup, geometry=True)")
        normals = corner_normals_from_pairs(vertices, constants.faces, constants.smoothing)
    return SceneArrays(
        vertices=vertices, faces=constants.faces, normals=normals,
        material=constants.material, kind=constants.kind,
        albedo=rgb_to_reflectance(albedo_rgb, tables).reshape(m, c),
        reflectance=rgb_to_reflectance(reflectance_rgb, tables).reshape(m, c),
        cauchy=cauchy, lamp_positions=positions.reshape(-1, 3),
        lamp_radiance=constants.lamp_spectra * intensities[:, None], sky=constants.sky,
        wavelengths=tables.wavelengths, illuminant=tables.illuminant,
        ambient=_f32(params["settings"]["ambient"]),
    )


def camera_from_parameters(
    camera_params: dict[str, Float[Array, "*dims"]], width: int, height: int, spp: int = 1
) -> tuple[Float[Array, "n 3"], Float[Array, "n 3"]]:
    """Origins and unit directions, float32 [height * width * spp, 3], of the pinhole camera
    ``params["camera"]``: :func:`jrt.camera.camera_rays`'s rays, bit for bit (the same
    float32 program, ``vfov`` in degrees turned to radians inside it; ``spp`` rays through
    each pixel's :func:`jrt.camera.subpixel_offsets`), and differentiable in every entry."""
    return _pinhole(_f32(camera_params["eye"]), _f32(camera_params["target"]),
                    _f32(camera_params["up"]), _f32(camera_params["vfov"]),
                    width=int(width), height=int(height),
                    offsets=None if spp == 1 else jnp.asarray(subpixel_offsets(spp)))


def _dtype(leaf) -> np.dtype:
    dtype = getattr(leaf, "dtype", None)  # a Python number has none: NumPy's choice
    return np.asarray(leaf).dtype if dtype is None else np.dtype(dtype)


def _describe(leaf) -> str:
    """``float32[3]``: a leaf's dtype and shape, as the error messages show them."""
    return f"{_dtype(leaf).name}{list(np.shape(leaf))}"


def check_parameters(params: Params, reference: Params) -> None:
    """Raise ValueError unless ``params`` has ``reference``'s structure and leaf shapes.

    ``reference`` is :func:`scene_parameters` of the setup. Every mismatch is listed, by
    path (``params['materials']['glass']['A']``), with what was found and what is
    expected. Leaves may be any floating dtype (they are cast to float32); integers are
    refused, since ``jax.grad`` does not differentiate them. Host side, before jit.
    """
    found = {jax.tree_util.keystr(path): leaf
             for path, leaf in jax.tree_util.tree_flatten_with_path(params)[0]}
    expected = {jax.tree_util.keystr(path): leaf
                for path, leaf in jax.tree_util.tree_flatten_with_path(reference)[0]}
    problems = []
    for key, want in expected.items():
        if key not in found:
            problems.append(f"params{key}: missing, expected {_describe(want)}")
            continue
        leaf = found[key]
        if np.shape(leaf) != np.shape(want) or not jnp.issubdtype(_dtype(leaf), jnp.floating):
            problems.append(f"params{key}: found {_describe(leaf)}, expected "
                            f"{_describe(want)} (a floating-point array of that shape)")
    problems += [f"params{key}: not a parameter of this scene ({_describe(leaf)})"
                 for key, leaf in found.items() if key not in expected]
    if not problems:
        ours = jax.tree_util.tree_structure(params)
        theirs = jax.tree_util.tree_structure(reference)
        if ours != theirs:  # same paths in other containers (a tuple for a list, say)
            problems.append(f"params: containers differ: found {ours}, expected {theirs}")
    if problems:
        raise ValueError("params do not match the scene's parameters "
                         "(jrt.params.scene_parameters):\n  " + "\n  ".join(problems))


__all__ = [
    "Params",
    "SceneConstants",
    "camera_from_parameters",
    "check_parameters",
    "scene_arrays",
    "scene_constants",
    "scene_parameters",
    "scene_smoothing_pairs",
]
