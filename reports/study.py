"""The whole study of the camel in one command: bench, stability, work-precision, renders, report.

    jrt study [-o DIR | --publish] [--quick | --full] [--skip STEPS] [--structures NAMES]

Runs, in this order, each writing its JSON into the output folder:

1. the benchmark suite (``benchmarks/suite.py``) on the camel: ``bench.json``;
2. the same suite on the other scenes of the scene suite (``jrt.scenes``: bunny, teapot,
   fandisk, stadium, herd, room, slivers; ``--scenes`` picks some), without its scaling,
   turntable and trimesh parts: ``scenes/NAME.json``. The generated scenes run at their
   small size unless ``--full`` (the full slivers with fewer rays: :data:`FULL_SCENE_RAYS`);
3. the stability suite (``benchmarks/stability.py``): ``stability.json``;
4. the work-precision study (``benchmarks/work_precision.py``): ``work_precision.json``;
5. the worked inverse problems (``benchmarks/inverse.py``, gradient descent through the
   differentiable queries and renderer; needs optax, skipped with a note without it):
   ``inverse.json``;
6. renders of the built-in scenes and a dispersion close-up of the glass camel
   (``jrt.whitted``), which the report copies into ``renders/``;
7. the report (``reports/report.py``) from all of it (the scenes in its section "The
   structures across scenes"): ``README.md``, ``index.html`` and
   the figures.

The output folder is ``./study`` in the working directory unless ``-o`` names another
(the repository ignores ``study/``). The published study, the repository's
``reports/camel/``, is rewritten only on request and only by a full run: ``--publish``
(``-o reports/camel --full``); any other size aimed at that folder is refused unless
``--force``, so that a smoke test never replaces the published figures.

Defaults take about 27 minutes on 2 cores (the full benchmark suite, the other scenes at
their small sizes, the stability suite at its ``standard`` size, the work-precision study's
quick points, both inverse problems at 150 steps; 1,623 s on a 2-core AMD EPYC Zen 2,
2026-12-07: bench 410, scenes 561, stability 375, work-precision 101, inverse 84, renders
82, most of it compiling: each scene's suite compiles 22 traversal programs); ``--full``
runs the stability suite's full sweep, every work-precision point, 300 inverse steps and
every scene at its full size as well (56 minutes on a 2-core AMD EPYC Zen 2, 2026-12-07:
bench 7, scenes 29, stability 14, work-precision 3, inverse 2, renders 1.5; what
``reports/camel/`` is published from); ``--quick`` (small ray sets, the 19k camel where a
step allows it, small images) about 13 minutes (794 s on the same host: bench 117,
scenes 400, stability 98, work-precision 106, inverse 22, renders 44), and is what CI runs
(with ``--structures bvh --scenes stadium``).
``--structures`` limits the benchmark suite to some acceleration structures (brute
force, its reference, always runs; the stability suite picks its own per case). A step
that fails stops the study with its error; the JSON of the steps before it stays in the
folder.
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import time
from pathlib import Path

import jrt
from benchmarks.structures import ENGINE_STRUCTURES, structure_names
from jrt.scenes import SCENES as SUITE_SCENES

#: The command name in usage and errors when run as ``python -m reports.study``
#: (``jrt study`` passes its own).
PROG = "python -m reports.study"
#: Where a study goes unless ``-o`` says otherwise: relative to the working directory.
DEFAULT_OUTPUT = Path("study")
#: The published study, tracked in the repository: written by ``--publish`` only (or by
#: ``-o`` naming it with ``--full``, or ``--force``).
PUBLISHED = Path(__file__).resolve().parent / "camel"

#: Render sizes (width, height) of the built-in scenes, full and --quick.
RENDER_SIZE = {"full": (480, 360), "quick": (96, 72)}
SCENES = ("camel", "glass-camel", "mirror-camel")
#: The scene suite's scenes that the scenes step runs (the camel is the bench step's).
OTHER_SCENES = tuple(name for name in SUITE_SCENES if name != "camel")
#: The dispersion close-up: the glass camel's own eye, aimed this fraction of the mesh's
#: height above its centre (the humps), with this vertical field of view (degrees) and
#: wavelength samples.
CLOSEUP = {"above_centre": 0.22, "vfov": 11.0, "samples": 16}


def build_parser(prog: str = PROG) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog=prog,
        description="The whole study of the camel in one command: the benchmark suite (on "
        "the camel and on the other scenes of the scene suite), the stability suite, the "
        "work-precision study, the worked inverse problems (gradient descent through the "
        "differentiable renderer; needs optax) and renders of the "
        "built-in scenes, each written into DIR, then the report (README.md, index.html, "
        "figures) from all of it. The default size takes about 27 minutes on 2 cores (9 "
        "of them the scenes), --full about 56, --quick about 13.",
        epilog="The published study (reports/camel in the repository) is rewritten only by "
        "--publish, or by -o naming it with --full; any other size aimed at it is refused "
        "unless --force.")
    parser.add_argument("-o", "--output", default=None, metavar="DIR",
                        help=f"folder for the JSON, the renders and the report (default "
                        f"./{DEFAULT_OUTPUT} in the working directory)")
    parser.add_argument("--publish", action="store_true",
                        help="rewrite the published study: the same as -o reports/camel "
                        "--full (the repository's reports/camel)")
    parser.add_argument("--force", action="store_true",
                        help="allow a --quick or default-size run to write into "
                        "reports/camel")
    size = parser.add_mutually_exclusive_group()
    size.add_argument("--quick", action="store_true",
                      help="small sizes: a smoke test of the whole chain (CI)")
    size.add_argument("--full", action="store_true",
                      help="the stability suite's full sweep and every work-precision "
                      "point: the published study's size")
    parser.add_argument("--skip", default="", metavar="STEPS",
                        help="comma-separated steps to skip, from bench, scenes, stability, "
                        "work_precision, inverse, renders (their JSON, if present, is reused)")
    parser.add_argument("--scenes", type=scene_names, default=None, metavar="NAMES",
                        help="comma-separated scenes of the scenes step, from "
                        f"{', '.join(OTHER_SCENES)} (default all)")
    parser.add_argument("--structures", type=structure_names, default=None, metavar="NAMES",
                        help="comma-separated acceleration structures for the benchmark "
                        f"suite, from {', '.join(ENGINE_STRUCTURES)} (default all; brute "
                        "force always runs)")
    return parser


def output_folder(args, parser: argparse.ArgumentParser) -> Path:
    """The folder a study of these options writes into (``./study`` by default), after
    the published study's rule: ``--publish`` means ``-o reports/camel --full``, and a run
    of another size aimed at ``reports/camel`` is an error unless ``--force``. Sets
    ``args.full`` for ``--publish``; exits through ``parser.error`` on a refusal, before
    anything is written."""
    if args.publish:
        if args.quick:
            parser.error("--publish rewrites the published study at its full size; it "
                         "cannot be --quick (a quick study goes to ./study by default)")
        if args.output is not None and Path(args.output).resolve() != PUBLISHED.resolve():
            parser.error(f"--publish writes into {PUBLISHED}; give --publish or -o "
                         f"{args.output}, not both")
        args.full = True
        # Relative where it can be: the commands recorded in the report name this path.
        return Path(os.path.relpath(PUBLISHED)) if PUBLISHED.is_relative_to(Path.cwd()) \
            else PUBLISHED
    out = DEFAULT_OUTPUT if args.output is None else Path(args.output)
    if out.resolve() == PUBLISHED.resolve() and not args.full and not args.force:
        size = "--quick" if args.quick else "default-size"
        parser.error(f"{out} holds the published study, made by a --full run; a {size} "
                     "run would replace its figures. Rewrite it with --publish (or -o "
                     f"{out} --full), write elsewhere (default ./{DEFAULT_OUTPUT}), or add "
                     "--force")
    return out


STEPS = ("bench", "scenes", "stability", "work_precision", "inverse", "renders")
#: The scenes step's suite options by study size: the suite without its scaling, turntable,
#: trimesh and trimesh-interface parts, the generated scenes small unless --full.
SCENE_SIZES = {
    "quick": ["--quick"],
    "default": ["--scene-size", "small", "--camera-size", "256", "--rays", "65536",
                "--builds", "3", "--repeats", "3"],
    "full": ["--scene-size", "full", "--camera-size", "512", "--rays", "131072"],
}
SCENE_PARTS_OFF = ["--scaling", "0", "--turntable-frames", "0", "--trimesh-rays", "0",
                   "--interface-rays", "0"]
#: Scenes whose rays cost far more than the others' at the full size, run there with fewer
#: rays: the full slivers' 50,000 crossing needles, which Embree traces at 0.03 Mrays/s
#: on 2 cores, the BVH at 0.004 and the BSP tree (one leaf of every needle) at 0.001
#: (2026-12-07): at the full study's 262,144 camera rays a single BSP call takes over
#: four minutes, and the scene alone hours.
FULL_SCENE_RAYS = {"slivers": ["--camera-size", "128", "--rays", "8192", "--builds", "3",
                               "--repeats", "3"]}


def scene_options(name: str, size: str) -> list[str]:
    """The benchmark suite's options for scene ``name`` in a study of ``size`` (quick,
    default, full): :data:`SCENE_SIZES`, then :data:`FULL_SCENE_RAYS` (the last of a
    repeated option counts), then :data:`SCENE_PARTS_OFF`."""
    fewer = FULL_SCENE_RAYS.get(name, []) if size == "full" else []
    return [*SCENE_SIZES[size], *fewer, *SCENE_PARTS_OFF]


def scene_names(text: str) -> list[str]:
    """``--scenes``: comma-separated names of :data:`OTHER_SCENES`, in the suite's order."""
    names = [n.strip() for n in text.split(",") if n.strip()]
    unknown = [n for n in names if n not in OTHER_SCENES]
    if unknown or not names:
        raise argparse.ArgumentTypeError(
            f"unknown scene(s) {unknown or [text]}; allowed: {', '.join(OTHER_SCENES)} (the "
            "camel is the bench step's)")
    return [n for n in OTHER_SCENES if n in names]
