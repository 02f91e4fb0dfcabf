"""The public API's contract: size buckets, keyword-only options, ``accel.build`` on a mesh,
directions of any length within the documented range, the exports, and the import-order
warning.

Every answer is checked against brute force (with unit directions, or with buckets off),
never a stored value. The rays are 1,100 of the 19k-triangle camel (a count that is not a
bucket: 1,536 rays are traced), so the tests share one compiled program per structure.
"""

from __future__ import annotations

import difflib
import importlib
import inspect
import os
import re
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

import accel
import jrt
from jrt import brute as jrt_brute
from jrt import engine, trace
from jrt.trace import as_numpy

ROOT = Path(__file__).resolve().parents[1]
N = 1100
FIELDS = ("t", "triangle", "u", "v")


@pytest.fixture(scope="module")
def mesh(camel19k):
    return camel19k


@pytest.fixture(scope="module")
def built(mesh):
    """Every structure of the 19k camel, from the mesh object itself."""
    return {name: accel.build(name, mesh) for name in accel.NAMES}


@pytest.fixture(scope="module")
def rays(camel19k_api_rays):
    return camel19k_api_rays


@pytest.fixture(scope="module")
def reference(built, rays):
    """Brute force's answers with unit directions and no size bucket."""
    o, d, t = rays
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv(trace.BUCKETS_ENV, "0")
        hits = as_numpy(jrt.closest_hit(built["brute"], o, d, tmax=t))
        occluded = np.asarray(jrt.occluded(built["brute"], o, d, tmax=t))
    assert 0.2 < (hits["triangle"] >= 0).mean() < 0.8
    np.testing.assert_array_equal(occluded, hits["triangle"] >= 0)  # two separate queries
    return hits, occluded


def assert_same(got, want, label):
    for field in FIELDS:
        assert np.array_equal(got[field], want[field]), (
            f"{label}: {field} differs on {int((got[field] != want[field]).sum())} rays")


# ------------------------------------------------------------------------- size buckets


def test_bucket_sizes_are_the_smallest_of_the_documented_set():
    """1024, then 2^k and 3 x 2^(k-1): at most 1.5x the rays, each a multiple of 256."""
    allowed = sorted({trace.MIN_BUCKET} | {m << k for m in (2, 3) for k in range(9, 30)})
    allowed = [b for b in allowed if b >= trace.MIN_BUCKET]
    for n in [1, 2, 255, 1000, 1023, 1024, 1025, 1100, 1536, 1537, 2047, 2048, 3000,
              20_000, 262_144, 1_000_000, 1 << 20, (1 << 20) + 1]:
        size = trace.bucket_size(n)
        assert size == next(b for b in allowed if b >= n), n
        assert size % 256 == 0
        if n > trace.MIN_BUCKET:
            assert size <= 1.5 * n
    assert trace.bucket_size(1 << 20) == 1 << 20  # a 1024^2 image is not padded


def test_a_new_ray_count_in_a_bucket_compiles_nothing(built, rays, monkeypatch):
    """Counts 1000, 1001, 700 and 1024 share one program per structure (the 1024 bucket);
    with the buckets off (JRT_SIZE_BUCKETS=0), a new count compiles a program of its own."""
    o, d, t = rays
    for structure, program in ((built["bvh"], engine._traverse),
                               (built["brute"], jrt_brute.closest_hit)):
        jrt.closest_hit(structure, o[:1000], d[:1000], tmax=t[:1000])
        compiled = program._cache_size()
        for n in (1001, 700, 1024):
            hits = jrt.closest_hit(structure, o[:n], d[:n], tmax=t[:n])
            assert hits.t.shape == hits.triangle.shape == (n,)
        assert program._cache_size() == compiled
        with monkeypatch.context() as mp:
            mp.setenv(trace.BUCKETS_ENV, "0")
            jrt.closest_hit(structure, o[:1001], d[:1001], tmax=t[:1001])
        assert program._cache_size() == compiled + 1


