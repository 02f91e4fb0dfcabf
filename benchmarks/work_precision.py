"""Work–precision runs of the Whitted renderer on the glass camel: error against
run time, each point one measured render.

    python -m benchmarks.work_precision [-o work_precision.json] [--quick]
                                        [--width W --height H] [--mesh camel|camel-19k]

Every point renders the built-in scene ``glass-camel`` (its mesh swapped to ``--mesh``, by
default the 19k-triangle camel to keep the run short) with one setting changed, and compares
it with a reference render: depth 10, many wavelength samples (32 with ``--quick``, 64
otherwise), no pruning (threshold 0), exact Fresnel, the watertight kernel. The run time is
the wall time of :func:`jrt.whitted.render_scene` (radiance and sRGB encoding) after a
warm-up render of the same shapes (same size, samples, mode, spp, kernel and Fresnel and depth),
so compiling is left out; the compile time of the warm-up is recorded apart
(``compile_seconds``). The error is measured on the encoded sRGB images: PSNR and SSIM by
scikit-image (``data_range=1``, ``channel_axis=-1``) and the mean CIEDE2000 ΔE by
colour-science (sRGB → XYZ → Lab, ``colour.delta_E(..., method="CIE 2000")``).

Studies (each a ``study``, one diagram in ``reports.report``; ``series`` joins points):

* ``Whitted depth``: ``max_depth`` 1..8 (quick: 1, 2, 4);
* ``wavelength samples``: 4, 8, 16, 32 (quick: 4, 8, 16);
* ``pruning threshold``: 1e-1, 1e-2, 1e-3, 1e-4 (quick: 1e-1, 1e-3);
* ``exact tree vs sampled branches``: the tree at the default depth, and ``mode="sampled"``
  at 1, 4, 16 paths per pixel (quick: 1);
* ``Fresnel exact vs Schlick``: both at the scene's defaults;
* ``kernel``: ``plane_barycentric``, ``moller_trumbore``, ``watertight``, float32 (jrt's
  meshes and kernels are float32; there is no float64 path without changing the library, so
  the float64 variant is left out and the JSON's ``notes`` say so).

Everything not varied stays at the scene's settings (depth 8, 16 samples, threshold 1e-3,
exact Fresnel, watertight kernel, BVH). Output: ``{"kind": "work_precision", "machine",
"parameters", "reference", "records", "notes"}``, records of kind ``work_precision``
(``study``, ``series``, ``method``, ``seconds``, ``compile_seconds``, ``psnr``, ``ssim``,
``delta_e``, ``rays``, ``command``) as ``reports.report`` reads them. The reference is not
a record; a point identical to it has ``psnr`` null (infinite) and ``identical`` true.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import platform
import sys
import time

import numpy as np

import jrt  # noqa: F401  (jrt sets XLA's flags before JAX starts)
from benchmarks.common import command_line, write_record

PROG = "python -m benchmarks.work_precision"
SCENE = "glass-camel"
KERNELS = ("plane_barycentric", "moller_trumbore", "watertight")

#: (full, quick) values of each study.
DEPTHS = ((1, 2, 3, 4, 5, 6, 7, 8), (1, 2, 4))
SAMPLES = ((4, 8, 16, 32), (4, 16))
THRESHOLDS = ((1e-1, 1e-2, 1e-3, 1e-4), (1e-1, 1e-3))
SPPS = ((1, 4, 16), (1,))
REFERENCE_SAMPLES = (64, 32)
REFERENCE_DEPTH = 10
#: Image size (full, quick).
SIZES = ((128, 96), (64, 48))


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=PROG, description=__doc__.split("\n\n")[0])
    p.add_argument("-o", "--output", default="work_precision.json", help="JSON to write")
    p.add_argument("--quick", action="store_true", help="fewer points, smaller images")
    p.add_argument("--width", type=int, default=None, help="image width (128; quick 64)")
    p.add_argument("--height", type=int, default=None, help="image height (96; quick 48)")
    p.add_argument("--mesh", choices=("camel", "camel-19k"), default="camel-19k",
                   help="the camel mesh of the glass camel (default camel-19k)")
    p.add_argument("--no-progress", action="store_true", help="no tqdm progress bar")
    return p


# ------------------------------------------------------------------------------ metrics


def metrics(image: np.ndarray, reference: np.ndarray) -> dict:
    """PSNR, SSIM and mean CIEDE2000 ΔE of encoded sRGB ``image`` against ``reference``."""
    import colour
    from skimage.metrics import peak_signal_noise_ratio, structural_similarity

    a = np.asarray(image, np.float64)
    b = np.asarray(reference, np.float64)
    identical = bool(np.array_equal(a, b))
    psnr = math.inf if identical else float(peak_signal_noise_ratio(b, a, data_range=1.0))
    ssim = float(structural_similarity(b, a, data_range=1.0, channel_axis=-1))
    lab_a = colour.XYZ_to_Lab(colour.sRGB_to_XYZ(a))
    lab_b = colour.XYZ_to_Lab(colour.sRGB_to_XYZ(b))
    delta_e = float(np.mean(colour.delta_E(lab_a, lab_b, method="CIE 2000")))
    return {"psnr": psnr if math.isfinite(psnr) else None, "ssim": ssim, "delta_e": delta_e,
            "identical": identical}


# ------------------------------------------------------------------------------ runs


def glass_camel(mesh: str):
    """The built-in glass camel with its objects' mesh set to ``mesh``."""
    from jrt.scene import load_scene

    scene = load_scene(SCENE)
    return dataclasses.replace(scene, objects=tuple(dataclasses.replace(o, mesh=mesh)
                                                    for o in scene.objects))