#: Arguments of the inverse problems' step by study size (benchmarks.inverse).
INVERSE_SIZES = {"quick": ["--quick"], "default": [], "full": ["--steps", "300"]}


def _check_skip(text: str, prog: str = PROG) -> set[str]:
    skip = {s.strip() for s in text.split(",") if s.strip()}
    unknown = sorted(skip - set(STEPS))
    if unknown:
        raise SystemExit(f"{prog}: error: unknown step(s) {unknown} in --skip; "
                         f"allowed: {', '.join(STEPS)}")
    return skip


def _render_scenes(quick: bool) -> list[str]:
    """The built-in scenes and a dispersion close-up of the glass camel (:data:`CLOSEUP`)
    as PNGs in a temporary folder, ``PATH:caption`` each: the report
    copies them into its ``renders/`` folder (which it clears of stale images first)."""
    import dataclasses
    import tempfile

    import numpy as np
    from skimage import io

    from jrt.scene import CameraSpec, load_scene
    from jrt.whitted import prepare, render_scene

    width, height = RENDER_SIZE["quick" if quick else "full"]
    folder = Path(tempfile.mkdtemp(prefix="jrt-study-renders-"))
    images = []

    def shrink(scene):  # --quick: a shallower tree and fewer wavelengths
        if not quick:
            return scene
        return dataclasses.replace(scene, settings=dataclasses.replace(
            scene.settings, max_depth=min(3, scene.settings.max_depth),
            samples=min(4, scene.settings.samples)))

    def render(name, scene, command, structure=None):
        image, stats = render_scene(prepare(scene, structure=structure), width=width,
                                    height=height)
        path = folder / f"{name}.png"
        io.imsave(path, np.round(np.clip(image, 0, 1) * 255).astype(np.uint8),
                  check_contrast=False)
        print(f"  {name}: {stats.summary()}")
        images.append(f"{path}:{command}: {stats.summary()}")

    for name in SCENES:
        render(name, shrink(load_scene(name)),
               f"`jrt render --scene {name} --width {width} --height {height}`")
    # The dispersion close-up: the humps of the glass camel, where light leaves the glass
    # after internal reflections and each wavelength leaves at its own angle.
    glass = load_scene("glass-camel")
    setup = prepare(glass)
    camera = setup.camera(width, height)
    lo, hi = setup.bounds
    target = (lo + hi) / 2 + np.array([0.0, CLOSEUP["above_centre"] * (hi - lo)[1], 0.0])
    closeup = dataclasses.replace(
        glass, camera=CameraSpec(eye=camera.eye, target=tuple(float(x) for x in target),
                                 up=camera.up, vfov=CLOSEUP["vfov"], width=width,
                                 height=height),
        settings=dataclasses.replace(glass.settings, samples=CLOSEUP["samples"]))
    render("glass-camel-closeup", shrink(closeup),
           f"dispersion close-up of `glass-camel` (`reports/study.py`: the scene's eye "
           f"aimed {CLOSEUP['above_centre']:.0%} of the height above the centre, vertical "
           f"field of view {CLOSEUP['vfov']:g}°, {CLOSEUP['samples']} wavelengths)",
           structure=setup.structure)
    return images


