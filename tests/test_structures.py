"""The conformance suite: every registered structure through the same checks.

The contract of a structure (``accel.StructureKind``): with the same kernel it returns
brute force's answers exactly, the same triangle, the same ``t``, ``u``, ``v`` bit for bit,
and ``occluded`` the same booleans. Checked here for every kind the registry lists
(``accel.names()``), with nothing written per structure:

- the camel (69k triangles), 20k camera and 20k incoherent rays, every kernel: closest hits
  against brute force's;
- ``occluded`` on 20k incoherent rays whose ``tmax`` is a random multiple of the closest
  hit, 2 % cut exactly at it (strict: not occluded by that triangle);
- the engine's counters: a hit costs a step, a test and a leaf; no triangle tested twice;
  any-hit does at most the work of closest-hit;
- the closed camel from inside (watertight kernel): rays through vertices and edge
  midpoints exactly, and from interior points at vertices, never slip through a crack;
- an empty mesh and degenerate faces: misses, and degenerate faces never hit;
- errors: a bad ray is named by its index, an unknown build parameter lists the
  parameters, a non-finite vertex is refused, arrays labelled as another kind are refused.

What only one structure has (its layout decoded against its documentation, its build
rules, random soups padded to its fixed shapes, its own edge cases) stays in its own file
(``test_bvh_*.py``, ``test_kdtree.py``, ``test_bsp.py``, ``test_octree.py``,
``test_grid.py``). ``tests/test_adding_a_structure.py`` runs this module again for a
structure registered from outside accel.

The checks take their structure from the ``kind`` fixture (engine kinds) and
``any_kind`` (brute force too): a module that imports them and overrides those fixtures
runs the same suite on other kinds.
"""

from __future__ import annotations

import igl
import numpy as np
import pytest
from test_bvh_build import stacked
from test_bvh_traversal import KERNELS, assert_same_hits

import accel
import jrt
from accel.structure import Structure
from benchmarks.stability import strictly_inside
from jrt.trace import as_numpy, bucket_size

#: Rays of the occlusion test that brute force traces itself (near tmax, and others).
BRUTE_OCCLUDED = 2_000
#: Rays per family of the closed-mesh test.
PER_FAMILY = 8_000


@pytest.fixture(params=accel.names(engine=True))
def kind(request):
    """Every structure the traversal engine steps (the registry's, brute force aside)."""
    return request.param


@pytest.fixture(params=accel.names())
def any_kind(request):
    """Every registered structure, brute force first."""
    return request.param


@pytest.fixture(params=KERNELS)
def kernel(request):
    return request.param


@pytest.fixture(params=["camera", "incoherent"])
def ray_set(request):
    return request.param


# ---------------------------------------------------------------------------------------------
# The camel
# ---------------------------------------------------------------------------------------------


def test_camel_closest_hit_matches_brute(kind, camel_structures, camel_rays, brute_hits,
                                         kernel, ray_set):
    structure = camel_structures(kind)
    origins, directions = camel_rays[ray_set]
    want = brute_hits(kernel, ray_set)
    got = as_numpy(jrt.closest_hit(structure, origins, directions, kernel=kernel))
    assert (want["triangle"] >= 0).mean() > 0.1
    assert_same_hits(got, want, origins, directions, f"{kind} {kernel}/{ray_set}")


