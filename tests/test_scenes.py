"""The study's scene suite (``jrt.scenes``): each scene has the character it is named for,
and every structure answers on it as brute force does, or, where brute force's float32
kernel is wrong, as the float64 oracle does.

The stadium is where the two part: its rays start some 2,000 camel heights from the camel,
so a camel triangle is a few float32 ulps wide as seen from a ray's origin, and a kernel
evaluated on such a triangle from far away decides by rounding. Brute force evaluates every
triangle for every ray and reports some of those false hits (watertight: its conservative
bound on t keeps a hit whose edge functions, rounded, all agree); the structures never test
the camel from rays that pass hundreds of units away, and agree with the float64 oracle.
"""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

import accel
import jrt
from benchmarks import suite
from benchmarks.stability.float64_oracle import oracle
from jrt.raysets import camera_set, incoherent_set
from jrt.scenes import GENERATED, HERD, NEEDLES, SCENES, scene_mesh
from jrt.trace import as_numpy

#: Rays of each set (camera, incoherent) traced on each scene.
RAYS = 2048


def test_the_scenes_and_their_sizes():
    assert SCENES[:4] == ("camel", "bunny", "teapot", "fandisk")
    assert set(GENERATED) == {"stadium", "herd", "room", "slivers"}
    assert len(scene_mesh("camel", size="small").faces) == 19_536
    assert len(scene_mesh("teapot").faces) == 6_320  # one size: the shipped mesh
    with pytest.raises(ValueError, match="unknown scene 'stadion'; the scenes are camel, "):
        scene_mesh("stadion")
    with pytest.raises(ValueError, match="unknown size 'huge' of scene 'room'; sizes are "
                       "full, small"):
        scene_mesh("room", size="huge")


def test_the_stadium_is_a_thousand_camels_across():
    camel = scene_mesh("camel", size="small")
    stadium = scene_mesh("stadium", size="small")
    assert len(stadium.faces) > len(camel.faces)
    extent = np.ptp(stadium.vertices, axis=0)
    assert min(extent[0], extent[2]) >= 1000 * camel.diagonal * 0.999
    # The camel stands on the ground at the centre, every face of it in the middle.
    centre = stadium.vertices[stadium.faces[:len(camel.faces)]].reshape(-1, 3)
    assert np.abs(centre[:, [0, 2]]).max() < camel.diagonal
    assert centre[:, 1].min() == pytest.approx(0.0, abs=1e-6)


def test_the_herd_is_camels_with_overlapping_boxes():
    herd = scene_mesh("herd", size="small")
    per = len(scene_mesh("camel", size="small").faces)
    assert len(herd.faces) == HERD["small"] * per
    boxes = [(p.min(axis=0), p.max(axis=0))
             for p in np.split(herd.vertices[herd.faces].reshape(-1, 3), HERD["small"])]
    overlapping = sum(bool(np.all(a[0] <= b[1]) and np.all(b[0] <= a[1]))
                      for i, a in enumerate(boxes) for b in boxes[i + 1:])
    assert overlapping >= 1
    assert HERD["full"] * 69_092 >= 1_100_000  # the full herd's size, not built here


def test_the_room_is_closed_and_every_ray_from_inside_hits():
    room = scene_mesh("room", size="small")
    walls = trimesh.Trimesh(room.vertices, room.faces[-12:], process=True)
    assert walls.is_watertight and walls.volume < 0  # wound inward: seen from inside
    lo, hi = walls.bounds
    rng = np.random.default_rng(3)
    origins = (lo + rng.uniform(0.05, 0.95, (1000, 3)) * (hi - lo)).astype(np.float32)
    directions = rng.normal(size=(1000, 3)).astype(np.float32)
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    hits = jrt.closest_hit(accel.build("brute", room.vertices, room.faces), origins,
                           directions)
    assert (np.asarray(hits.triangle) >= 0).all()


def test_slivers_are_needles():
    mesh = scene_mesh("slivers", size="small")
    assert len(mesh.faces) == NEEDLES["small"]
    p = mesh.vertices[mesh.faces].astype(np.float64)
    sides = np.linalg.norm(p - p[:, [1, 2, 0]], axis=2)
    assert (sides.min(axis=1) <= 1.01e-3 * sides.max(axis=1)).all()


@pytest.fixture(scope="module", params=["stadium", "room", "slivers"])
def scene(request):
    mesh = scene_mesh(request.param, size="small")
    o1, d1 = camera_set(mesh.vertices, RAYS)
    o2, d2 = incoherent_set(mesh.vertices, RAYS, seed=5)
    origins, directions = np.concatenate([o1[:RAYS], o2]), np.concatenate([d1[:RAYS], d2])
    brute = as_numpy(jrt.closest_hit(accel.build("brute", mesh.vertices, mesh.faces),
                                     origins, directions))
    return request.param, mesh, origins, directions, brute