def with_settings(setup, **changes):
    """``setup`` with scene settings changed (kernel, fresnel): geometry and structure kept."""
    scene = setup.scene
    return dataclasses.replace(
        setup, scene=dataclasses.replace(scene, settings=dataclasses.replace(scene.settings,
                                                                             **changes)))


def measured_render(setup, *, width, height, max_depth, samples, threshold, mode="tree",
                    spp=1):
    """(sRGB image, stats, warm-up compile seconds): a warm-up render of the same shapes,
    then the measured one."""
    import jax

    from jrt import whitted

    kw = dict(width=width, height=height, samples=samples, mode=mode, spp=spp,
              key=jax.random.PRNGKey(0))
    # The same render first: it compiles the program and sizes the tree's levels.
    _, warm = whitted.render_scene(setup, max_depth=max_depth, threshold=threshold, **kw)
    image, stats = whitted.render_scene(setup, max_depth=max_depth, threshold=threshold, **kw)
    return image, stats, warm.compile_seconds + stats.compile_seconds


def plan(quick: bool, settings) -> list[dict]:
    """The points of every study: dicts of study, series, method and render changes."""
    q = int(bool(quick))
    depth, samples, threshold = settings.max_depth, settings.samples, settings.threshold
    points = []
    for d in DEPTHS[q]:
        points.append(dict(study="Whitted depth", series="tree", method=f"depth {d}",
                           max_depth=d))
    for s in SAMPLES[q]:
        points.append(dict(study="wavelength samples", series="tree", method=f"{s} samples",
                           samples=s))
    for t in THRESHOLDS[q]:
        points.append(dict(study="pruning threshold", series="tree", method=f"threshold {t:g}",
                           threshold=t))
    points.append(dict(study="exact tree vs sampled branches", series="tree",
                       method=f"tree (depth {depth})"))
    for n in SPPS[q]:
        points.append(dict(study="exact tree vs sampled branches", series="sampled",
                           method=f"sampled {n} spp", mode="sampled", spp=n))
    for f in ("exact", "schlick"):
        points.append(dict(study="Fresnel exact vs Schlick", series=f, method=f"Fresnel {f}",
                           fresnel=f))
    for k in KERNELS:
        points.append(dict(study="kernel", series=k, method=f"{k} float32", kernel=k))
    for p in points:
        p.setdefault("max_depth", depth)
        p.setdefault("samples", samples)
        p.setdefault("threshold", threshold)
        p.setdefault("mode", "tree")
        p.setdefault("spp", 1)
        p.setdefault("fresnel", settings.fresnel)
        p.setdefault("kernel", settings.kernel)
    return points


def machine_record() -> dict:
    import colour
    import jax
    import skimage

    return {"platform": platform.platform(), "processor": platform.machine(),
            "cpu_count": os.cpu_count(), "python": platform.python_version(),
            "jax": jax.__version__, "numpy": np.__version__, "scikit-image": skimage.__version__,
            "colour-science": colour.__version__,
            "jax_devices": [str(d) for d in jax.devices()]}