def test_a_small_structure_of_another_size_compiles_nothing():
    """Two small meshes (80 and 64 triangles, so that every kind's arrays differ in
    length, with the same static layout) share one traversal program per kind: their
    structures are padded to the same size buckets (``jrt.trace.padded_structure``). Each
    still returns brute force's hits, and the structure the caller holds keeps its own
    arrays."""
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=1)
    meshes = [(sphere.vertices.astype(np.float32), sphere.faces),
              (sphere.vertices.astype(np.float32), sphere.faces[16:])]
    rng = np.random.default_rng(5)
    origins = rng.uniform(-2, 2, (300, 3)).astype(np.float32)
    directions = -origins + rng.normal(0, 0.3, (300, 3)).astype(np.float32)
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    for kind in accel.names(engine=True):
        built = [accel.build(kind, v, f) for v, f in meshes]
        assert built[0].num_triangles == 80 and built[1].num_triangles == 64
        # The layout (leaf_bits) is static: a program of its own whatever the lengths.
        assert built[0].layout == built[1].layout, kind
        counts = []
        for structure, (v, f) in zip(built, meshes, strict=True):
            got = as_numpy(jrt.closest_hit(structure, origins, directions))
            want = as_numpy(jrt.closest_hit(accel.build("brute", v, f), origins, directions))
            assert_same(got, want, kind)
            assert (got["triangle"] >= 0).mean() > 0.3
            counts.append(engine.compiled_programs())
        assert counts[1] == counts[0], f"{kind}: the second mesh compiled a program"
        assert built[1]["triangles"].shape == (64, 3, 3)


@pytest.mark.parametrize("kind", accel.NAMES)
def test_padded_calls_return_brute_forces_unpadded_hits(kind, built, rays, reference):
    o, d, t = rays
    want_hits, want_occluded = reference
    assert_same(as_numpy(jrt.closest_hit(built[kind], o, d, tmax=t)), want_hits, kind)
    assert np.array_equal(np.asarray(jrt.occluded(built[kind], o, d, tmax=t)), want_occluded)


def test_counters_and_occluded_are_the_same_with_and_without_buckets(built, rays,
                                                                     monkeypatch):
    """Per-ray work is the ray's own: padding changes no count either."""
    o, d, t = rays
    structure = built["bvh"]
    hits, count = jrt.closest_hit(structure, o, d, tmax=t, counters=True)
    mask, occ_count = jrt.occluded(structure, o, d, tmax=t, counters=True)
    monkeypatch.setenv(trace.BUCKETS_ENV, "0")
    hits0, count0 = jrt.closest_hit(structure, o, d, tmax=t, counters=True)
    mask0, occ_count0 = jrt.occluded(structure, o, d, tmax=t, counters=True)
    assert_same(as_numpy(hits), as_numpy(hits0), "counters=True")
    np.testing.assert_array_equal(np.asarray(mask), np.asarray(mask0))
    for a, b in ((count, count0), (occ_count, occ_count0)):
        for field in a._fields:
            np.testing.assert_array_equal(np.asarray(getattr(a, field)),
                                          np.asarray(getattr(b, field)))
    assert np.asarray(count.steps).sum() > N  # the counts are real work


def test_padding_rays_take_no_step(built, rays):
    """The engine answers a padding ray (tmax -inf) before any lane takes it."""
    o, d, t = rays
    size = trace.bucket_size(N)
    po, pd, pt = engine.pad_rays(o, d, t, size, xp=np)
    structure = built["bvh"]
    _, count, status = engine.traverse(trace.traversal_of(structure), structure.arrays,
                                       po, pd, pt, kernel="watertight", any_hit=False,
                                       counters=True)
    assert int(status) == 0
    assert np.asarray(count)[N:].sum() == 0 and np.asarray(count)[:N].sum() > 0


# ------------------------------------------------------------------- keyword-only options