def main(argv=None, prog: str = PROG) -> int:
    """``jrt study``: run the steps and the report; 0 on success. ``prog`` names the
    command in usage and errors."""
    parser = build_parser(prog)
    args = parser.parse_args(argv)
    skip = _check_skip(args.skip, prog)
    out = output_folder(args, parser)
    out.mkdir(parents=True, exist_ok=True)
    quick = ["--quick"] if args.quick else []
    start = time.perf_counter()
    jsons = {step: out / f"{step}.json"
             for step in ("bench", "stability", "work_precision", "inverse")}

    def step(name, run):
        if name in skip:
            print(f"[study] {name}: skipped")
            return None
        begun = time.perf_counter()
        print(f"[study] {name} ...", flush=True)
        result = run()
        jrt.clear_caches()  # (jrt.programs: a study compiles past the mappings limit)
        print(f"[study] {name}: {time.perf_counter() - begun:.0f} s", flush=True)
        return result

    size = "quick" if args.quick else "full" if args.full else "default"
    sizes = {"stability": ["--size", "quick" if args.quick else "full" if args.full
                           else "standard"],
             "work_precision": [] if args.full else ["--quick"]}
    # Brute force, the suite's reference, runs whatever the structures.
    structures = ([] if args.structures is None
                  else ["--structures", ",".join(args.structures)])
    step("bench", lambda: _ok(_step_main("bench")(
        ["-o", str(jsons["bench"]), *quick, *structures])))
    scenes = {name: out / "scenes" / f"{name}.json" for name in args.scenes or OTHER_SCENES}

    def run_scenes():
        for name, path in scenes.items():
            print(f"[study] scenes: {name}", flush=True)
            _ok(_step_main("bench")(["-o", str(path), "--scene", name,
                                     *scene_options(name, size), *structures]))
            jrt.clear_caches()

    step("scenes", run_scenes)
    for name in ("stability", "work_precision"):
        step(name, lambda name=name: _ok(_step_main(name)(
            ["-o", str(jsons[name])] + sizes.get(name, quick))))
    if "inverse" not in skip and importlib.util.find_spec("optax") is None:
        print("[study] inverse: skipped (its optimiser, optax, is not installed: "
              "pip install optax)")
    else:
        step("inverse", lambda: _ok(_step_main("inverse")(
            ["--json", str(jsons["inverse"])] + INVERSE_SIZES[size])))
    images = step("renders", lambda: _render_scenes(args.quick)) or []

    from reports import report

    present = [str(p) for p in [*jsons.values(), *scenes.values()] if p.exists()]
    if not present:
        raise SystemExit(f"{prog}: error: no results to report (every step skipped and "
                         f"no JSON in {out})")
    report_args = present + ["-o", str(out)]
    for image in images:
        report_args += ["--image", image]
    _ok(report.main(report_args))
    print(f"[study] done in {time.perf_counter() - start:.0f} s: {out / 'README.md'}, "
          f"{out / 'index.html'}")
    return 0


def _step_main(step: str):
    """The ``main`` of a step's suite, imported when the step runs (so that ``jrt study
    --help`` and a study that skips a step do not load it)."""
    if step == "bench":
        from benchmarks.suite import main as step_main
    elif step == "stability":
        from benchmarks.stability import main as step_main
    elif step == "inverse":
        from benchmarks.inverse import main as step_main
    else:
        from benchmarks.work_precision import main as step_main
    return step_main


def _ok(status) -> None:
    """A step's main returned a non-zero status: stop the study there."""
    if isinstance(status, int) and status != 0:
        raise SystemExit(status)


if __name__ == "__main__":
    raise SystemExit(main())