def run(*, quick=False, width=None, height=None, mesh="camel-19k", command=PROG,
        progress=True, points=None, reference_samples=None,
        reference_depth=REFERENCE_DEPTH) -> dict:
    """All the studies; returns the JSON document. ``points`` overrides :func:`plan`;
    ``reference_samples`` the reference's wavelength samples (64; quick 32)."""
    from tqdm import tqdm

    from jrt import whitted

    q = int(bool(quick))
    width = SIZES[q][0] if width is None else int(width)
    height = SIZES[q][1] if height is None else int(height)
    scene = glass_camel(mesh)
    settings = scene.settings
    start = time.perf_counter()
    setup = whitted.prepare(scene)
    prepare_seconds = time.perf_counter() - start
    points = plan(quick, settings) if points is None else points
    ref_samples = REFERENCE_SAMPLES[q] if reference_samples is None else int(reference_samples)

    ref_settings = dict(max_depth=reference_depth, samples=ref_samples, threshold=0.0,
                        fresnel="exact", kernel="watertight", mode="tree", spp=1)
    bar = tqdm(total=len(points) + 1, desc="work-precision", unit="render",
               disable=not progress, file=sys.stderr)
    bar.set_postfix_str("reference")
    ref_setup = with_settings(setup, fresnel="exact", kernel="watertight")
    reference, ref_stats, ref_compile = measured_render(
        ref_setup, width=width, height=height, max_depth=reference_depth,
        samples=ref_samples, threshold=0.0)
    bar.update()
    records = []
    for p in points:
        bar.set_postfix_str(f"{p['study']}: {p['method']}")
        s = with_settings(setup, fresnel=p["fresnel"], kernel=p["kernel"])
        image, stats, compile_seconds = measured_render(
            s, width=width, height=height, max_depth=p["max_depth"], samples=p["samples"],
            threshold=p["threshold"], mode=p["mode"], spp=p["spp"])
        m = metrics(image, reference)
        record = {"kind": "work_precision", "study": p["study"], "series": p["series"],
                  "method": p["method"], "seconds": stats.seconds,
                  "compile_seconds": compile_seconds, "psnr": m["psnr"], "ssim": m["ssim"],
                  "delta_e": m["delta_e"], "rays": stats.total_rays,
                  "settings": {k: p[k] for k in ("max_depth", "samples", "threshold", "mode",
                                                 "spp", "fresnel", "kernel")},
                  "command": command}
        if m["identical"]:
            record["identical"] = True
        records.append(record)
        bar.update()
    bar.close()
    return {
        "kind": "work_precision",
        "machine": machine_record(),
        "parameters": {"scene": SCENE, "mesh": mesh, "width": width, "height": height,
                       "quick": bool(quick),
                       "triangles": int(setup.geometry.faces.shape[0]),
                       "accel": settings.accel, "background": settings.background,
                       "defaults": dataclasses.asdict(settings),
                       "prepare_seconds": prepare_seconds,
                       "timing": "wall time of render_scene after a warm-up render of the "
                                 "same shapes (compile excluded, in compile_seconds)",
                       "metrics": "on encoded sRGB: PSNR and SSIM (scikit-image, data_range "
                                  "1, channel_axis -1), mean CIEDE2000 dE (colour-science, "
                                  "sRGB -> XYZ -> Lab)"},
        "reference": {**ref_settings, "width": width, "height": height,
                      "seconds": ref_stats.seconds, "compile_seconds": ref_compile,
                      "rays": ref_stats.total_rays, "dtype": "float32"},
        "records": records,
        "notes": [
            "Kernels are measured in float32 only: jrt's meshes, rays and kernels are float32 "
            "throughout and there is no float64 path without changing the library (enabling "
            "jax x64 does not turn the float32 mesh and ray arrays into float64), so the "
            "float64 variant is omitted.",
            "The reference is float32 too (for the same reason): deep (depth "
            f"{reference_depth}), {ref_samples} wavelength samples, threshold 0, "
            "exact Fresnel, watertight kernel; it is not among the records.",
            "Points that vary one setting keep the scene's others (depth "
            f"{settings.max_depth}, {settings.samples} samples, threshold "
            f"{settings.threshold:g}, {settings.fresnel} Fresnel, {settings.kernel} kernel); "
            "the depth and threshold studies therefore level off at the error of 16 samples.",
            "Every level of a render runs in one compiled program (jrt.wavefront); a "
            "level's capacity is rounded up to a size bucket, and its chunks of 32,768 rays "
            "past the live rays are skipped, so run times flatten at small workloads.",
            "Sampled branches use jax.random.PRNGKey(0), all paths through the pixel centre.",
        ],
    }


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    command = command_line(PROG, argv)
    start = time.perf_counter()
    doc = run(quick=args.quick, width=args.width, height=args.height, mesh=args.mesh,
              command=command, progress=not args.no_progress)
    doc["parameters"]["total_seconds"] = time.perf_counter() - start
    out = write_record(doc, args.output)
    ref = doc["reference"]
    print(f"reference: depth {ref['max_depth']}, {ref['samples']} samples, "
          f"{ref['seconds']:.2f} s (compile {ref['compile_seconds']:.2f} s)")
    for r in doc["records"]:
        psnr = "inf" if r["psnr"] is None else f"{r['psnr']:.2f}"
        print(f"{r['study']:32s} {r['method']:28s} {r['seconds']:7.3f} s  PSNR {psnr:>6s} dB"
              f"  SSIM {r['ssim']:.4f}  dE {r['delta_e']:.3f}")
    print(f"wrote {out} ({len(doc['records'])} points, "
          f"{doc['parameters']['total_seconds']:.1f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