def test_options_are_keyword_only_and_alike():
    params = {f: inspect.signature(f).parameters for f in (jrt.closest_hit, jrt.occluded)}
    for p in params.values():
        assert [n for n, v in p.items() if v.kind == v.POSITIONAL_OR_KEYWORD] == [
            "structure", "origins", "directions"]
    keyword = [[(n, v.default) for n, v in p.items() if v.kind == v.KEYWORD_ONLY]
               for p in params.values()]
    assert keyword[0] == keyword[1]
    assert [n for n, _ in keyword[0]][:2] == ["tmax", "kernel"]


def test_a_fourth_positional_argument_is_refused(built, rays):
    o, d, _ = rays
    for query in (jrt.closest_hit, jrt.occluded):
        with pytest.raises(TypeError, match="positional argument"):
            query(built["bvh"], o[:4], d[:4], 4.5)


# --------------------------------------------------------------------------- accel.build


def test_build_takes_a_mesh_object_or_its_arrays(mesh):
    trimesh = pytest.importorskip("trimesh")
    tri = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
    for kind in ("bvh", "grid"):
        ref = accel.build(kind, mesh.vertices, mesh.faces)
        for source in (mesh, tri):
            got = accel.build(kind, source)
            assert set(got.arrays) == set(ref.arrays)
            for name, array in ref.arrays.items():
                np.testing.assert_array_equal(got.arrays[name], array, err_msg=name)


def test_build_refuses_unclear_input_with_what_it_takes(mesh):
    with pytest.raises(TypeError, match=r"got a ndarray and no faces: pass a mesh with "
                                        r"'vertices' and 'faces' attributes"):
        accel.build("bvh", mesh.vertices)
    with pytest.raises(TypeError, match=r"got a mesh \(Mesh\) and faces as well"):
        accel.build("bvh", mesh, mesh.faces)
    with pytest.raises(TypeError, match="got a str and no faces"):
        accel.build("bvh", "camel.off")


def test_an_unknown_parameter_lists_the_builders_parameters(mesh):
    for kind in accel.NAMES:
        own = inspect.signature(importlib.import_module(f"accel.{kind}").build).parameters
        expected = [n for n, p in own.items() if p.kind == p.KEYWORD_ONLY]
        assert list(accel.parameters(kind)) == expected
        with pytest.raises(TypeError) as info:
            accel.build(kind, mesh, widht=4)
        text = str(info.value)
        assert f"unknown parameter 'widht' for accel.build('{kind}', ...)" in text
        for name in expected:
            assert f"{name}=" in text
        close = difflib.get_close_matches("widht", expected, n=1)
        assert ("did you mean" in text) == bool(close)
        assert not close or f"did you mean {close[0]!r}" in text
    with pytest.raises(TypeError, match=r"did you mean 'width'\?.*width=4"):
        accel.build("bvh", mesh, widht=4)
    with pytest.raises(ValueError, match=r"unknown acceleration structure 'bhv' \(did you "
                                         r"mean 'bvh'\?\); allowed: brute, bvh"):
        accel.build("bhv", mesh)


# ------------------------------------------------------------------ non-unit directions


@pytest.mark.parametrize("kind", accel.NAMES)
def test_power_of_two_lengths_give_the_unit_hits_scaled_exactly(kind, built, rays,
                                                                reference):
    """|d| = 2^k, k in [-19, 19] per ray: the same triangles, u, v, and t / 2^k bit for bit
    (the kernels are affine in d, the margins relative), tmax scaled alike."""
    o, d, t = rays
    want_hits, want_occluded = reference
    k = np.random.default_rng(4).integers(-19, 20, N)
    scale = np.ldexp(np.float32(1), k).astype(np.float32)
    ds, ts = d * scale[:, None], t / scale
    got = as_numpy(jrt.closest_hit(built[kind], o, ds, tmax=ts))
    assert_same(got, dict(want_hits, t=want_hits["t"] / scale), kind)
    assert np.array_equal(np.asarray(jrt.occluded(built[kind], o, ds, tmax=ts)),
                          want_occluded)


