"""Shared fixtures: the camel (found through jrt's resolver) and its structures, built once."""

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
