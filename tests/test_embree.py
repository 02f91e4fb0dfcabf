"""Every kernel's closest hits against Intel Embree's on the camel (brute force and BVH).

A ray disagrees when one side hits and the other misses, or when both hit but |Δt|
exceeds 1e-4 of the scene size (float32 on grazing rays: Embree's own t is off by up to
about 1e-4 against float64 on this mesh). At most 1e-4 of the rays may disagree.

Brute force runs on the conformance suite's 20k rays of each set (its 69k tests a ray cost
two minutes on 2 cores at 100k; ``conftest.brute_hits`` traces them once per test session),
the BVH on 50k. The other structures are not traced here: the
conformance suite (``tests/test_structures.py``) checks every structure's hits equal to
brute force's bit for bit, so Embree's agreement with brute force carries over to them;
``python -m benchmarks.structures_correctness`` does the same on the full 1M sets.
"""

from __future__ import annotations

import numpy as np
import pytest

import jrt
from jrt.raysets import camera_set, incoherent_set
from jrt.trace import as_numpy

RAYS = 50_000
BRUTE_RAYS = 20_000
MAX_SHARE = 1e-4


@pytest.fixture(params=["brute", "bvh"])
def structure(request, camel_structures):
    """Brute force, the reference of every structure, and the BVH."""
    return camel_structures(request.param)


@pytest.fixture(scope="module")
def ray_sets(camel):
    return {
        "camera": camera_set(camel.vertices, RAYS),
        "incoherent": incoherent_set(camel.vertices, RAYS, seed=1),
    }


@pytest.fixture(scope="module")
def embree_hits(ray_sets, embree_camel):
    return {name: embree_camel.closest_hit(o, d) for name, (o, d) in ray_sets.items()}


def compare(ours: dict, ref: dict, scene_size: float) -> dict:
    hit, ref_hit = ours["triangle"] >= 0, ref["triangle"] >= 0
    both = hit & ref_hit
    with np.errstate(invalid="ignore"):  # inf - inf on rays both miss
        dt = np.abs(ours["t"] - ref["t"])
    far = both & (dt > 1e-4 * scene_size)
    return {
        "rays": len(hit),
        "hits": int(hit.sum()),
        "embree_hits": int(ref_hit.sum()),
        "only_ours": int((hit & ~ref_hit).sum()),
        "only_embree": int((~hit & ref_hit).sum()),
        "t_apart": int(far.sum()),
        "other_triangle": int((both & (ours["triangle"] != ref["triangle"])).sum()),
        "max_dt": float(dt[both].max()) if both.any() else 0.0,
    }


@pytest.fixture(scope="module")
def embree_brute_hits(camel_rays, embree_camel):
    """Embree's hits on the conformance suite's rays (``conftest.camel_rays``), whose brute
    force hits the session computes once (``conftest.brute_hits``)."""
    return {name: embree_camel.closest_hit(o, d) for name, (o, d) in camel_rays.items()}


@pytest.mark.parametrize("ray_set", ["camera", "incoherent"])
@pytest.mark.parametrize("kernel", list(jrt.KERNELS))
def test_closest_hits_match_embree(camel, structure, ray_sets, embree_hits, camel_rays,
                                   brute_hits, embree_brute_hits, kernel, ray_set):
    if structure.kind == "brute":  # the session's brute-force hits on its 20k rays
        assert len(camel_rays[ray_set][0]) == BRUTE_RAYS
        ours, ref = brute_hits(kernel, ray_set), embree_brute_hits[ray_set]
    else:
        origins, directions = ray_sets[ray_set]
        ours = as_numpy(jrt.closest_hit(structure, origins, directions, kernel=kernel))
        ref = embree_hits[ray_set]
    report = compare(ours, ref, camel.diagonal)
    disagree = report["only_ours"] + report["only_embree"] + report["t_apart"]
    print(f"\n{structure.kind} / {kernel} / {ray_set}: {report} -> {disagree} disagree "
          f"({disagree / report['rays']:.2e}); 'other_triangle' counts ties on shared "
          "edges and vertices where both sides hit at the same t")
    assert report["hits"] > 0.1 * report["rays"]
    assert disagree <= MAX_SHARE * report["rays"]
    assert np.all(np.isfinite(ours["u"])) and np.all(np.isfinite(ours["v"]))


@pytest.mark.parametrize("kernel", list(jrt.KERNELS))
def test_occluded_matches_embree(camel, camel_brute, embree_camel, kernel):
    """Any-hit with a finite tmax: rays from the incoherent set, cut at a random length."""
    origins, directions = incoherent_set(camel.vertices, 20_000, seed=2)
    tmax = np.random.default_rng(3).uniform(0.5, 3.0, len(origins)).astype(np.float32)
    ours = np.asarray(jrt.occluded(camel_brute, origins, directions, tmax=tmax, kernel=kernel))
    ref = embree_camel.occluded(origins, directions, tmax)
    # A hit within 1e-4 of the scene size of tmax may fall either side in float32.
    closest = embree_camel.closest_hit(origins, directions)
    near_tmax = np.abs(closest["t"] - tmax) <= 1e-4 * camel.diagonal
    disagree = int(((ours != ref) & ~near_tmax).sum())
    print(f"\n{kernel}: occluded {int(ours.sum())} vs Embree {int(ref.sum())}, "
          f"{disagree} disagree away from tmax")
    assert 0.05 * len(ours) < ref.sum() < 0.95 * len(ours)
    assert disagree <= MAX_SHARE * len(ours)