def test_any_length_in_range_agrees_with_brute_force_and_unit_rays(built, rays, reference):
    """Lengths spread over [1e-6, 1e6]: every structure equals brute force on the same rays
    bit for bit, and brute force finds the unit rays' triangles at t / |d|."""
    o, d, t = rays
    want_hits, _ = reference
    length = np.float32(10.0) ** np.random.default_rng(5).uniform(-6, 6, N).astype(np.float32)
    length = np.clip(length, 1.01e-6, 0.99e6)
    ds = (d * length[:, None]).astype(np.float32)
    ts = (t / length).astype(np.float32)
    brute_hits = as_numpy(jrt.closest_hit(built["brute"], o, ds, tmax=ts))
    for kind in ("bvh", "grid"):
        assert_same(as_numpy(jrt.closest_hit(built[kind], o, ds, tmax=ts)), brute_hits, kind)
    norm = np.linalg.norm(ds.astype(np.float64), axis=1)
    # A ray through an edge or vertex may take either neighbour once d is rounded.
    inner = np.minimum(np.minimum(want_hits["u"], want_hits["v"]),
                       1 - want_hits["u"] - want_hits["v"]) > 1e-4
    same = brute_hits["triangle"] == want_hits["triangle"]
    assert same[inner | (want_hits["triangle"] < 0)].all()
    hit = same & (want_hits["triangle"] >= 0)
    np.testing.assert_allclose(brute_hits["t"][hit] * norm[hit], want_hits["t"][hit],
                               rtol=1e-5)


@pytest.mark.parametrize("kind", ["brute", "bvh"])
@pytest.mark.parametrize("value", [0.0, 5e-7, 1e-30, 2e6, 1e30])
def test_a_direction_out_of_range_is_named_with_its_length(kind, built, rays, value):
    o, d, _ = rays
    d = d[:5].copy()
    d[3] = np.float32([0.0, value, 0.0])
    for query in (jrt.closest_hit, jrt.occluded):
        with pytest.raises(ValueError) as info:
            query(built[kind], o[:5], d)
        assert str(info.value) == (
            f"directions of ray 3 is {d[3].tolist()} (length {float(d[3, 1]):.6g}; 1 such "
            "rays of 5); allowed: a length within [1e-06, 1e+06] (t is in units of that "
            "length)")


# -------------------------------------------------------------------------------- exports


def test_the_readme_names_only_what_jrt_has():
    """Every ``jrt.NAME`` the README's table names resolves; ``__all__`` lists real names
    and the types its docstrings point to."""
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    table = "\n".join(line for line in readme.splitlines() if line.startswith("|"))
    names = set(re.findall(r"`jrt\.([A-Za-z_]\w*)", table))
    assert {"closest_hit", "occluded", "load_mesh"} <= names
    missing = [name for name in sorted(names) if not hasattr(jrt, name)]
    assert not missing, missing
    for name in jrt.__all__:
        assert hasattr(jrt, name), name
    assert jrt.Counters is engine.Counters and "Counters" in jrt.__all__
    assert {"StackOverflowError", "TraversalError", "ImportOrderWarning"} <= set(jrt.__all__)


def test_clear_caches_empties_the_renderers_caches_and_jaxs(monkeypatch):
    """jrt.clear_caches empties every cache of compiled programs registered with
    jrt.programs (the renderers' ones among them) and JAX's own caches. (Run on stand-ins,
    so that the rest of this process keeps its compiled programs.)"""
    from jrt import batch, host_tree, programs, wavefront

    registered = [id(c) for c in programs._CACHES]
    for cache in (wavefront._COMPILED, wavefront._RENDERERS, host_tree._COMPILED,
                  batch._COMPILED):
        assert id(cache) in registered
    calls = []
    monkeypatch.setattr(programs, "_CACHES", [])
    monkeypatch.setattr(programs.jax, "clear_caches", lambda: calls.append("jax"))
    mine = programs.program_cache()
    mine["a program"] = object()
    jrt.clear_caches()
    assert mine == {} and calls == ["jax"]