@pytest.mark.parametrize("kind", accel.names(engine=True))
def test_every_structure_answers_as_brute_force_or_the_float64_oracle(scene, kind):
    name, mesh, origins, directions, want = scene
    got = as_numpy(jrt.closest_hit(accel.build(kind, mesh.vertices, mesh.faces), origins,
                                   directions))
    assert (want["triangle"] >= 0).mean() > 0.05  # (thin needles: 9 % of the rays)
    differ = np.flatnonzero((got["triangle"] != want["triangle"])
                            | (got["t"] != want["t"]) | (got["u"] != want["u"])
                            | (got["v"] != want["v"]))
    if name != "stadium":
        assert differ.size == 0, (name, kind, differ[:5])
        return
    # Where the structure is not brute force, brute force is wrong: the float64 oracle
    # finds no hit there, or the structure's triangle.
    assert differ.size < 0.02 * len(origins)
    t_ref, row_ref = oracle(mesh.vertices[mesh.faces].astype(np.float64), origins[differ],
                            directions[differ])
    np.testing.assert_array_equal(got["triangle"][differ], row_ref, err_msg=f"{kind}")
    assert (want["triangle"][differ] != row_ref).all()


def test_jrt_bench_takes_a_scene(tmp_path):
    """``--scene NAME`` benchmarks a scene of the suite, its small size with --quick; it
    cannot be given with --mesh."""
    parser = suite.build_parser()
    quick = suite._resolve(parser.parse_args(["--quick", "--scene", "stadium"]))
    assert quick["mesh"] == "stadium-small"
    assert len(suite._load(quick["mesh"]).faces) == len(scene_mesh("stadium",
                                                                   size="small").faces)
    assert suite._resolve(parser.parse_args(["--scene", "herd"]))["mesh"] == "herd"
    assert suite._resolve(parser.parse_args(["--quick", "--scene", "camel"]))["mesh"] == \
        "camel-19k"
    assert suite._resolve(parser.parse_args(["--quick", "--scene", "fandisk"]))["mesh"] == \
        "fandisk"
    with pytest.raises(SystemExit):
        parser.parse_args(["--scene", "stadium", "--mesh", "camel"])
    # --scene-size overrides the size --quick implies; it needs a scene.
    assert suite._resolve(parser.parse_args(["--scene", "herd", "--scene-size", "small"]))[
        "mesh"] == "herd-small"
    assert suite._resolve(parser.parse_args(["--quick", "--scene", "room", "--scene-size",
                                             "full"])) == {**quick, "mesh": "room",
                                                           "scene": "room"}
    with pytest.raises(suite.BenchError, match="--scene-size applies to --scene"):
        suite._resolve(parser.parse_args(["--scene-size", "small"]))
    with pytest.raises(SystemExit):
        parser.parse_args(["--scene", "arena"])


@pytest.mark.parametrize("query", ["closest", "occluded"])
def test_the_suites_mismatches_are_judged_by_the_float64_oracle(query):
    """Where a structure and brute force differ, the suite's correctness record says which
    one the float64 oracle sides with: here ray 0 hits the triangle and ray 1 misses it,
    and the 'brute force' answers are made wrong on purpose for both."""
    triangles = np.array([[[0, 0, 5], [1, 0, 5], [0, 1, 5]]], np.float64)
    origins = np.array([[0.2, 0.2, 0], [2, 2, 0], [0.1, 0.1, 0]], np.float32)
    directions = np.tile(np.float32([0, 0, 1]), (3, 1))
    ray_set = suite.RaySet("camera", query, origins, directions, None, 3)
    if query == "closest":
        def answer(triangle):
            return {"triangle": np.array(triangle), "t": np.zeros(3, np.float32)}
        ours, brute = answer([0, -1, 0]), answer([-1, 0, 0])
        embree = {"triangle": np.array([0, -1, 0])}
    else:
        ours, brute = {"occluded": np.array([True, False, True])}, \
            {"occluded": np.array([False, True, True])}
        embree = np.array([True, False, True])
    idx = np.arange(3)
    record = suite.correctness_record("bvh", ray_set, idx, ours, brute, embree, triangles)
    assert record["mismatches"] == 2
    assert record["oracle"] == {"rays": 2, "structure_right": 2, "brute_right": 0}
    swapped = suite.correctness_record("bvh", ray_set, idx, brute, ours, embree, triangles)
    assert swapped["oracle"] == {"rays": 2, "structure_right": 0, "brute_right": 2}
    assert "oracle" not in suite.correctness_record("bvh", ray_set, idx, ours, ours, embree,
                                                    triangles)


def test_the_build_benchmark_times_every_structure_beside_embree(tmp_path):
    """``python -m benchmarks.builds``: each structure's and Embree's build times on a
    scene, and the same structure as accel.build makes (its SAH cost)."""
    import json

    from benchmarks import builds

    out = tmp_path / "builds.json"
    builds.main(["--scenes", "slivers", "--size", "small", "--builds", "2", "--structures",
                 "bvh,grid", "--json", str(out)])
    (r,) = json.loads(out.read_text())["results"]
    mesh = scene_mesh("slivers", size="small")
    assert (r["scene"], r["triangles"]) == ("slivers", len(mesh.faces))
    assert set(r["seconds"]) == {"embree", "bvh", "grid"}
    assert all(len(v) == 2 and min(v) >= 0 for v in r["seconds"].values())
    assert r["sah_cost"]["bvh"] == accel.build("bvh", mesh.vertices, mesh.faces).stats[
        "sah_cost"]
    with pytest.raises(SystemExit):
        builds.main(["--scenes", "arena"])
