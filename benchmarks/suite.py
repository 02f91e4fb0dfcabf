"""The benchmark suite: every structure on the camel, side by side with Embree, as JSON.

    python -m benchmarks [--quick] [-o out/bench.json] [--structures bvh,grid]
        [--device cpu|gpu] [--mesh camel|camel-19k|PATH] [--camera-size 1024] ...

One run measures, in this order, and writes one record per measurement under
``"records"`` (see ``benchmarks.schema`` for the layout, checked before writing):

- ``build``: every structure's build time (median, min, max of ``--builds``) with its
  statistics (nodes or cells, leaves, depth, references per leaf, bytes, SAH cost).
- ``trace`` and ``peer``: five ray sets, traced by every structure and by Embree
  (embreex, robust mode, one Python thread per core, in this same process): **camera**
  rays (``--camera-size``², a 3/4 view whose framing is fitted so that the mesh fills the
  frame), and ``--rays`` each of **shadow** rays (any-hit, from the camera hits that face
  the lamp ``jrt.render.default_lamp``, toward it), **reflected** and **refracted** rays
  (the glass camel's secondary rays at the camera hits, n = 1.5, through ``jrt.optics``)
  and **incoherent** rays (``jrt.raysets.incoherent_set``). Derived rays start a small
  offset off the surface along the geometric normal; they take the camera hits in raster
  order (evenly spaced ones, or repeated up to ``--rays``), so that sets of one query share
  one shape, and one compiled query (a compile costs seconds here). jrt's first call
  (compile and run) is recorded apart; rates are the median, min and max of ``--repeats``
  warm calls (``jax.block_until_ready``; fewer, at least one, once they have taken
  :data:`TRACE_BUDGET_SECONDS`: a BSP tree on the slivers takes 10-25 s a call), and
  every row carries its ratio to Embree's median rate on the same rays. Per ray: traversal
  steps, triangle tests, leaves (mean, p95, max), from a separate run with the engine's
  counters. trimesh's rtree intersector runs on ``--trimesh-rays`` of each set (one call,
  one thread) when ``rtree`` is installed; Open3D and Mitsuba 3 (llvm) when importable.
- ``correctness``: every structure's hits on ``--brute-rays`` distinct rays of each set
  (all of them, some repeated, when a set has fewer) against brute force (same kernel:
  triangle, t, u, v bit for bit; ``occluded`` for shadow rays), and, for orientation,
  against Embree's triangles on the whole set.
- ``scaling``: the camel ladder 19k, 69k, 276k, 1.1M triangles (the last two by libigl's
  ``upsample``; ``--scaling`` meshes of it): build time and camera-ray Mrays/s against N,
  with fitted exponents; Embree on the same rays for the ratio.
- ``cost_model``: per structure, wall time per ray ~ C_0 + C_TS x steps + C_IT x tests
  fitted over the ray sets (Havran & Purgathofer 2003, "On comparing ray shooting
  algorithms"), by non-negative least squares on relative errors; C_TS, C_IT and C_0 in
  ns of wall time with all devices working.

Ratios to Embree measured in the same run are the figures to quote: absolute times drift
on a shared machine. ``--quick`` is CI's smoke test (the 19k camel, 64² rays a set, 2
repeats, scaling over 19k and 69k).

The other engines (Embree, trimesh, Open3D, Mitsuba) and their records are in
``benchmarks.peers``. This file is longer than ~800 lines because it holds the run and the
builders of every record kind the run writes (build, trace, heatmap, correctness, scaling,
cost model), which ``benchmarks.schema`` checks together and ``tests/test_report.py``
calls one by one.
"""

from __future__ import annotations

import argparse
import datetime
import importlib
import importlib.metadata
import importlib.util
import math
import os
import platform
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm.auto import tqdm

import accel
import jrt  # noqa: F401  (XLA flags before JAX starts its backend)
import jrt.data
import jrt.raysets
from accel.threads import build_threads
from benchmarks.build_scaling import build_times, fit_exponent, ns_per_n_log2_n, subdivide
from benchmarks.common import cost_model, jsonable, rates, summary, time_calls, write_record
from benchmarks.peers import (
    EmbreePeer,
    mitsuba_rows,
    open3d_rows,
    peer_row,
    ray_subset,
    trimesh_rows,
)
from benchmarks.structures import ENGINE_STRUCTURES, structure_names
from benchmarks.trimesh_interface import interface_records
from jrt.interaction import face_forward, surface_interaction
from jrt.scenes import GENERATED_LABELS, SCENES, SIZES, parse_label, scene_label, scene_mesh

PROJECT_ROOT = Path(__file__).resolve().parents[1]

#: Defaults of a full run and of ``--quick``; any option given on the command line wins.
DEFAULTS = {
    "full": {"camera_size": 1024, "rays": 2**18, "builds": 5, "repeats": 5, "brute_rays": 4096,
             "trimesh_rays": 256, "scaling": 4, "scaling_builds": 1, "scaling_repeats": 3,
             "turntable_frames": 24, "interface_rays": 65536},
    "quick": {"camera_size": 64, "rays": 4096, "builds": 2, "repeats": 2, "brute_rays": 4096,
              "trimesh_rays": 32, "scaling": 2, "scaling_builds": 1, "scaling_repeats": 2,
              "turntable_frames": 8, "interface_rays": 512},
}
#: The ray sets, in the order they are traced, and their query.
SETS = {"camera": "closest", "shadow": "occluded", "reflected": "closest",
        "refracted": "closest", "incoherent": "closest"}
GLASS_INDEX = 1.5  # the glass camel's index (seed: n = 1.5 for glass)
OFFSET = 1e-4  # origin offset of derived rays, in units of the bounding-box diagonal
FILL = 0.95  # the camera framing puts the mesh's farthest vertex at 95 % of the half-frame
DEVICE_PLATFORMS = {"cpu": ("cpu",), "gpu": ("gpu", "cuda", "rocm")}


class BenchError(ValueError):
    """A suite option that cannot be honoured (the message says what is allowed)."""


# --- Command line ---------------------------------------------------------------------------