def test_camel_occluded_matches_brute(kind, camel, camel_structures, camel_brute, camel_rays,
                                      brute_hits, kernel):
    """20k rays, tmax a random multiple (0 to 2) of each ray's closest hit (or of the scene
    size for a miss), 2 % of them cut exactly at their closest hit.

    Brute force's answer: away from tmax, whether its closest hit comes before tmax; the
    rays at or near tmax (and as many others, up to BRUTE_OCCLUDED) through brute force's
    own ``occluded``."""
    structure = camel_structures(kind)
    origins, directions = camel_rays["incoherent"]
    t = brute_hits(kernel, "incoherent")["t"]
    rng = np.random.default_rng(4)
    scale = np.where(np.isfinite(t), t, 3 * camel.diagonal)
    tmax = (rng.uniform(0, 2, len(t)) * scale).astype(np.float32)
    exact = rng.random(len(t)) < 0.02
    tmax[exact] = t[exact]
    with np.errstate(invalid="ignore"):  # inf - inf for misses
        near = np.isfinite(t) & (np.abs(t - tmax) <= 1e-5 * t)
    others = np.flatnonzero(~near)
    traced = np.union1d(np.flatnonzero(near), rng.choice(
        others, BRUTE_OCCLUDED - near.sum(), replace=False))
    got = np.asarray(jrt.occluded(structure, origins, directions, tmax=tmax, kernel=kernel))
    want = np.where(near, False, t < tmax)
    want[traced] = np.asarray(jrt.occluded(camel_brute, origins[traced], directions[traced],
                                           tmax=tmax[traced], kernel=kernel))
    assert near.sum() >= 100 and 0.1 < want.mean() < 0.9
    bad = np.flatnonzero(got != want)
    assert bad.size == 0, (f"{kind}: {bad.size} rays differ, e.g. {bad[:5]}: got "
                           f"{got[bad[:5]]} tmax {tmax[bad[:5]]} closest t {t[bad[:5]]}")


def test_camel_counters(kind, camel_structures, camel_rays, brute_hits):
    """The engine's counters (steps, triangle tests, leaves per ray) on hits and misses."""
    structure = camel_structures(kind)
    origins, directions = camel_rays["incoherent"]
    hits, count = jrt.closest_hit(structure, origins, directions, counters=True)
    got = as_numpy(hits)
    assert_same_hits(got, brute_hits("watertight", "incoherent"), origins, directions,
                     f"{kind} with counters")
    hit = got["triangle"] >= 0
    steps, tests, leaves = (np.asarray(a) for a in count)
    for a in (steps, tests, leaves):
        assert a.dtype == np.int32 and a.shape == hit.shape and (a >= 0).all()
    assert (steps[hit] >= 1).all(), "a hit without a step"
    assert (tests[hit] >= 1).all() and (leaves[hit] >= 1).all(), "a hit without a test"
    assert (leaves <= tests).all(), "a leaf visited without a triangle test"
    # A triangle is tested at most once per leaf that references it.
    assert (tests <= structure.stats.get("references", structure.num_triangles)).all()
    assert tests.mean() < 0.01 * structure.num_triangles, "no better than brute force"
    mask, occ = jrt.occluded(structure, origins, directions, counters=True)
    np.testing.assert_array_equal(np.asarray(mask), hit)
    # Any-hit follows the closest-hit traversal up to its first hit, then stops.
    for a, b in zip(occ, count, strict=True):
        assert (np.asarray(a) <= np.asarray(b)).all()


# ---------------------------------------------------------------------------------------------
# The closed camel from inside: no cracks (watertight kernel)
# ---------------------------------------------------------------------------------------------


def axis_aligned_through(mesh, targets, normals, step):
    """Rays along ±x/±y/±z (closest to the outward normal) ending at ``targets``, from
    interior points: only the axis coordinate of the origin differs from the target's."""
    axis = np.argmax(np.abs(normals), axis=1)
    sign = np.sign(normals[np.arange(len(normals)), axis])
    directions = np.zeros_like(targets)
    directions[np.arange(len(targets)), axis] = sign
    origins = targets - step * directions
    keep = strictly_inside(mesh.vertices, mesh.faces, origins)
    return origins[keep].astype(np.float32), directions[keep].astype(np.float32)


