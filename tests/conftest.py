"""Shared fixtures: the camel (found through jrt's resolver) and its structures, built once."""

from __future__ import annotations

import pytest

import accel
import jrt  # (XLA flags before JAX starts)
from jrt.data import camel_path
from jrt.mesh import load_mesh
from jrt.raysets import camera_set, incoherent_set
from jrt.trace import as_numpy

#: Rays of each camel set that every structure's tests trace against brute force.
CAMEL_RAYS = 20_000


@pytest.fixture(scope="session")
def camel():
    try:
        path = camel_path("camel")
    except FileNotFoundError as exc:
        pytest.skip(str(exc))
    return load_mesh(path)


@pytest.fixture(scope="session")
def camel_brute(camel):
    return accel.build("brute", camel.vertices, camel.faces)


@pytest.fixture(scope="session")
def camel_bvh(camel_structures):
    return camel_structures("bvh")


@pytest.fixture(scope="session")
def camel_structures(camel):
    """name -> the camel's structure of that kind, each built once per session."""
    built = {}

    def get(name):
        if name not in built:
            built[name] = accel.build(name, camel.vertices, camel.faces)
        return built[name]

    return get


@pytest.fixture(params=accel.NAMES)
def structure(request, camel_structures):
    """The camel under every structure, brute force first: a test over all of them."""
    return camel_structures(request.param)


@pytest.fixture(scope="session")
def embree_camel(camel):
    peers = pytest.importorskip("benchmarks.peers")
    return peers.EmbreePeer(camel.vertices, camel.faces)


@pytest.fixture(scope="session")
def camel_rays(camel):
    """The camel's camera and incoherent sets, CAMEL_RAYS each (the same count, so that
    both share every compiled function)."""
    origins, directions = camera_set(camel.vertices, CAMEL_RAYS)
    return {
        "camera": (origins[:CAMEL_RAYS], directions[:CAMEL_RAYS]),
        "incoherent": incoherent_set(camel.vertices, CAMEL_RAYS, seed=0),
    }


@pytest.fixture(scope="session")
def brute_hits(camel_brute, camel_rays):
    """Brute force's closest hits per (kernel, ray set), computed once per session when
    first asked (each costs 20k x 69k triangle tests)."""
    cache = {}

    def get(kernel, ray_set):
        if (kernel, ray_set) not in cache:
            origins, directions = camel_rays[ray_set]
            cache[kernel, ray_set] = as_numpy(
                jrt.closest_hit(camel_brute, origins, directions, kernel=kernel))
        return cache[kernel, ray_set]

    return get