def _positive(value: str) -> int:
    number = int(value)
    if number < 1:
        raise argparse.ArgumentTypeError(f"must be a positive integer, got {value}")
    return number


def _non_negative(value: str) -> int:
    number = int(value)
    if number < 0:
        raise argparse.ArgumentTypeError(f"must be a non-negative integer, got {value}")
    return number


#: The command name in usage and errors when run as ``python -m benchmarks`` (``jrt bench``
#: passes its own).
PROG = "python -m benchmarks"
#: Where the results go by default (relative to the working directory).
DEFAULT_OUTPUT = "out/bench.json"


def build_parser(add_help: bool = True, prog: str = PROG) -> argparse.ArgumentParser:
    """The suite's options (``jrt bench`` reuses them: pass ``add_help=False`` for parents)."""
    full, quick = DEFAULTS["full"], DEFAULTS["quick"]

    def default(key):
        return f"default {full[key]}, --quick {quick[key]}"

    parser = argparse.ArgumentParser(
        prog=prog, add_help=add_help,
        description="Every acceleration structure on the camel beside Embree: build, trace "
                    "(camera, shadow, reflected, refracted, incoherent rays), correctness, "
                    "scaling and cost model, written as JSON.")
    parser.add_argument("-o", "--output", default=DEFAULT_OUTPUT, metavar="JSON",
                        help=f"the results' JSON file (default {DEFAULT_OUTPUT}, in the "
                             "working directory)")
    parser.add_argument("--quick", action="store_true",
                        help="CI's smoke test: the 19k camel, 64x64 rays a set, 2 repeats, "
                             "two scaling meshes")
    parser.add_argument("--structures", type=structure_names, default=list(ENGINE_STRUCTURES),
                        help=f"comma-separated, from {','.join(ENGINE_STRUCTURES)} "
                             "(default all)")
    parser.add_argument("--device", choices=tuple(DEVICE_PLATFORMS), default=None,
                        help="the JAX device to trace on (default: JAX's default backend)")
    where = parser.add_mutually_exclusive_group()
    where.add_argument("--mesh", default=None,
                       help="camel, camel-19k or a mesh file (default camel; --quick "
                            "camel-19k when present)")
    where.add_argument("--scene", dest="suite_scene", default=None, choices=SCENES,
                       metavar="NAME", help="a scene of the study's suite (jrt.scenes: "
                       f"{', '.join(SCENES)}); --quick takes its small size")
    parser.add_argument("--scene-size", choices=SIZES, default=None,
                        help="the size of --scene's mesh (default full, --quick small)")
    parser.add_argument("--kernel", default="watertight", choices=tuple(jrt.KERNELS))
    parser.add_argument("--camera-size", type=_positive, default=None,
                        help=f"camera image side in pixels ({default('camera_size')})")
    parser.add_argument("--rays", type=_positive, default=None,
                        help=f"rays of each other set: shadow, reflected, refracted, "
                             f"incoherent ({default('rays')})")
    parser.add_argument("--builds", type=_positive, default=None,
                        help=f"builds per structure ({default('builds')})")
    parser.add_argument("--repeats", type=_positive, default=None,
                        help=f"warm timed calls per structure and set ({default('repeats')})")
    parser.add_argument("--brute-rays", type=_positive, default=None,
                        help=f"rays of each set checked against brute force "
                             f"({default('brute_rays')})")
    parser.add_argument("--trimesh-rays", type=_non_negative, default=None,
                        help=f"rays of each set for trimesh's intersector, 0 to skip "
                             f"({default('trimesh_rays')})")
    parser.add_argument("--scaling", type=_non_negative, default=None,
                        help=f"meshes of the scaling ladder 19k, 69k, 276k, 1.1M, 0 to skip "
                             f"({default('scaling')})")
    parser.add_argument("--scaling-builds", type=_positive, default=None,
                        help=f"builds per structure of each scaling mesh other than the "
                             f"main one ({default('scaling_builds')})")
    parser.add_argument("--scaling-repeats", type=_positive, default=None,
                        help=f"warm timed calls on each scaling mesh "
                             f"({default('scaling_repeats')})")
    parser.add_argument("--turntable-frames", type=_non_negative, default=None,
                        help=f"frames of the glass camel's turntable rendered batched "
                             f"(jrt.batch) and as a loop of single renders, images/s of "
                             f"both (benchmarks/turntable.py), 0 to skip "
                             f"({default('turntable_frames')})")
    parser.add_argument("--interface-rays", type=_non_negative, default=None,
                        help=f"rays and points of trimesh's ray interface through jrt, "
                             f"trimesh's Embree intersector and trimesh's own, on the mesh "
                             f"and an icosphere (benchmarks/trimesh_interface.py), 0 to skip "
                             f"({default('interface_rays')})")
    parser.add_argument("--seed", type=int, default=0, help="incoherent rays' seed")
    parser.add_argument("--progress", action=argparse.BooleanOptionalAction, default=True,
                        help="progress bars (default on)")
    return parser


def main(argv=None, prog: str = PROG) -> dict:
    """``python -m benchmarks`` (``jrt bench``): parse, run, write the JSON; returns the
    results. ``prog`` names the command in usage and errors."""
    parser = build_parser(prog=prog)
    args = parser.parse_args(argv)
    try:
        return run(args)
    except BenchError as exc:
        parser.exit(2, f"{parser.prog}: error: {exc}\n")


# --- Machine --------------------------------------------------------------------------------