@pytest.fixture(scope="module")
def crack_rays(camel):
    """Three families of rays from inside the closed camel: axis-aligned through vertices
    exactly, the same through edge midpoints, and from interior points at vertices."""
    rng = np.random.default_rng(7)
    v, f = camel.vertices, camel.faces
    step = 2e-3 * camel.diagonal
    vn = igl.per_vertex_normals(v.astype(np.float64), f.astype(np.int64))
    pick = rng.choice(len(v), PER_FAMILY, replace=False)
    families = {"vertices": axis_aligned_through(camel, v[pick], vn[pick], step)}
    edges = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    pick = rng.choice(len(edges), PER_FAMILY, replace=False)
    midpoints = ((v[edges[pick, 0]] + v[edges[pick, 1]]) / 2).astype(np.float32)
    edge_normals = vn[edges[pick, 0]] + vn[edges[pick, 1]]
    families["edge midpoints"] = axis_aligned_through(camel, midpoints, edge_normals, step)
    lo, hi = camel.bounds
    candidates = lo + rng.uniform(size=(20 * PER_FAMILY, 3)) * (hi - lo)
    interior = candidates[strictly_inside(v, f, candidates)][:PER_FAMILY].astype(np.float32)
    targets = v[rng.choice(len(v), len(interior))]
    directions = targets - interior
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    families["interior to vertices"] = (interior, directions.astype(np.float32))
    for name, (o, _) in families.items():
        assert len(o) > PER_FAMILY // 4, f"too few interior origins for {name}"
    return families


def test_no_cracks_from_inside(any_kind, camel_structures, crack_rays, camel_rays):
    """A ray from inside a closed mesh that hits nothing went through a crack. The other
    two kernels leak through shared edges by design; the stability suite measures by how
    much (its case 1)."""
    structure = camel_structures(any_kind)
    # One call on the three families together, within the size bucket of the camel's
    # 20k-ray sets, whose watertight program the tests above compiled already.
    origins = np.concatenate([o for o, _ in crack_rays.values()])
    directions = np.concatenate([d for _, d in crack_rays.values()])
    assert len(origins) <= bucket_size(len(camel_rays["camera"][0]))
    missed = np.asarray(jrt.closest_hit(structure, origins, directions,
                                        kernel="watertight").triangle) < 0
    ends = np.cumsum([len(o) for o, _ in crack_rays.values()])
    cracks = {name: (int(part.sum()), len(part))
              for name, part in zip(crack_rays, np.split(missed, ends[:-1]), strict=True)}
    assert all(count == 0 for count, _ in cracks.values()), (any_kind, cracks)


# ---------------------------------------------------------------------------------------------
# Empty and degenerate meshes
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("vertex_count", [0, 3])
def test_an_empty_mesh_builds_and_misses(any_kind, vertex_count):
    structure = accel.build(any_kind, np.zeros((vertex_count, 3), np.float32),
                            np.zeros((0, 3), np.int32))
    assert structure.kind == any_kind and structure.num_triangles == 0
    origins = np.float32([[0, 0, -1], [0.5, 0.5, 0.5], [0, 0, 0]])
    directions = np.float32([[0, 0, 1], [1, 0, 0], [0, -1, 0]])
    hits = as_numpy(jrt.closest_hit(structure, origins, directions))
    np.testing.assert_array_equal(hits["triangle"], -1)
    np.testing.assert_array_equal(hits["t"], np.inf)
    np.testing.assert_array_equal(np.asarray(jrt.occluded(structure, origins, directions)),
                                  False)