def test_a_program_cache_keeps_the_most_recently_used():
    """The renderers' caches are bounded: beyond ``maxsize`` the least recently used entry
    goes (reading one, by ``[]`` or ``get``, makes it the newest), and the dropped program
    is freed when nothing else holds it. Checked against a list kept in order of use."""
    import gc
    import weakref

    from jrt import batch, host_tree, programs, wavefront

    for cache in (wavefront._COMPILED, host_tree._COMPILED, batch._COMPILED):
        assert isinstance(cache, programs.ProgramCache)
        assert cache.maxsize == programs.DEFAULT_MAXSIZE
    assert wavefront._RENDERERS.maxsize == 8

    class Program:  # a stand-in that weakref can follow
        pass

    cache, order = programs.ProgramCache(maxsize=3), []  # order: oldest use first
    made = {}
    rng = np.random.default_rng(7)
    for step in range(200):
        key = int(rng.integers(6))
        if rng.random() < 0.5:
            got = cache.get(key)
            assert (got is not None) == (key in order)
            if got is not None:
                assert got is made[key]
                order.remove(key)
                order.append(key)
        else:
            made[key] = cache[key] = Program()
            if key in order:
                order.remove(key)
            order.append(key)
            del order[:-3]
        assert list(cache) == order, step
    dropped = weakref.ref(made[order[0]])
    for key in (10, 11, 12):
        made.pop(key, None)
        cache[key] = Program()
    made.clear()
    gc.collect()
    assert dropped() is None and list(cache) == [10, 11, 12]
    for bad in (0, -1, 2.5, True, "8"):
        with pytest.raises(ValueError, match="maxsize"):
            programs.ProgramCache(bad)


def test_the_query_programs_are_dropped_beyond_their_bound(monkeypatch):
    """JAX keeps every program a jitted function compiles; the query functions (the
    engine's traversal, brute force's, all_hits' record) are registered with
    jrt.programs and dropped together once they hold more than the bound, after a query.
    (Checked on stand-in jitted functions, so that this process keeps its programs; and a
    query calls the trim once, spied on.)"""
    import jax
    import jax.numpy as jnp

    from jrt import brute, engine, programs

    all_hits = importlib.import_module("jrt.all_hits")  # (jrt.all_hits is the function)
    for fn in (engine._traverse, brute.closest_hit, brute.occluded, brute.all_rows,
               all_hits._record):
        assert fn in programs._JITTED
    assert programs.MAX_QUERY_PROGRAMS * 195 < 65_530 // 2  # mappings of camel traversals
    one, two = jax.jit(lambda x: x + 1), jax.jit(lambda x: jnp.sin(x) * 2)
    monkeypatch.setattr(programs, "_JITTED", [one, two])
    for n in range(1, 4):  # three programs each, six in all
        one(jnp.ones(n)).block_until_ready()
        two(jnp.ones(n)).block_until_ready()
    assert one._cache_size() == 3 and two._cache_size() == 3
    assert not programs.trim_programs(limit=6)
    assert one._cache_size() == 3 and two._cache_size() == 3
    assert programs.trim_programs(limit=5)
    assert one._cache_size() == 0 and two._cache_size() == 0
    assert float(one(jnp.ones(1))[0]) == 2.0  # compiles again, same answer

    calls = []
    monkeypatch.setattr(trace, "trim_programs", lambda: calls.append(1))
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)
    s = accel.build("brute", v, np.array([[0, 1, 2]], np.int32))
    jrt.closest_hit(s, np.array([[0.2, 0.2, 1]], np.float32),
                    np.array([[0, 0, -1]], np.float32))
    assert calls == [1]