def select_device(kind: str | None) -> list:
    """The JAX devices the engine will split rays over, after honouring ``--device``.

    ``cpu`` keeps JAX on its CPU backend (set before the backend starts, so even a machine
    with a GPU traces on the cores); ``gpu`` requires a GPU backend. A device that is
    absent is an error naming the ones present.
    """
    import jax
    from jax._src import xla_bridge

    if kind is None:
        return list(jax.local_devices())
    if kind not in DEVICE_PLATFORMS:
        raise BenchError(f"unknown device {kind!r}; allowed: {', '.join(DEVICE_PLATFORMS)}")
    if kind == "cpu" and not xla_bridge.backends_are_initialized():
        jax.config.update("jax_platforms", "cpu")
    try:
        jax.devices(kind)
    except RuntimeError:
        present = ", ".join(f"{d.platform}:{d.id} ({d.device_kind})" for d in jax.devices())
        raise BenchError(f"no {kind} device: JAX sees {present}; pass another --device "
                         "or leave it out") from None
    if jax.default_backend() not in DEVICE_PLATFORMS[kind]:
        raise BenchError(
            f"JAX's backend already started on {jax.default_backend()} in this process, and "
            f"the traversal engine uses the default backend's devices; run the suite in a "
            f"fresh process to trace on {kind}")
    return list(jax.local_devices())


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.lower().startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _version(distribution: str, module: str | None = None) -> str | None:
    try:
        return importlib.metadata.version(distribution)
    except importlib.metadata.PackageNotFoundError:
        pass
    try:
        return str(importlib.import_module(module or distribution).__version__)
    except (ImportError, AttributeError):
        return None


def git_commit() -> str | None:
    """``git rev-parse HEAD`` of the project (read-only), or None outside a repository."""
    try:
        out = subprocess.run(["git", "rev-parse", "HEAD"], cwd=PROJECT_ROOT, text=True,
                             capture_output=True, timeout=10, check=False)
    except (OSError, subprocess.SubprocessError):
        return None
    commit = out.stdout.strip()
    return commit if out.returncode == 0 and commit else None


def machine_record(devices, requested: str | None) -> dict:
    """CPU, cores, the builders' threads (``accel.threads``), JAX devices, library versions,
    git commit and date."""
    versions = {name: _version(dist, module) for name, dist, module in (
        ("jrt", "jrt", None), ("jax", "jax", None), ("jaxlib", "jaxlib", None),
        ("numpy", "numpy", None), ("embreex", "embreex", None), ("trimesh", "trimesh", None),
        ("igl", "libigl", "igl"), ("colour", "colour-science", "colour"),
        ("tqdm", "tqdm", None), ("rtree", "rtree", None))}
    try:
        affinity = len(os.sched_getaffinity(0))
    except AttributeError:
        affinity = os.cpu_count() or 1
    return {
        "cpu": _cpu_model(), "cores": os.cpu_count() or 1, "cores_usable": affinity,
        "build_threads": build_threads(),
        "os": platform.platform(), "python": platform.python_version(),
        "device": {"requested": requested, "platform": devices[0].platform,
                   "kind": devices[0].device_kind, "count": len(devices),
                   "devices": [str(d) for d in devices]},
        "xla_flags": os.environ.get("XLA_FLAGS", ""),
        "versions": versions, "git_commit": git_commit(),
        "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
    }


# --- Rays -----------------------------------------------------------------------------------


@dataclass
class RaySet:
    """One set of rays, float32 [N, 3] each, with the query it is traced with."""

    name: str
    query: str  # "closest" or "occluded"
    origins: np.ndarray
    directions: np.ndarray
    tmax: np.ndarray | None
    distinct: int  # its first ``distinct`` rays are distinct (the rest repeat them)
    note: str = ""

    @property
    def rays(self) -> int:
        return len(self.origins)


def fitted_camera(vertices, size: int, fill: float = FILL) -> jrt.Camera:
    """A square ``size``² 3/4 view (``jrt.frame_mesh``) whose mesh fills the frame.

    ``frame_mesh`` fits the bounding sphere; here its margin is scaled until the farthest
    vertex lies at ``fill`` of the half-frame (nothing is cut off).
    """
    v = np.asarray(vertices, np.float64)
    margin = 0.85
    for _ in range(6):
        camera = jrt.frame_mesh(v, width=size, height=size, margin=margin)
        eye, target = np.asarray(camera.eye), np.asarray(camera.target)
        forward = (target - eye) / np.linalg.norm(target - eye)
        right = np.cross(forward, camera.up)
        right /= np.linalg.norm(right)
        up = np.cross(right, forward)
        rel = v - eye
        depth = rel @ forward
        half = math.tan(math.radians(camera.vfov) / 2)
        extent = max(np.abs(rel @ right / depth).max(), np.abs(rel @ up / depth).max()) / half
        if abs(extent - fill) < 1e-3:
            break
        margin *= extent / fill
    return camera


def _unit(x):
    return x / np.linalg.norm(x, axis=1, keepdims=True)


def _take(indices: np.ndarray, n: int) -> np.ndarray:
    """``n`` of ``indices`` in their order: evenly spaced ones, or all repeated up to n."""
    if len(indices) >= n:
        return indices[np.floor(np.linspace(0, len(indices) - 1, n)).astype(np.int64)]
    return np.resize(indices, n)


