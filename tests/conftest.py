"""Shared fixtures: the camel (the packaged mesh, through jrt's resolver) and its structures,
built once."""

from __future__ import annotations

import atexit
import contextlib
import fcntl
import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import pytest

# One on-disk JAX compilation cache for the test session: the xdist workers and the
# processes the tests start (jrt study, the CLI) inherit it, so a program that several
# test files compile (brute force on the camel's rays, say) is compiled once. Set before
# JAX is imported; the process that creates the folder removes it at exit.
if "JAX_COMPILATION_CACHE_DIR" not in os.environ:
    _cache = tempfile.mkdtemp(prefix="jrt-tests-jax-cache-")
    os.environ["JAX_COMPILATION_CACHE_DIR"] = _cache
    atexit.register(shutil.rmtree, _cache, ignore_errors=True)
# One folder for what the whole session makes once and several files read (the quick
# study), shared by the xdist workers the same way.
if "JRT_TEST_SESSION_DIR" not in os.environ:
    _session = tempfile.mkdtemp(prefix="jrt-tests-session-")
    os.environ["JRT_TEST_SESSION_DIR"] = _session
    atexit.register(shutil.rmtree, _session, ignore_errors=True)

import accel
import jrt  # (XLA flags before JAX starts)
from jrt.data import mesh_path
from jrt.mesh import load_mesh
from jrt.raysets import camera_set, incoherent_set
from jrt.trace import as_numpy

#: The test files that take longest (minutes of a worker each), run first: xdist hands
#: files (--dist loadfile --no-loadscope-reorder) to its workers in collection order, so a
#: long file collected last kept one worker busy for minutes after the other had finished.
SLOW_FILES_FIRST = ("test_study.py", "test_structures.py", "test_bvh_traversal.py",
                    "test_octree.py")
#: The files that read the quick study's results (:func:`quick_study`), run last: by the
#: time the other worker reaches them, the study (test_study.py, first) has finished. A
#: reader collected earlier held its worker idle on the study's lock (test_bench.py's
#: first test waited 191 s of a 22 min run).
READERS_LAST = ("test_bench.py", "test_stability.py", "test_work_precision.py",
                "test_inverse.py")

#: The fast tier (``pytest -m "not slow"``, about two minutes on 2 cores): the modules
#: that compile no traversal of a real mesh and render nothing. Every test of the other
#: files is marked ``slow`` here; the full suite (CI's, the README's) runs them all.
FAST_FILES = frozenset({
    "test_kernels.py", "test_optics.py", "test_spectral.py", "test_normals.py",
    "test_camera.py", "test_mesh.py", "test_data.py", "test_scene.py", "test_report.py",
    "test_architecture.py", "test_registry.py", "test_build_threads.py",
})


def pytest_collection_modifyitems(session, config, items):
    def rank(item):
        name = item.path.name
        if name in READERS_LAST:
            return len(SLOW_FILES_FIRST) + 1
        return SLOW_FILES_FIRST.index(name) if name in SLOW_FILES_FIRST else len(
            SLOW_FILES_FIRST)

    for item in items:
        if item.path.name not in FAST_FILES:
            item.add_marker(pytest.mark.slow)
    items.sort(key=rank)  # stable: each file keeps its own order


#: Rays of each camel set that every structure's tests trace against brute force.
CAMEL_RAYS = 20_000


@pytest.fixture(scope="session")
def camel():
    return load_mesh(mesh_path("camel"))


@pytest.fixture(scope="session")
def camel19k():
    """The 19k-triangle camel: the far-away, scaled and multi-mesh tests' smaller mesh."""
    return load_mesh(mesh_path("camel-19k"))


@pytest.fixture(scope="session")
def camel19k_api_rays(camel19k):
    """1,100 incoherent rays of the 19k camel (about 40 % hit; not a size bucket, so 1,536
    are traced), a third of them stopped at a finite tmax: the API and x64 tests' rays."""
    origins, directions = incoherent_set(camel19k.vertices, 1100, seed=3)
    rng = np.random.default_rng(3)
    tmax = np.where(rng.random(1100) < 1 / 3, np.float32(0.8 * camel19k.diagonal), np.inf)
    return origins, directions, tmax.astype(np.float32)


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


@contextlib.contextmanager
def session_lock(path: Path):
    """Held by one xdist worker at a time: an exclusive file lock on ``path``."""
    with open(path, "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)


def session_shared(name: str, compute):
    """``compute()`` (a dict of NumPy arrays) once per test session, shared by the xdist
    workers through the session folder: the first to ask computes it under a file lock and
    writes it there, the others wait on the lock and read it back."""
    folder = Path(os.environ["JRT_TEST_SESSION_DIR"]) / "shared"
    folder.mkdir(exist_ok=True)
    path = folder / f"{name}.npz"
    with session_lock(folder / f"{name}.lock"):
        if not path.exists():
            with open(folder / f"{name}.tmp.npz", "wb") as f:
                np.savez(f, **compute())
            os.replace(folder / f"{name}.tmp.npz", path)
        with np.load(path) as data:
            return {key: data[key] for key in data.files}


@pytest.fixture(scope="session")
def brute_hits(camel_brute, camel_rays):
    """Brute force's closest hits per (kernel, ray set), computed once per test session
    when first asked (each costs 20k x 69k triangle tests; :func:`session_shared`)."""
    cache = {}

    def get(kernel, ray_set):
        if (kernel, ray_set) not in cache:
            origins, directions = camel_rays[ray_set]
            cache[kernel, ray_set] = session_shared(
                f"brute-hits-{kernel}-{ray_set}", lambda: as_numpy(
                    jrt.closest_hit(camel_brute, origins, directions, kernel=kernel)))
        return cache[kernel, ray_set]

    return get


#: The quick study's structures, scenes and command line (after ``jrt``): one structure,
#: brute force and one scene besides the camel keep it to a few minutes; every structure
#: and scene has its own tests in the suites'.
QUICK_STUDY_STRUCTURES = ("bvh",)
QUICK_STUDY_SCENES = ("stadium",)
QUICK_STUDY = ("study", "--quick", "--structures", ",".join(QUICK_STUDY_STRUCTURES),
               "--scenes", ",".join(QUICK_STUDY_SCENES))


@pytest.fixture(scope="session")
def quick_study_structures():
    """The structures the quick study (:func:`quick_study`) benchmarks, in its order."""
    return list(QUICK_STUDY_STRUCTURES)


@pytest.fixture(scope="session")
def quick_study():
    """``jrt study --quick --structures bvh``, as a user runs it (a process of its own),
    once per test session: ``(folder, printed)``, its output folder and what it printed.

    The xdist workers share it through the session folder: the first to ask runs it under
    a file lock, the others wait on the lock and read it. A failed run is recorded there
    too, so that every reader fails with its error instead of running it again."""
    root = Path(os.environ["JRT_TEST_SESSION_DIR"])
    out, record = root / "quick-study" / "camel", root / "quick-study.json"
    with session_lock(root / "quick-study.lock"):
        if not record.exists():
            run = subprocess.run(
                [sys.executable, "-c", "import sys; from jrt.cli import main; sys.exit(main())",
                 *QUICK_STUDY, "-o", str(out)],
                cwd=Path(__file__).resolve().parents[1], capture_output=True, text=True,
                timeout=1200)
            record.write_text(json.dumps({"returncode": run.returncode,
                                          "stdout": run.stdout, "stderr": run.stderr}))
        done = json.loads(record.read_text())
    assert done["returncode"] == 0, done["stderr"][-3000:]
    return out, done["stdout"]