def test_degenerate_faces_are_never_hit(any_kind):
    """Three stacked triangles among four degenerate faces (a repeated corner, collinear
    corners): the degenerate ones are left out, the others keep their face indices."""
    vertices, faces = stacked(3)
    extra = np.float32([[0.5, 0.5, 0.5], [1.5, 1.5, 0.5], [2.5, 2.5, 0.5]])
    vertices = np.concatenate([vertices, extra])
    faces = np.concatenate([np.int32([[9, 10, 11], [0, 0, 1]]), faces,
                            np.int32([[9, 9, 9], [3, 4, 3]])])
    structure = accel.build(any_kind, vertices, faces)
    assert structure.num_triangles == 3
    np.testing.assert_array_equal(np.sort(structure["triangle_ids"]), [2, 3, 4])
    origins = np.float32([[0.5, 0.5, 0], [0.5, 0.5, 9], [9, 9, 0]])
    directions = np.float32([[0, 0, 1], [0, 0, -1], [0, 0, 1]])
    hits = as_numpy(jrt.closest_hit(structure, origins, directions))
    np.testing.assert_array_equal(hits["triangle"], [2, 4, -1])
    np.testing.assert_array_equal(hits["t"], np.float32([1, 6, np.inf]))
    np.testing.assert_array_equal(np.asarray(jrt.occluded(structure, origins, directions)),
                                  [True, True, False])


# ---------------------------------------------------------------------------------------------
# Errors
# ---------------------------------------------------------------------------------------------

#: One triangle in z = 1 covering (0.5, 0.5).
TINY_MESH = (np.float32([[-1, -1, 1], [3, -1, 1], [-1, 3, 1]]), np.int32([[0, 1, 2]]))


def test_bad_rays_are_named(any_kind):
    """The engine checks the rays in its own pass (engine.STATUS_BAD_RAYS) and the public
    functions name the first bad one, as brute force's separate check does: a NaN or
    infinite origin or direction, a zero direction, a NaN tmax; one bad ray among good
    ones, on either device's share (odd and even indices)."""
    structure = accel.build(any_kind, *TINY_MESH)
    good_o, good_d = np.float32([[0.5, 0.5, 0]] * 5), np.float32([[0, 0, 1]] * 5)
    cases = [("origins", 3, "o", [np.nan, 0.5, 0]), ("origins", 2, "o", [0.5, np.inf, 0]),
             ("directions", 1, "d", [0, -np.inf, 1]), ("directions", 4, "d", [0, 0, 0]),
             ("tmax", 0, "t", np.nan)]
    for name, index, field, value in cases:
        o, d, t = good_o.copy(), good_d.copy(), np.full(5, np.inf, np.float32)
        {"o": o, "d": d, "t": t}[field][index] = value
        for query in (jrt.closest_hit, jrt.occluded):
            with pytest.raises(ValueError, match=f"{name} of ray {index} is"):
                query(structure, o, d, tmax=t)
    # The good rays alone answer.
    np.testing.assert_array_equal(np.asarray(jrt.closest_hit(structure, good_o, good_d).t), 1)


def test_an_unknown_parameter_lists_the_parameters(any_kind):
    with pytest.raises(TypeError, match=rf"unknown parameter 'no_such_option' for "
                       rf"accel.build\('{any_kind}', ...\)"):
        accel.build(any_kind, *TINY_MESH, no_such_option=1)


@pytest.mark.parametrize("value", [np.nan, np.inf, -np.inf])
def test_a_non_finite_vertex_is_refused(any_kind, value):
    vertices, faces = stacked(2)
    vertices[4, 1] = value
    with pytest.raises(ValueError, match="vertex 4 is .* non-finite vertices"):
        accel.build(any_kind, vertices, faces)


def test_arrays_of_another_kind_are_refused(any_kind):
    """Another kind's arrays labelled as this kind: a ValueError names the arrays and
    layout this kind needs (a traversal reading them as its own could loop or answer
    misses)."""
    mine = accel.kind(any_kind)
    other = next(k.name for k in accel.kinds()
                 if (k.arrays, k.layout) != (mine.arrays, mine.layout))
    built = accel.build(other, *TINY_MESH)
    wrong = Structure(kind=any_kind, arrays=dict(built.arrays), layout=built.layout)
    o, d = np.float32([[0.5, 0.5, -1], [0.2, 0.3, -1]]), np.float32([[0, 0, 1], [0, 0, 1]])
    for query in (jrt.closest_hit, jrt.occluded):
        with pytest.raises(ValueError, match=f"a '{any_kind}' structure needs the arrays"):
            query(wrong, o, d)