def ray_sets(mesh, camera, embree, threads: int, seed: int, n: int) -> tuple[dict, dict]:
    """The five ray sets (name -> RaySet) and what they were derived from.

    Camera rays: one per pixel. The other sets have ``n`` rays each. Shadow and secondary
    rays start at the camera rays' closest hits (Embree's, so that the sets do not depend
    on the structures under test), taken in raster order: evenly spaced ones when there
    are more than ``n``, repeated when there are fewer.
    """
    o, d = (np.asarray(a) for a in jrt.camera_rays(camera))
    sets = {"camera": RaySet("camera", "closest", o, d, None, len(o))}
    hits = embree.closest_hit(o, d, threads=threads)
    hit = np.flatnonzero(hits["triangle"] >= 0)
    info = {"camera_hits": int(hit.size)}
    lamp = jrt.render.default_lamp(mesh, camera)
    info["lamp"] = lamp.tolist()
    if hit.size:
        # The hit points and geometric normals in float64 (NumPy arrays in, NumPy out), the
        # normal turned against the camera ray.
        incident = d[hit].astype(np.float64)
        surface = surface_interaction(
            mesh.vertices.astype(np.float64), mesh.faces, hits["triangle"][hit],
            hits["u"][hit].astype(np.float64), hits["v"][hit].astype(np.float64), incident)
        point = surface.point
        normal = face_forward(surface.geometric_normal, -incident)
        eps = OFFSET * mesh.diagonal
        to_lamp = lamp.astype(np.float64) - point
        dist = np.linalg.norm(to_lamp, axis=1)
        light = to_lamp / dist[:, None]
        lit = np.flatnonzero(np.sum(normal * light, axis=1) > 0)
        info["lit_hits"] = int(lit.size)
        if lit.size:
            idx = _take(lit, n)
            sets["shadow"] = RaySet(
                "shadow", "occluded", (point[idx] + eps * normal[idx]).astype(np.float32),
                light[idx].astype(np.float32), (dist[idx] - eps).astype(np.float32),
                len(np.unique(idx)), "from the lamp-facing camera hits toward the lamp, tmax = "
                               "the distance to it")
        if importlib.util.find_spec("jrt.optics") is not None:
            from jrt import optics

            idx = _take(np.arange(hit.size), n)
            l32, n32 = incident.astype(np.float32), normal.astype(np.float32)
            reflected = _unit(np.asarray(optics.reflect(l32, n32), np.float64))
            refracted, tir = optics.refract(l32, n32, 1.0, GLASS_INDEX)
            refracted = _unit(np.asarray(refracted, np.float64))
            info["total_internal_reflections"] = int(np.asarray(tir).sum())
            sets["reflected"] = RaySet(
                "reflected", "closest", (point + eps * normal)[idx].astype(np.float32),
                reflected[idx].astype(np.float32), None, len(np.unique(idx)),
                "jrt.optics.reflect at the camera hits")
            sets["refracted"] = RaySet(
                "refracted", "closest", (point - eps * normal)[idx].astype(np.float32),
                refracted[idx].astype(np.float32), None, len(np.unique(idx)),
                f"jrt.optics.refract at the camera hits, n = 1 -> {GLASS_INDEX}")
        else:
            info["secondary"] = "skipped: jrt.optics is not there"
    io, idir = jrt.raysets.incoherent_set(mesh.vertices, n, seed=seed)
    sets["incoherent"] = RaySet("incoherent", "closest", io, idir, None, n)
    return {k: sets[k] for k in SETS if k in sets}, info


# --- Measurements ---------------------------------------------------------------------------


def _first_stats(stats: dict, *keys):
    for key in keys:
        if key in stats:
            return stats[key]
    return None


def build_record(name: str, mesh_name: str, triangles: int, times, structure) -> dict:
    st = dict(structure.stats)
    return {
        "kind": "build", "structure": name, "mesh": mesh_name, "triangles": triangles,
        "repeats": times, "seconds": summary(times),
        "nodes": _first_stats(st, "nodes", "cells"), "leaves": st.get("leaves"),
        "depth": st.get("depth"),
        "references_per_leaf_mean": _first_stats(
            st, "references_per_leaf_mean", "triangles_per_leaf_mean"),
        "references_per_leaf_max": _first_stats(
            st, "references_per_leaf_max", "triangles_per_leaf_max"),
        "bytes": st.get("bytes", structure.nbytes), "sah_cost": st.get("sah_cost"),
        "stats": st,
    }


def _counter_summary(counts) -> dict:
    out = {}
    for key, values in counts._asdict().items():
        values = np.asarray(values)
        out[key] = {"mean": float(values.mean()), "p95": float(np.percentile(values, 95)),
                    "max": int(values.max())}
    return out


#: A structure's timed calls on one set stop once they have taken this long (seconds):
#: at that length one call's time varies by well under a percent (the BSP tree's on the
#: slivers, 0.1-0.6 % over three calls), and further calls only lengthen the run.
TRACE_BUDGET_SECONDS = 10.0


class Tracer:
    """Runs jrt's queries: one call, or the timed repeats of one structure on one set."""

    def __init__(self, kernel: str, repeats: int):
        self.kernel = kernel
        self.repeats = repeats

    def call(self, structure, arrays, query: str, counters: bool = False):
        import jax

        o, d, tmax = arrays
        if query == "occluded":
            out = jrt.occluded(structure, o, d, tmax=tmax, kernel=self.kernel, counters=counters)
        else:
            out = jrt.closest_hit(structure, o, d, kernel=self.kernel, tmax=tmax,
                                  counters=counters)
        return jax.block_until_ready(out)

    def measure(self, structure, arrays, query: str) -> dict:
        """The timed repeats (the first one's hits are kept), then the counters.

        The query was compiled before (:func:`first_calls`), so every repeat is warm.
        """
        kept = []

        def call():
            out = self.call(structure, arrays, query)
            if not kept:
                kept.append(out)

        times = time_calls(call, self.repeats, TRACE_BUDGET_SECONDS)
        first = kept[0]
        _, counts = self.call(structure, arrays, query, counters=True)
        if query == "occluded":
            result = {"occluded": np.asarray(first)}
        else:
            result = {k: np.asarray(v) for k, v in first._asdict().items()}
        return {"result": result, "times": times, "counters": _counter_summary(counts),
                "counts": counts}


#: Heat maps of the per-ray counters on the camera set have at most this many cells a side.
HEATMAP_SIDE = 128


def heatmap_record(name: str, counts, width: int, height: int,
                   side: int = HEATMAP_SIDE) -> dict:
    """Per-pixel cost of the camera rays (traversal steps, triangle tests) as images: the
    counters of the pixels (raster order, one ray each) averaged over square blocks so
    that the larger side has at most ``side`` cells."""
    block = max(1, math.ceil(max(width, height) / side))
    h, w = height // block, width // block
    out = {"kind": "heatmap", "structure": name, "set": "camera", "width": w, "height": h,
           "block": block}
    for key in ("steps", "tests"):
        image = np.asarray(getattr(counts, key), np.float64).reshape(height, width)
        image = image[:h * block, :w * block].reshape(h, block, w, block).mean(axis=(1, 3))
        out[key] = np.round(image, 1).tolist()
    return out


