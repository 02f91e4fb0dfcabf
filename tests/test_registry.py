"""The structure registry (``accel.registry``): each kind's declaration agrees with what its
builder makes, and every list of structures is the registry's."""

from __future__ import annotations

import dataclasses
import inspect

import numpy as np
import pytest

import accel
import accel.bvh
from accel.registry import BUILTIN_MODULES

#: One triangle in z = 1 and two stacked above it.
VERTICES = np.float32([[-1, -1, 1], [3, -1, 1], [-1, 3, 1], [-1, -1, 2], [3, -1, 2],
                       [-1, 3, 2], [-1, -1, 3], [3, -1, 3], [-1, 3, 3]])
FACES = np.int32([[0, 1, 2], [3, 4, 5], [6, 7, 8]])


def test_the_builtin_kinds_in_their_order():
    assert accel.names() == ("brute", "bvh", "kdtree", "octree", "bsp", "grid")
    assert accel.names(engine=True) == accel.names()[1:]
    assert accel.names(engine=False) == ("brute",)
    assert accel.NAMES == accel.names()
    assert [m.rsplit(".", 1)[1] for m in BUILTIN_MODULES] == list(accel.names())


@pytest.mark.parametrize("name", ["brute", "bvh", "kdtree", "octree", "bsp", "grid"])
def test_a_declaration_matches_what_its_builder_makes(name):
    declared = accel.kind(name)
    built = accel.build(name, VERTICES, FACES)
    assert built.kind == name
    assert frozenset(built.arrays) == declared.arrays
    assert frozenset(key for key, _ in built.layout) == declared.layout
    assert accel.SIGNATURES[name] == (declared.arrays, declared.layout)
    # The parameters are the builder's keyword arguments, with its defaults.
    signature = inspect.signature(declared.build)
    keywords = {p.name: p.default for p in signature.parameters.values()
                if p.default is not inspect.Parameter.empty}
    assert accel.parameters(name) == keywords
    assert declared.engine == (name != "brute")
    if declared.engine:  # the jrt module of the same name steps it
        assert declared.traversal == f"jrt.{name}:traversal"
        planes = accel.planes(built)
        assert len(planes) == 3 and all(p.dtype == np.float32 for p in planes)
        assert all((np.diff(p) > 0).all() for p in planes), "sorted, unique"


def test_a_planes_decoder_reports_the_bvh_root_box():
    """The BVH's planes are its decoded child boxes' faces: the three stacked triangles'
    box, x and y from -1 to 3 and z from 1 to 3, is among them (the boxes are rounded
    outward to float32 around the local frame, so within a few ulps)."""
    planes = accel.planes(accel.build("bvh", VERTICES, FACES))
    for axis, (lo, hi) in enumerate([(-1, 3), (-1, 3), (1, 3)]):
        assert np.min(np.abs(planes[axis] - lo)) <= 4 * np.spacing(np.float32(abs(lo) + 1))
        assert np.min(np.abs(planes[axis] - hi)) <= 4 * np.spacing(np.float32(abs(hi) + 1))


def test_unknown_names_and_bad_declarations_are_errors():
    with pytest.raises(ValueError, match=r"unknown acceleration structure 'bhv' \(did you "
                       r"mean 'bvh'\?\); allowed: brute, bvh, kdtree, octree, bsp, grid"):
        accel.build("bhv", VERTICES, FACES)
    bvh = accel.kind("bvh")
    with pytest.raises(ValueError, match="registered already"):
        accel.register(dataclasses.replace(bvh, summary="another"))
    with pytest.raises(ValueError, match="must include"):
        accel.StructureKind(name="bad", build=bvh.build, arrays=frozenset({"nodes"}))
    with pytest.raises(ValueError, match="'module:function'"):
        accel.StructureKind(name="bad", build=bvh.build, arrays=bvh.arrays,
                            traversal="jrt.bvh.traversal")
    with pytest.raises(ValueError, match="identifier"):
        accel.StructureKind(name="a b", build=bvh.build, arrays=bvh.arrays)
    with pytest.raises(ValueError, match=r"rows \['cells'\] are not among its arrays"):
        accel.StructureKind(name="bad", build=bvh.build, arrays=bvh.arrays,
                            rows=frozenset({"nodes", "cells"}))
    with pytest.raises(TypeError, match="StructureKind"):
        accel.register("bvh")
