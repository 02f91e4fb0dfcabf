"""A structure registered from outside accel passes the conformance suite unchanged.

``docs/adding-a-structure.md`` walks through adding a structure; this is its example, run:
a binary BVH (``accel.bvh``'s builder with ``width=2``) declared as a kind of its own,
``"bvh2"``, with the BVH's traversal step (``jrt.bvh.traversal``) and plane decoder. It is
registered by this module alone (no other module names it), and every check of
``tests/test_structures.py`` runs on it: the camel's hits bit for bit against brute force,
occluded, counters, no cracks, empty and degenerate meshes, the errors. The registry's own
rules (a taken name, an unknown name, the derived lists) are checked here too.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

# The conformance tests, collected again in this module for the kind below (the fixtures
# ``kind`` and ``any_kind`` are overridden here).
from test_structures import *  # noqa: F403
from test_structures import TINY_MESH

import accel
import accel.bvh
import jrt
import jrt.bvh
from accel.structure import Structure

NAME = "bvh2"


def build_bvh2(vertices, faces, *, max_leaf_size: int = 4) -> Structure:
    """A BVH of binary nodes, as its own kind."""
    built = accel.bvh.build(vertices, faces, max_leaf_size=max_leaf_size, width=2)
    return dataclasses.replace(built, kind=NAME)


BVH2 = accel.StructureKind(
    name=NAME, build=build_bvh2, arrays=accel.kind("bvh").arrays,
    layout=accel.kind("bvh").layout, traversal=jrt.bvh.traversal,
    planes=accel.bvh.stored_planes, summary="a binary BVH (the docs' example)")


@pytest.fixture(scope="module", autouse=True)
def registered():
    accel.register(BVH2)
    yield
    accel.unregister(NAME)


@pytest.fixture
def kind():
    return NAME


@pytest.fixture
def any_kind():
    return NAME


def test_the_registry_lists_the_new_kind_everywhere():
    assert accel.names()[-1] == NAME and NAME in accel.names(engine=True)
    assert NAME in accel.NAMES and accel.SIGNATURES[NAME] == (BVH2.arrays, BVH2.layout)
    assert accel.parameters(NAME) == {"max_leaf_size": 4}
    structure = accel.build(NAME, *TINY_MESH)
    assert structure.kind == NAME and structure.layout_value("width") == 2
    planes = accel.planes(structure)
    assert [p.dtype for p in planes] == [np.float32] * 3 and all(len(p) for p in planes)
    hits = jrt.closest_hit(structure, np.float32([[0.5, 0.5, 0]]), np.float32([[0, 0, 1]]))
    assert int(hits.triangle[0]) == 0 and float(hits.t[0]) == 1.0


def test_the_new_kind_answers_all_hits_as_brute_force(camel19k):
    """``jrt.all_hits`` needs nothing of a structure beyond its step: the new kind's every
    hit, bit for bit, is brute force's (incoherent rays of the 19k camel)."""
    from jrt.raysets import incoherent_set

    origins, directions = incoherent_set(camel19k.vertices, 500, seed=1)
    got, want = (jrt.all_hits(accel.build(name, camel19k.vertices, camel19k.faces),
                              origins, directions, 4) for name in (NAME, "brute"))
    assert int(np.sum(want.count)) > 0
    for field, a, b in zip(got._fields, got, want, strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b), err_msg=field)


def test_an_unknown_name_lists_the_new_kind():
    with pytest.raises(ValueError, match=r"unknown acceleration structure 'bvh3' .*"
                       r"allowed: brute, bvh, kdtree, octree, bsp, grid, bvh2$"):
        accel.build("bvh3", *TINY_MESH)