def first_calls(tasks, quiet: bool, desc: str) -> dict:
    """Run each ``(key, fn)`` once, one after the other; key -> wall seconds.

    These are the first calls, which compile (XLA compiles on one thread, and two compiles
    side by side in threads took as long as one after the other on this machine).
    """
    out = {}
    for key, fn in tqdm(tasks, desc=desc, disable=quiet, leave=False):
        start = time.perf_counter()
        fn()
        out[key] = time.perf_counter() - start
    return out


def _device_arrays(ray_set: RaySet):
    import jax

    tmax = None if ray_set.tmax is None else jax.device_put(ray_set.tmax)
    return jax.device_put(ray_set.origins), jax.device_put(ray_set.directions), tmax


def _brute_reference(brute, ray_set: RaySet, idx, kernel: str) -> dict:
    o, d = ray_set.origins[idx], ray_set.directions[idx]
    if ray_set.query == "occluded":
        return {"occluded": np.asarray(jrt.occluded(brute, o, d, tmax=ray_set.tmax[idx],
                                                    kernel=kernel))}
    return {k: np.asarray(v) for k, v in jrt.closest_hit(brute, o, d, kernel=kernel)
            ._asdict().items()}


def correctness_record(name, ray_set, idx, ours, reference, embree_result,
                       triangles=None) -> dict:
    """The structure's answers on the rays ``idx`` against brute force's (``reference``),
    field by field, and against Embree's on the whole set.

    Where they differ and ``triangles`` (float64 [T, 3, 3], the mesh's faces) is given, the
    float64 oracle (``benchmarks.stability.float64_oracle``) decides which of the two is
    right: brute force evaluates every triangle for every ray, and a float32 kernel
    evaluated on a triangle a few ulps wide seen from far away (the stadium's camel) can
    report a false hit that the structures, whose boxes cull that triangle, never see.
    """
    fields = {}
    differ = np.zeros(len(idx), bool)
    for key, ref in reference.items():
        mine = ours[key][idx]
        bad = mine != ref
        fields[key] = int(bad.sum())
        differ |= bad
    if ray_set.query == "occluded":
        reference_hits = int(reference["occluded"].sum())
        embree_differ = ours["occluded"] != embree_result
    else:
        reference_hits = int((reference["triangle"] >= 0).sum())
        embree_differ = ours["triangle"] != embree_result["triangle"]
    record = {"kind": "correctness", "structure": name, "set": ray_set.name,
              "query": ray_set.query, "reference": "brute", "rays": len(idx),
              "reference_hits": reference_hits, "mismatches": int(differ.sum()),
              "mismatches_by_field": fields, "embree_rays": ray_set.rays,
              "embree_disagreements": int(embree_differ.sum()),
              "note": "bit for bit against brute force with the same kernel; Embree uses its "
                      "own kernel, so a few disagreements on edges are expected"}
    if differ.any() and triangles is not None:
        from benchmarks.stability.float64_oracle import oracle

        rows = np.asarray(idx)[differ]
        tmax = None if ray_set.tmax is None else np.asarray(ray_set.tmax)[rows]
        _, row_ref = oracle(triangles, ray_set.origins[rows], ray_set.directions[rows], tmax)
        if ray_set.query == "occluded":
            key, want = "occluded", row_ref >= 0
        else:
            key, want = "triangle", row_ref
        mine_ok = ours[key][rows] == want
        brute_ok = reference[key][differ] == want
        record["oracle"] = {"rays": int(differ.sum()),
                            "structure_right": int((mine_ok & ~brute_ok).sum()),
                            "brute_right": int((brute_ok & ~mine_ok).sum())}
    return record


def oracle_text(check: dict) -> str:
    """What the float64 oracle said of a correctness record's mismatches, for the log."""
    o = check.get("oracle")
    if not o:
        return ""
    return (f" (float64 oracle: {check['structure']} right on {o['structure_right']}, brute "
            f"force on {o['brute_right']})")


def scaling_ladder(mesh, mesh_label: str, count: int) -> list[tuple[str, object]]:
    """(label, mesh) of the scaling meshes: camel-19k, camel, camel x4, camel x16.

    A mesh other than the camels gives itself and its subdivisions. Meshes are loaded or
    subdivided here, in the ladder's order, and only as many as asked for.
    """
    if count == 0:
        return []
    camels = {"camel-19k", "camel"}
    ladder = []
    if mesh_label in camels:
        for label in ("camel-19k", "camel"):
            if jrt.data.has_camel(label):
                ladder.append((label, lambda label=label: jrt.load_mesh(jrt.camel_path(label))))
        base_label, base = "camel", lambda: jrt.load_mesh(jrt.camel_path("camel"))
    else:
        ladder.append((mesh_label, lambda: mesh))
        base_label, base = mesh_label, lambda: mesh
    for level in (1, 2, 3):
        def upsampled(level=level):
            b = base()
            v, f = subdivide(b.vertices, b.faces, level)[-1]
            return jrt.mesh_from_arrays(v.astype(np.float32), f.astype(np.int32),
                                        name=f"{base_label} x{4 ** level}")
        ladder.append((f"{base_label} x{4 ** level}", upsampled))
    return ladder[:count]


# --- The run --------------------------------------------------------------------------------


def _resolve(args) -> dict:
    mode = "quick" if args.quick else "full"
    params = {k: getattr(args, k) if getattr(args, k, None) is not None else v
              for k, v in DEFAULTS[mode].items()}
    mesh_arg = args.mesh
    scene = getattr(args, "suite_scene", None)
    asked = getattr(args, "scene_size", None)
    if asked and scene is None:
        raise BenchError("--scene-size applies to --scene NAME (a scene of jrt.scenes)")
    if scene is not None:  # labelled "stadium", or "stadium-small" where it has two sizes
        mesh_arg = scene_label(scene, asked or ("small" if args.quick else "full"))
    elif mesh_arg is None:
        mesh_arg = "camel-19k" if args.quick and jrt.data.has_camel("camel-19k") else "camel"
    params["mesh"] = mesh_arg
    params["scene"] = scene
    return params


