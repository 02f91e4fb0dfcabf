"""Shared fixtures: the camel (found through jrt's resolver), its brute-force and BVH structures."""

from __future__ import annotations

import pytest

import accel
import jrt  # noqa: F401  (XLA flags before JAX starts)
from jrt.data import camel_path
from jrt.mesh import load_mesh


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
def camel_bvh(camel):
    return accel.build("bvh", camel.vertices, camel.faces)


@pytest.fixture(params=["brute", "bvh"])
def structure(request):
    """The camel's brute-force structure, then its BVH: a test over both."""
    return request.getfixturevalue({"brute": "camel_brute", "bvh": "camel_bvh"}[request.param])


@pytest.fixture(scope="session")
def embree_camel(camel):
    peers = pytest.importorskip("benchmarks.peers")
    return peers.EmbreePeer(camel.vertices, camel.faces)