def test_the_readme_example_runs_and_matches_brute_force():
    """The README's Python example, as printed, in a fresh interpreter; its hits equal brute
    force's and its any-hit answer equals ``t < tmax`` of those hits."""
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    blocks = re.findall(r"```python\n(.*?)```", readme, flags=re.S)
    assert blocks, "README.md has no ```python block"
    check = """
        import numpy as _np
        _reference = jrt.closest_hit(accel.build("brute", mesh), origins, directions,
                                     kernel="watertight")
        for _field in ("t", "triangle", "u", "v"):
            _np.testing.assert_array_equal(getattr(hits, _field), getattr(_reference, _field))
        _np.testing.assert_array_equal(_np.asarray(blocked), _np.asarray(hits.t) < 2.0)
        print("HIT FRACTION", float(_np.mean(_np.asarray(hits.triangle) >= 0)))
    """
    out = _python(blocks[0] + textwrap.dedent(check))
    assert out.returncode == 0, out.stderr[-3000:]
    fraction = float(out.stdout.split("HIT FRACTION")[1])
    assert 0.1 < fraction < 0.9, out.stdout  # the example's rays meet the camel, not all


def test_the_readme_render_example_runs_and_matches_the_host_tree():
    """The README's renderer example, as printed, in a fresh interpreter: its image equals
    the host-stepped reference tree's, and each vmapped item its own single render."""
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    blocks = re.findall(r"```python\n(.*?)```", readme, flags=re.S)
    example = next(b for b in blocks if "whitted.renderer(" in b)
    check = """
        import numpy as _np
        _want, _ = whitted.host_radiance(render.setup, width=96, height=72, max_depth=3,
                                         spp=4)
        _peak = _np.abs(_want).max()
        _np.testing.assert_allclose(_np.asarray(radiance), _want, rtol=1e-5,
                                    atol=1e-5 * _peak)
        assert image.shape == (72, 96, 3)
        for _item, _params in zip(_np.asarray(images), variants):
            _single = _np.asarray(render(_params))
            _np.testing.assert_allclose(_item, _single, rtol=1e-5, atol=1e-5 * _peak)
        print("CHANGE", float(_np.abs(_np.asarray(images[1]) - _np.asarray(images[0])).max()
                              / _peak))
    """
    out = _python(example + textwrap.dedent(check))
    assert out.returncode == 0, out.stderr[-3000:]
    assert float(out.stdout.split("CHANGE")[1]) > 0.01, out.stdout  # A moved the image


# ------------------------------------------------------------------------ import order


def _python(code: str, **env) -> subprocess.CompletedProcess:
    """``code`` in a fresh interpreter without jrt's flags in XLA_FLAGS."""
    clean = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS",)}
    clean.update(env, PYTHONPATH=str(ROOT))
    return subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True,
                          text=True, env=clean, cwd=ROOT, timeout=300)


def test_importing_jrt_after_jax_started_warns_with_the_fix():
    out = _python("""
        import warnings
        import jax
        jax.devices()
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            import jrt
        for w in caught:
            print(w.category.__name__, "|", w.message)
    """, JRT_CPU_DEVICES="3")
    assert out.returncode == 0, out.stderr
    lines = [line for line in out.stdout.splitlines() if line.startswith("ImportOrderWarning")]
    assert len(lines) == 1, out.stdout
    text = lines[0]
    assert "has 1 device(s) where jrt asks for 3" in text
    assert "Import jrt before jax" in text
    assert "XLA_FLAGS='" in text and "--xla_force_host_platform_device_count=3" in text


def test_importing_jrt_after_jax_alone_is_silent_and_starts_nothing():
    out = _python("""
        import warnings
        warnings.simplefilter("error")
        import jax
        import jrt
        from jax._src import xla_bridge
        print("started", xla_bridge.backends_are_initialized())
        print("devices", jax.device_count())
    """, JRT_CPU_DEVICES="3")
    assert out.returncode == 0, out.stderr
    assert "started False" in out.stdout
    assert "devices 3" in out.stdout