def _load(mesh_arg: str):
    if mesh_arg in GENERATED_LABELS:  # a generated scene of jrt.scenes, at either size
        name, size = parse_label(mesh_arg)
        return scene_mesh(name, size=size)
    try:
        if mesh_arg in jrt.data.MESHES:
            return jrt.load_mesh(jrt.camel_path(mesh_arg))
        return jrt.load_mesh(mesh_arg)
    except (FileNotFoundError, jrt.MeshError) as exc:
        raise BenchError(str(exc)) from None


def run(args) -> dict:
    """Run the suite with parsed options (``build_parser().parse_args(...)``)."""
    wall_start = time.perf_counter()
    devices = select_device(args.device)
    import jax

    import jrt.render  # noqa: F401  (default_lamp)

    p = _resolve(args)
    quiet = not args.progress

    def log(message):
        tqdm.write(message, file=sys.stdout)
        sys.stdout.flush()

    mesh = _load(p["mesh"])
    names = list(args.structures)
    threads = os.cpu_count() or 1
    machine = machine_record(devices, args.device)
    log(f"{mesh.summary()} | {machine['device']['count']} {machine['device']['platform']} "
        f"device(s), {machine['cores']} cores | structures {', '.join(names)}")
    records, notes = [], []

    # Builds.
    built = {}
    for name in tqdm(names, desc="build", disable=quiet, leave=False):
        times, structure = build_times(name, mesh.vertices, mesh.faces, p["builds"])
        built[name] = structure
        rec = build_record(name, p["mesh"], len(mesh.faces), times, structure)
        records.append(rec)
        log(f"build {name:<7} {rec['seconds']['median']:7.3f} s (min {rec['seconds']['min']:.3f}"
            f", max {rec['seconds']['max']:.3f}), {rec['nodes']:,} nodes, {rec['leaves']:,} "
            f"leaves, depth {rec['depth']}, {rec['bytes'] / 2**20:.1f} MiB, "
            f"SAH {rec['sah_cost']:.3g}")

    # Rays and Embree.
    camera = fitted_camera(mesh.vertices, p["camera_size"])
    try:
        embree = EmbreePeer(mesh.vertices, mesh.faces)
    except ImportError as exc:
        raise BenchError(f"the suite measures against Embree and needs embreex "
                         f"(pip install -e '.[dev]'): {exc}") from None
    sets, derived = ray_sets(mesh, camera, embree, threads, args.seed, p["rays"])
    if "secondary" in derived:
        notes.append(f"reflected and refracted rays {derived['secondary']}")
    if "shadow" not in sets:
        notes.append("no shadow rays: no camera hit faces the lamp")
    log("ray sets: " + ", ".join(f"{s.name} ({s.query}, {s.rays:,} rays, {s.distinct:,} "
                                 "distinct)" for s in sets.values()))
    arrays = {name: _device_arrays(s) for name, s in sets.items()}

    # First calls (compile): per structure, each query and number of rays, with and
    # without counters, and brute force on the correctness subsets; each on the first
    # set of its kind (the others share the compiled code).
    brute = accel.build("brute", mesh.vertices, mesh.faces)
    triangles = np.asarray(mesh.vertices, np.float64)[np.asarray(mesh.faces)]  # the oracle's
    tracer = Tracer(args.kernel, p["repeats"])
    subsets = {name: ray_subset(s, p["brute_rays"], args.seed + 1, pad=True)
               for name, s in sets.items()}
    first_set = {}
    for s in sets.values():
        first_set.setdefault((s.query, s.rays), s.name)
    tasks = []
    for (query, _), set_name in first_set.items():
        for name in names:
            for counters in (False, True):
                tasks.append(((name, set_name, counters), lambda s=built[name],
                              a=arrays[set_name], q=query, c=counters: tracer.call(s, a, q, c)))
    brute_first = {}  # the first calls' answers: the references of those sets
    for query in dict.fromkeys(s.query for s in sets.values()):
        s = next(s for s in sets.values() if s.query == query)
        tasks.append((("brute", s.name, False), lambda s=s: brute_first.setdefault(
            s.name, _brute_reference(brute, s, subsets[s.name], args.kernel))))
    first = first_calls(tasks, quiet, "compile")
    log("first calls (compile and run): " + ", ".join(
        f"{k[0]} {sets[k[1]].query} "
        f"{p['brute_rays'] if k[0] == 'brute' else sets[k[1]].rays:,}"
        f"{' +counters' if k[2] else ''} {v:.1f} s" for k, v in first.items()))

    # Traces, Embree, correctness.
    traces = {name: [] for name in names}
    embree_rates = {}
    bar = tqdm(total=len(sets) * len(names), desc="trace", disable=quiet, leave=False)
    for ray_set in sets.values():
        emb = embree.query_call(ray_set, threads)
        embree_result = emb()  # warm-up, and the hits to compare with
        seconds = time_calls(emb, p["repeats"])
        row = peer_row("embree", ray_set, seconds, None, threads=threads,
                       note="embreex robust mode, one Python thread per core")
        embree_rates[ray_set.name] = row["mrays_per_s"]["median"]
        row["ratio_to_embree"] = 1.0
        records.append(row)
        log(f"{ray_set.name:<10} embree   {row['mrays_per_s']['median']:8.3f} Mrays/s")
        idx = subsets[ray_set.name]
        reference = brute_first.pop(ray_set.name, None)
        if reference is None:
            reference = _brute_reference(brute, ray_set, idx, args.kernel)
        for name in names:
            m = tracer.measure(built[name], arrays[ray_set.name], ray_set.query)
            rate = rates(ray_set.rays, m["times"])
            result = m["result"]
            hits = (int(result["occluded"].sum()) if ray_set.query == "occluded"
                    else int((result["triangle"] >= 0).sum()))
            first_of = first_set[(ray_set.query, ray_set.rays)]
            rec = {"kind": "trace", "structure": name, "set": ray_set.name,
                   "query": ray_set.query, "rays": ray_set.rays,
                   "distinct_rays": ray_set.distinct, "hits": hits,
                   "first_call_set": first_of,
                   "first_call_seconds": first[(name, first_of, False)],
                   "counters_first_call_seconds": first[(name, first_of, True)],
                   "repeats": m["times"], "seconds": summary(m["times"]),
                   "mrays_per_s": rate, "embree_mrays_per_s": embree_rates[ray_set.name],
                   "ratio_to_embree": rate["median"] / embree_rates[ray_set.name],
                   "counters": m["counters"]}
            records.append(rec)
            traces[name].append(rec)
            if ray_set.name == "camera":
                records.append(heatmap_record(name, m["counts"], camera.width, camera.height))
            check = correctness_record(name, ray_set, idx, result, reference, embree_result,
                                       triangles)
            records.append(check)
            c = rec["counters"]
            log(f"{ray_set.name:<10} {name:<8} {rate['median']:8.3f} Mrays/s "
                f"(x{rec['ratio_to_embree']:.3f} Embree), steps {c['steps']['mean']:.1f}, "
                f"tests {c['tests']['mean']:.1f}, leaves {c['leaves']['mean']:.1f}; "
                f"{check['mismatches']} mismatches of {check['rays']:,} vs brute"
                f"{oracle_text(check)}")
            bar.update()
    bar.close()
    # Compile time apart: the first call less a warm call on the same set.
    for name in names:
        for rec in traces[name]:
            warm = next(t for t in traces[name] if t["set"] == rec["first_call_set"])
            rec["compile_seconds"] = max(rec["first_call_seconds"] - warm["seconds"]["median"],
                                         0.0)
    del arrays

    # Other peers.
    for rows in (trimesh_rows(mesh, sets, embree_rates, p["trimesh_rays"], args.seed + 2, log),
                 open3d_rows(mesh, sets, embree_rates, p["repeats"]),
                 mitsuba_rows(mesh, sets, embree_rates, p["repeats"])):
        records.extend(rows)
        for r in rows:
            if r["status"] == "ok":
                log(f"{r['set']:<10} {r['peer']:<8} {r['mrays_per_s']['median']:10.6f} Mrays/s "
                    f"(x{r['ratio_to_embree']:.6f} Embree) on {r['rays']:,} rays")
            else:
                log(f"{r['peer']}: {r['status']} ({r['note']})")

    # Scaling.
    records.extend(scaling_records(mesh, p, names, traces, records, tracer, threads,
                                   EmbreePeer, quiet, log))

    # Cost model.
    for name in names:
        rec = cost_model(name, traces[name])
        records.append(rec)
        log(f"cost model {name:<7} C_TS {rec['c_ts_ns']:.2f} ns, C_IT {rec['c_it_ns']:.2f} ns, "
            f"C_0 {rec['c_ray_ns']:.2f} ns, residual {rec['residual']:.1%}")

    # trimesh's ray interface: jrt's intersector, trimesh's Embree one and its own.
    if p["interface_rays"]:
        import trimesh

        for name, tm in ((p["mesh"], trimesh.Trimesh(mesh.vertices, mesh.faces,
                                                     process=False)), ("sphere", None)):
            records.extend(interface_records(
                name, p["interface_rays"], p["interface_rays"], max(p["trimesh_rays"], 1),
                p["repeats"], args.seed + 3, log, mesh=tm))

    # Batched renders: a turntable, batched against a loop of single renders.
    if p["turntable_frames"] and not jrt.data.has_camel("camel-19k"):
        notes.append("no turntable: it renders the glass camel on camel-19k, which was not "
                     "found (see jrt.camel_path)")
    elif p["turntable_frames"]:
        rec = turntable_record(args.quick, p["turntable_frames"])
        records.append(rec)
        log(f"turntable {rec['frames']} frames {rec['width']}x{rec['height']}: batched "
            f"{rec['batched_images_per_s']:.2f} images/s, loop "
            f"{rec['loop_images_per_s']:.2f} (same capacities "
            f"{rec['loop_same_capacities_images_per_s']:.2f}), x{rec['ratio']:.2f}")

    results = {
        "schema": "jrt-bench/1", "machine": machine,
        "parameters": {
            "quick": bool(args.quick), "mesh": p["mesh"], "scene": p["scene"],
            "mesh_summary": mesh.summary(),
            "triangles": len(mesh.faces), "structures": names, "kernel": args.kernel,
            "device": args.device, "camera": {
                "width": camera.width, "height": camera.height, "eye": camera.eye,
                "target": camera.target, "vfov": camera.vfov, "fill": FILL},
            "camera_rays": camera.num_rays, "rays": p["rays"], "sets": [
                {"name": s.name, "query": s.query, "rays": s.rays, "distinct_rays": s.distinct,
                 "note": s.note} for s in sets.values()],
            "derived_from": derived, "ray_offset": OFFSET * mesh.diagonal,
            "glass_index": GLASS_INDEX, "builds": p["builds"], "repeats": p["repeats"],
            "trace_budget_seconds": TRACE_BUDGET_SECONDS,
            "brute_rays": p["brute_rays"], "trimesh_rays": p["trimesh_rays"],
            "scaling_meshes": p["scaling"], "scaling_builds": p["scaling_builds"],
            "scaling_repeats": p["scaling_repeats"], "embree_threads": threads,
            "seed": args.seed, "turntable_frames": p["turntable_frames"],
            "interface_rays": p["interface_rays"],
            "jax_devices": len(jax.local_devices()),
        },
        "records": records, "notes": notes,
        "wall_seconds": time.perf_counter() - wall_start,
    }
    results = jsonable(results)
    from benchmarks.schema import validate

    validate(results)
    log(headline(results))
    write_record(results, args.output)
    log(f"suite: {results['wall_seconds']:.0f} s")
    return results


def turntable_record(quick: bool, frames: int) -> dict:
    """images/s of the glass camel's turntable (``benchmarks.turntable``), batched by
    ``jrt.batch.render_batch`` and as a Python loop of ``jrt.whitted`` renders."""
    from benchmarks import turntable

    doc = turntable.run(quick=quick, frames=frames)
    p = doc["parameters"]
    return {"kind": "turntable", "scene": p["scene"], "mesh": p["mesh"], "frames": p["frames"],
            "width": p["width"], "height": p["height"], "samples": p["samples"],
            "max_depth": p["max_depth"],
            "batched_images_per_s": doc["batched"]["images_per_second"],
            "loop_images_per_s": doc["loop"]["images_per_second"],
            "loop_same_capacities_images_per_s": doc["loop_same_capacities"]["images_per_second"],
            "ratio": doc["ratio"], "batch_devices": doc["batched"]["devices"],
            "max_abs_difference": doc["max_abs_difference"]["loop_same_capacities"],
            "peak_radiance": doc["max_abs_difference"]["peak_radiance"],
            "note": "ratio: batched images/s over the faster loop; loop_same_capacities "
                    "renders each frame at the batch's level capacities (the fairer loop)"}


def headline(results: dict) -> str:
    """A Markdown table of the run: per structure, build time, and per set Mrays/s with
    the ratio to Embree (the figures to quote)."""
    records = results["records"]
    sets = [s["name"] for s in results["parameters"]["sets"]]
    builds = {r["structure"]: r for r in records if r["kind"] == "build"}
    traces = {(r["structure"], r["set"]): r for r in records if r["kind"] == "trace"}
    embree = {r["set"]: r for r in records if r["kind"] == "peer" and r["peer"] == "embree"}
    lines = ["| structure | build (s) | " + " | ".join(
                 f"{s} Mrays/s (x Embree)" for s in sets) + " |",
             "| --- | --- | " + " | ".join("---" for _ in sets) + " |",
             "| embree | | " + " | ".join(
                 f"{embree[s]['mrays_per_s']['median']:.2f} (1)" for s in sets) + " |"]
    for name in results["parameters"]["structures"]:
        cells = [f"{traces[name, s]['mrays_per_s']['median']:.3f} "
                 f"({traces[name, s]['ratio_to_embree']:.3f})" for s in sets]
        lines.append(f"| {name} | {builds[name]['seconds']['median']:.2f} | "
                     + " | ".join(cells) + " |")
    return "\n".join(lines)


def scaling_records(mesh, p, names, traces, records, tracer, threads, embree_cls, quiet,
                    log) -> list[dict]:
    """Build time and camera-ray Mrays/s against N; one record per structure."""
    ladder = scaling_ladder(mesh, p["mesh"], p["scaling"])
    if not ladder:
        return []
    rows = {name: [] for name in names}
    main_builds = {r["structure"]: r for r in records if r["kind"] == "build"}
    main_embree = next(r for r in records if r["kind"] == "peer" and r["peer"] == "embree"
                       and r["set"] == "camera")
    n = p["camera_size"] ** 2
    bar = tqdm(total=len(ladder) * len(names), desc="scaling", disable=quiet, leave=False)
    for label, load in ladder:
        if label == p["mesh"]:
            for name in names:
                trace = next(t for t in traces[name] if t["set"] == "camera")
                b = main_builds[name]
                rows[name].append(_scaling_row(
                    label, b["triangles"], b["repeats"], trace["repeats"], trace["rays"],
                    trace["first_call_seconds"], main_embree["mrays_per_s"]["median"], True))
                bar.update()
            continue
        m = load()
        camera = fitted_camera(m.vertices, p["camera_size"])
        o, d = (np.asarray(a) for a in jrt.camera_rays(camera))
        embree = embree_cls(m.vertices, m.faces)
        embree.closest_hit(o, d, threads=threads)
        emb_rate = rates(n, time_calls(lambda o=o, d=d, e=embree: e.closest_hit(
            o, d, threads=threads), p["scaling_repeats"]))["median"]
        del embree
        arrays = _device_arrays(RaySet("camera", "closest", o, d, None, n))
        built = {}
        for name in names:
            built[name] = build_times(name, m.vertices, m.faces, p["scaling_builds"])
        first = first_calls([(name, lambda s=s, a=arrays: tracer.call(s, a, "closest"))
                             for name, (_, s) in built.items()], quiet, "compile")
        for name in names:
            times, structure = built.pop(name)
            trace_times = time_calls(lambda s=structure, a=arrays: tracer.call(s, a, "closest"),
                                     p["scaling_repeats"])
            rows[name].append(_scaling_row(label, len(m.faces), times, trace_times, n,
                                           first[name], emb_rate, False))
            r = rows[name][-1]
            log(f"scaling {name:<7} {label:<10} {len(m.faces):>9,} triangles: build "
                f"{r['build_seconds']['median']:.2f} s, {r['mrays_per_s']['median']:.3f} "
                f"Mrays/s (x{r['ratio_to_embree']:.3f} Embree)")
            bar.update()
    bar.close()
    out = []
    for name in names:
        r = rows[name]
        counts = [row["triangles"] for row in r]
        out.append({
            "kind": "scaling", "structure": name, "set": "camera", "rays": n, "rows": r,
            "build_exponent": fit_exponent(counts, [row["build_seconds"]["median"]
                                                    for row in r]),
            "trace_exponent": fit_exponent(counts, [row["trace_seconds"]["median"]
                                                    for row in r]),
            "note": "exponents: slope of log(time) against log(N); the trace time is for a "
                    "fixed number of camera rays"})
        build_k, trace_k = out[-1]["build_exponent"], out[-1]["trace_exponent"]
        log(f"scaling {name:<7} " + (f"build ~ N^{build_k:.2f}, trace time ~ N^{trace_k:.2f}"
            if build_k == build_k else f"exponents not fitted ({len(set(counts))} sizes)"))
    return out


def _scaling_row(label, triangles, build, trace, rays, first, embree_rate, reused) -> dict:
    rate = rates(rays, trace)
    build_s = summary(build)
    return {"mesh": label, "triangles": triangles, "build_repeats": build,
            "build_seconds": build_s,
            "ns_per_n_log2_n": ns_per_n_log2_n(build_s["median"], triangles),
            "trace_repeats": trace, "trace_seconds": summary(trace), "mrays_per_s": rate,
            "first_call_seconds": first, "embree_mrays_per_s": embree_rate,
            "ratio_to_embree": rate["median"] / embree_rate,
            "from_main_run": reused}


if __name__ == "__main__":
    main()
