"""The ``jrt`` command line: ``jrt trace``, ``jrt render`` and the commands registered on top.

``jrt trace`` and ``jrt render`` are the library's own. The packages above the library add
the study's commands (``jrt bench``, ``jrt stability``, ``jrt study``, ``jrt report``) as
entry points of the group :data:`COMMAND_GROUP` (``pyproject.toml``), each naming a
``main(argv, prog=...)``: the library never imports them, a command's module is loaded only
when it runs, and ``jrt --help`` reads each one's line of help from its module's docstring
without importing it.

``jrt trace`` and ``jrt render`` keep their compiled XLA programs on disk
(:mod:`jrt.compile_cache`): a second run in a new process loads them instead of compiling.
``JRT_CACHE_DIR`` names the folder (default ``$XDG_CACHE_HOME/jrt/jax`` or
``~/.cache/jrt/jax``), ``JRT_CACHE_DIR=0`` turns the cache off, and a
``JAX_COMPILATION_CACHE_DIR`` of your own is left as it is.
"""

from __future__ import annotations

import argparse
import ast
import contextlib
import importlib.metadata
import importlib.util
import math
import re
import sys
import time
import warnings
from pathlib import Path

import numpy as np

import accel
import jrt  # (applies the XLA flags before JAX starts)
from jrt.compile_cache import enable as enable_compile_cache
from jrt.data import MESHES, mesh_path
from jrt.kernels import DEFAULT_KERNEL, KERNELS
from jrt.mesh import MeshError, MeshWarning, load_mesh
from jrt.rays_io import RaysFileError, load_rays, save_hits
from jrt.scenes import GENERATED_LABELS, parse_label, scene_mesh

#: The command line's own description (plain text: argparse prints it as it is).
DESCRIPTION = ("jrt traces rays through triangle meshes with JAX. 'jrt trace' and 'jrt render' "
               "use the library; the other commands (the benchmark suite, the stability "
               "suite, the whole study of the camel, the report generator) come with the "
               "packages installed on top of it, each with its own options: "
               "jrt COMMAND --help.")

#: The help's closing note: the environment variable of the compilation cache.
EPILOG = ("'jrt trace' and 'jrt render' keep their compiled programs on disk, so a second run "
          "skips compiling: JRT_CACHE_DIR=DIR names the folder (default "
          "$XDG_CACHE_HOME/jrt/jax or ~/.cache/jrt/jax), JRT_CACHE_DIR=0 turns the cache off, "
          "and a JAX_COMPILATION_CACHE_DIR you set is used as it is.")

#: Commands that use the on-disk compilation cache (jrt bench and jrt study measure
#: compile times, so they compile every time).
CACHED = ("trace", "render")

#: The entry-point group through which the packages above the library add commands: each
#: entry point names a ``main(argv, prog="jrt NAME")`` (``pyproject.toml``'s
#: ``[project.entry-points."jrt.commands"]``).
COMMAND_GROUP = "jrt.commands"
#: The library's own commands; a registered command of the same name is ignored.
LIBRARY_COMMANDS = ("trace", "render")
#: The study's commands that a full install registers: named here so that an install
#: without them says so (instead of "invalid choice"), in this order in the help.
STUDY_COMMANDS = ("bench", "stability", "study", "report")
#: What ``jrt render --turntable N`` (or ``--sweep``) turns (or varies) without
#: ``--scene``: the built-in scene of what ``jrt render`` alone renders, the camel in the
#: same 3/4 view.
DEFAULT_SCENE = "camel"


def _mesh(arg: str | None):
    """A path, a short name of a shipped mesh (``jrt.data.MESHES``: camel, camel-19k,
    bunny, teapot, fandisk) or a generated scene of the scene suite
    (``jrt.scenes.GENERATED_LABELS``: stadium, herd, room, slivers, each also ``-small``)."""
    if arg is None or arg in MESHES:
        return load_mesh(mesh_path(arg or "camel"))
    if arg in GENERATED_LABELS:
        name, size = parse_label(arg)
        return scene_mesh(name, size=size)
    return load_mesh(arg)


def _mesh_stem(arg: str | None) -> str:
    """The default name of a mesh's output files: its short name, or its file's stem."""
    if arg is None:
        return "camel"
    if arg in MESHES or arg in GENERATED_LABELS:
        return arg
    name = Path(arg).name
    return name.split(".")[0] or "render"


def _cmd_trace(args) -> int:
    from jrt.trace import as_numpy, closest_hit, occluded

    mesh = _mesh(args.mesh)
    origins, directions, tmax = load_rays(args.rays)
    print(mesh.summary())
    structure = accel.build(args.accel, mesh.vertices, mesh.faces)

    def query(o, d):
        if args.any_hit:
            return {"occluded": np.asarray(occluded(structure, o, d, tmax=tmax,
                                                    kernel=args.kernel))}
        return as_numpy(closest_hit(structure, o, d, kernel=args.kernel, tmax=tmax))

    n = len(origins)
    timing = ""
    if n:
        # Compile first, on rays of the same shapes that leave the mesh's box at once, so
        # that the timed call below traces the file's rays and nothing else.
        start = time.perf_counter()
        query(*_rays_away(mesh, n))
        compile_seconds = time.perf_counter() - start
    start = time.perf_counter()
    result = query(origins, directions)
    seconds = time.perf_counter() - start
    if n:
        timing = (f" in {seconds:.3f} s ({_rate(n, seconds)}; compiled first, in "
                  f"{compile_seconds:.2f} s)")
    if args.any_hit:
        summary = f"{int(result['occluded'].sum()):,} occluded"
    else:
        summary = f"{int((result['triangle'] >= 0).sum()):,} hits"
    out = save_hits(args.output, **result)
    print(f"{n:,} rays, {summary}{timing} -> {out}")
    return 0


def _rays_away(mesh, n: int) -> tuple[np.ndarray, np.ndarray]:
    """float32 [n, 3] origins beyond the mesh box's upper corner and +x directions: rays
    that leave the box at once, for a compile on the shapes of ``n`` rays."""
    corner = mesh.bounds[1].astype(np.float64) + max(mesh.diagonal, 1.0)
    origins = np.broadcast_to(corner.astype(np.float32), (n, 3)).copy()
    directions = np.zeros((n, 3), np.float32)
    directions[:, 0] = 1.0
    return origins, directions


def _rate(rays: int, seconds: float) -> str:
    """Rays per second in Mrays/s, at least three significant digits (a small batch's
    rate reads 0.000585, not 0.000)."""
    mrays = rays / seconds / 1e6 if seconds > 0 else float("inf")
    return f"{mrays:,.0f} Mrays/s" if mrays >= 100 else f"{mrays:.3g} Mrays/s"


def _cmd_render(args) -> int:
    if args.scene is None and (args.turntable is not None or args.sweep is not None):
        # A batch renders a scene (the Whitted tree): without one, the default scene.
        option = "--turntable" if args.turntable is not None else "--sweep"
        if args.mesh is not None:
            raise ValueError(f"{option} applies to scene renders (the Whitted tree), not to "
                             f"a mesh ({args.mesh}): leave the mesh out for the default "
                             f"scene ({DEFAULT_SCENE}), or give --scene NAME|FILE (camel, "
                             "glass-camel, mirror-camel or a .toml)")
        return _render_scene(args, DEFAULT_SCENE)
    if args.scene is not None:
        return _render_scene(args, args.scene)
    if args.depth is not None or args.samples is not None:
        raise ValueError("--depth and --samples apply to --scene renders (the Whitted tree)")
    from skimage import io

    from jrt.camera import frame_mesh
    from jrt.normals import DEFAULT_CREASE_ANGLE
    from jrt.render import render_lambert, to_srgb8

    accel_name = args.accel or "bvh"
    kernel = args.kernel or DEFAULT_KERNEL
    width, height = args.width or 640, args.height or 480
    mesh = _mesh(args.mesh)
    print(mesh.summary())
    structure = accel.build(accel_name, mesh.vertices, mesh.faces)
    camera = frame_mesh(mesh.vertices, width=width, height=height, vfov=args.vfov,
                        azimuth=args.azimuth, elevation=args.elevation)
    crease = DEFAULT_CREASE_ANGLE if args.crease_angle is None else args.crease_angle

    def render():
        return render_lambert(mesh, structure, camera, kernel=kernel,
                              shadows=not args.no_shadows, ambient=args.ambient,
                              crease_angle=crease)

    # The first render compiles its queries (and is timed as such); the second, on the
    # same shapes, is the render's own time.
    first = render()[1].seconds
    image, stats = render()
    out = Path(args.output or f"{_mesh_stem(args.mesh)}.png")
    out.parent.mkdir(parents=True, exist_ok=True)
    io.imsave(out, to_srgb8(image), check_contrast=False)
    print(f"{accel_name}/{kernel} {stats.width}x{stats.height}: {stats.primary_rays:,} camera "
          f"rays + {stats.shadow_rays:,} shadow rays in {stats.seconds:.2f} s "
          f"({_rate(stats.rays, stats.seconds)}; compiled first, in a render of "
          f"{first:.2f} s) -> {out}")
    return 0


def _render_scene(args, spec: str) -> int:
    """``jrt render --scene NAME|FILE`` (``spec``): the Whitted renderer (jrt.whitted)."""
    import dataclasses

    from skimage import io

    from jrt.scene import MAX_DEPTH, MAX_SAMPLES, load_scene
    from jrt.whitted import prepare, render_scene

    if args.mesh is not None:
        raise ValueError(f"give a mesh ({args.mesh}) or --scene, not both")
    for option, value, most in (("--depth", args.depth, MAX_DEPTH),
                                ("--samples", args.samples, MAX_SAMPLES)):
        if value is not None and value > most:
            raise ValueError(f"{option} {value}: allowed 1..{most}")
    scene = load_scene(spec)
    settings = scene.settings
    changes = {key: value for key, value in (
        ("accel", args.accel), ("kernel", args.kernel), ("max_depth", args.depth),
        ("samples", args.samples)) if value is not None}
    if changes:
        scene = dataclasses.replace(scene, settings=dataclasses.replace(settings, **changes))
    if args.crease_angle is not None:
        scene = dataclasses.replace(scene, objects=tuple(
            dataclasses.replace(o, crease_angle=args.crease_angle) for o in scene.objects))
    width = args.width or scene.camera.width
    height = args.height or scene.camera.height
    if args.turntable is not None and args.sweep is not None:
        raise ValueError("--turntable and --sweep are separate batches: give one of them")
    if args.sweep is not None:
        return _render_sweep(args, scene, width, height)
    setup = prepare(scene)
    if args.turntable is not None:
        return _render_turntable(args, setup, width, height)
    geometry = setup.geometry
    print(f"{geometry.mesh.summary()}; {scene.settings.accel} built in "
          f"{setup.structure.stats.get('build_seconds', float('nan')):.2f} s")
    image, stats = render_scene(setup, width=width, height=height, spp=args.spp)
    out = Path(args.output or f"{scene.name}.png")
    out.parent.mkdir(parents=True, exist_ok=True)
    io.imsave(out, np.round(np.clip(image, 0, 1) * 255).astype(np.uint8), check_contrast=False)
    print(f"{scene.settings.accel}/{scene.settings.kernel} {scene.name} {stats.summary()} "
          f"-> {out}")
    return 0


#: Frame time of the turntable GIF, milliseconds (GIF counts in hundredths of a second).
GIF_FRAME_MS = 80


def _to_uint8(image) -> np.ndarray:
    return np.round(np.clip(image, 0, 1) * 255).astype(np.uint8)


def _render_turntable(args, setup, width: int, height: int) -> int:
    """``jrt render --scene S --turntable N``: N frames around the camera's target (one
    batch, jrt.batch), written as DIR/frame_000.png... and the animated DIR/turntable.gif."""
    import imageio.v3 as iio

    from jrt.batch import batch_to_srgb, render_batch, turntable

    scene = setup.scene
    frames = args.turntable
    cameras = turntable(setup, frames, width=width, height=height)
    radiance, stats = render_batch(setup, cameras=cameras)
    images = _to_uint8(batch_to_srgb(radiance, setup))
    folder = Path(args.output or f"{scene.name}-turntable")
    if folder.suffix.lower() in (".png", ".gif"):
        raise ValueError(f"-o {folder}: with --turntable, -o names a folder for the frames "
                         "and the GIF (e.g. -o turntable/)")
    folder.mkdir(parents=True, exist_ok=True)
    digits = max(3, len(str(frames - 1)))
    for i, image in enumerate(images):
        iio.imwrite(folder / f"frame_{i:0{digits}d}.png", image)
    gif = folder / "turntable.gif"
    iio.imwrite(gif, images, duration=GIF_FRAME_MS, loop=0)
    print(f"{scene.settings.accel}/{scene.settings.kernel} {scene.name} turntable: "
          f"{stats.summary()} -> {folder}/frame_*.png, {gif}")
    return 0


def _render_sweep(args, scene, width: int, height: int) -> int:
    """``jrt render --scene S --sweep MATERIAL.FIELD=START:STOP:N``: one batch over the
    values (jrt.batch), written as a contact sheet, each tile labelled by its value."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from jrt.batch import batch_to_srgb, parse_sweep, prepare_sweep, render_batch

    sweep = parse_sweep(args.sweep)
    setup, scenes = prepare_sweep(scene, sweep)  # checks material and field first
    radiance, stats = render_batch(setup, scenes=scenes, width=width, height=height)
    images = batch_to_srgb(radiance, setup)
    n = len(images)
    cols = math.ceil(math.sqrt(n))
    rows = math.ceil(n / cols)
    tile = max(2.0, width / 100)  # inches: at least 2 so that the labels fit
    fig, axes = plt.subplots(rows, cols, squeeze=False,
                             figsize=(cols * tile, rows * tile * height / width + 0.6 * rows))
    for ax in axes.flat:
        ax.axis("off")
    unit = " µm²" if sweep.field == "B" else ""
    for ax, image, value in zip(axes.flat, images, sweep.values, strict=False):
        ax.imshow(image, interpolation="nearest")
        ax.set_title(f"{sweep.label} = {value:.6g}{unit}", fontsize=9)
    fig.suptitle(f"{scene.name}: {sweep.label} from {sweep.values[0]:g} to "
                 f"{sweep.values[-1]:g}, {n} values", fontsize=10)
    fig.tight_layout()
    out = Path(args.output or f"{scene.name}-sweep.png")
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=100)
    plt.close(fig)
    print(f"{scene.settings.accel}/{scene.settings.kernel} {scene.name} sweep of "
          f"{sweep.label}: {stats.summary()} -> {out}")
    return 0


def _frames(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(
            f"N must be an integer >= 1 (the number of frames), got {text!r}")
    return value


def _crease_angle(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not 0.0 <= value <= 180.0:
        raise argparse.ArgumentTypeError(
            f"DEG must be a number of degrees in [0, 180] (0 flat, 180 all smooth), "
            f"got {text!r}")
    return value


def _positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be a positive integer, got {text}")
    return value


class _CommandLine(argparse.ArgumentParser):
    """The ``jrt`` parser. Until its help is asked for, the registered commands' help lines
    are not read (parsing a command needs their names only); ``jrt --help`` prints the
    help of a parser built with them."""

    def __init__(self, *args, described: bool = True, **kwargs):
        super().__init__(*args, **kwargs)
        self.described = described

    def format_help(self) -> str:
        if self.described:
            return super().format_help()
        return build_parser(describe=True).format_help()


def build_parser(describe: bool = False) -> argparse.ArgumentParser:
    """The ``jrt`` parser: the library's commands and those registered under
    :data:`COMMAND_GROUP` (whose options are their own: they are parsed by the command).
    ``describe`` reads the registered commands' help lines now rather than when the help
    is printed."""
    parser = _CommandLine(prog="jrt", description=DESCRIPTION, epilog=EPILOG,
                          described=describe)
    sub = parser.add_subparsers(dest="command", required=True,
                                parser_class=argparse.ArgumentParser)

    def common(p, scene_default=False):
        also = "; with --scene, the scene's" if scene_default else ""
        p.add_argument("--kernel", choices=tuple(KERNELS),
                       default=None if scene_default else DEFAULT_KERNEL,
                       help=f"ray-triangle kernel (default {DEFAULT_KERNEL}{also})")
        p.add_argument("--accel", choices=accel.NAMES, default=None if scene_default else "bvh",
                       help=f"acceleration structure (default bvh{also}; brute is the oracle)")

    trace = sub.add_parser("trace", help="closest hits (or occlusion) of rays from a file",
                           epilog=EPILOG)
    trace.add_argument("mesh", help="mesh file (OFF/OBJ/PLY/STL, or .gz of one), a "
                       f"shipped mesh: {', '.join(MESHES)}, or a generated scene: "
                       f"{', '.join(GENERATED_LABELS)}")
    trace.add_argument("rays",
                       help=".npz with origins, directions float32 [N,3], optional tmax [N]")
    trace.add_argument("-o", "--output", required=True, help="output .npz of hits")
    trace.add_argument("--any-hit", action="store_true",
                       help="write 'occluded' (any hit before tmax) instead of closest hits")
    common(trace)
    trace.set_defaults(run=_cmd_trace)

    render = sub.add_parser(
        "render", help="render a mesh (Lambert, default: the camel) or a scene (--scene, "
        "Whitted) to a PNG", epilog=EPILOG)
    render.add_argument("mesh", nargs="?", default=None,
                        help=f"mesh file, a shipped mesh: {', '.join(MESHES)}, or a "
                        f"generated scene: {', '.join(GENERATED_LABELS)} (default camel)")
    render.add_argument("--scene", default=None, metavar="NAME|FILE",
                        help="render a scene with the Whitted tree: a built-in name (camel, "
                        "glass-camel, mirror-camel) or a .toml scene file")
    render.add_argument("-o", "--output", default=None,
                        help="PNG path (default MESH.png, camel.png without a mesh, or "
                        "SCENE-NAME.png with --scene)")
    render.add_argument("--width", type=_positive_int, default=None,
                        help="pixels (default 640, or the scene's camera)")
    render.add_argument("--height", type=_positive_int, default=None,
                        help="pixels (default 480, or the scene's camera)")
    render.add_argument("--depth", type=_positive_int, default=None,
                        help="--scene: levels of the Whitted tree (default the scene's)")
    render.add_argument("--samples", type=_positive_int, default=None,
                        help="--scene: wavelength samples with dispersion (default the scene's)")
    render.add_argument("--spp", type=_positive_int, default=1,
                        help="--scene: camera rays per pixel at stratified sub-pixel positions "
                        "(anti-aliasing; default 1, the pixel centre)")
    render.add_argument("--turntable", type=_frames, default=None, metavar="N",
                        help="N frames of the scene (default the camel scene) around the "
                        "camera's target (360/N degrees about +y) in one batch: -o DIR "
                        "(default SCENE-turntable) gets frame_000.png... and turntable.gif")
    render.add_argument("--sweep", default=None, metavar="MATERIAL.FIELD=START:STOP:N",
                        help="N linearly spaced values of a material field of the scene "
                        "(default the camel scene) in one batch (dielectric index, A, B; "
                        "diffuse albedo; mirror reflectance), e.g. glass.B=0.002:0.02:8; "
                        "-o PNG (default SCENE-sweep.png) gets a contact sheet")
    mesh_only = "; mesh renders only (a scene has its own)"
    render.add_argument("--vfov", type=float, default=30.0,
                        help=f"vertical field of view, degrees{mesh_only}")
    render.add_argument("--azimuth", type=float, default=50.0,
                        help=f"degrees around the up axis{mesh_only}")
    render.add_argument("--elevation", type=float, default=20.0,
                        help=f"degrees above the horizon{mesh_only}")
    render.add_argument("--ambient", type=float, default=0.15,
                        help=f"ambient share in [0, 1]{mesh_only}")
    render.add_argument("--no-shadows", action="store_true",
                        help=f"skip the shadow rays{mesh_only}")
    render.add_argument("--crease-angle", type=_crease_angle, default=None, metavar="DEG",
                        help="edges whose faces meet at more than DEG degrees shade sharp, "
                        "the others smooth (0 flat, 180 all smooth; default 30, or with "
                        "--scene each object's crease_angle, which DEG then replaces)")
    common(render, scene_default=True)
    render.set_defaults(run=_cmd_render)

    registered = registered_commands()
    for name, entry_point in registered.items():
        what = command_summary(entry_point) if describe else ""
        sub.add_parser(name, add_help=False, help=f"{what} (options: jrt {name} --help)")
    for name in STUDY_COMMANDS:
        if name not in registered:
            sub.add_parser(name, add_help=False, help="not installed here (see jrt "
                           f"{name}): a full install of jrt registers it")
    return parser


def registered_commands() -> dict[str, importlib.metadata.EntryPoint]:
    """The commands registered under :data:`COMMAND_GROUP`, by name: the study's in
    :data:`STUDY_COMMANDS` order, then any other in alphabetical order. Nothing is
    imported."""
    found: dict[str, importlib.metadata.EntryPoint] = {}
    for entry_point in importlib.metadata.entry_points(group=COMMAND_GROUP):
        if entry_point.name not in LIBRARY_COMMANDS:
            found.setdefault(entry_point.name, entry_point)
    order = {name: i for i, name in enumerate(STUDY_COMMANDS)}
    return {name: found[name]
            for name in sorted(found, key=lambda n: (order.get(n, len(order)), n))}


def command_summary(entry_point: importlib.metadata.EntryPoint) -> str:
    """A registered command's line of help: the first paragraph of its module's docstring
    as plain text, read from the source without importing the module (or its package)."""
    source = _module_source(entry_point.module)
    try:
        doc = ast.get_docstring(ast.parse(source.read_bytes())) if source else None
    except (OSError, SyntaxError, ValueError):
        doc = None
    if not doc:
        return (f"provided by {entry_point.value}" if source else
                f"not available: {entry_point.module} is not installed")
    first = " ".join(doc.split("\n\n")[0].split()).rstrip(".")
    if first[1:2].islower():  # a sentence's capital, not an acronym's: "the ..." as above
        first = first[0].lower() + first[1:]
    # reStructuredText markup (``code``, :role:`name`) has no place in a terminal.
    return re.sub(r"``(.+?)``|:\w+:`~?(.+?)`", lambda m: m.group(1) or m.group(2), first)


def _module_source(module: str) -> Path | None:
    """The source file of a dotted module name, found without importing anything: the
    top-level package's spec (which imports nothing), then the file under its folder."""
    top, *rest = module.split(".")
    try:
        spec = importlib.util.find_spec(top)
    except (ImportError, ValueError):
        return None
    if spec is None:
        return None
    if not rest:
        return Path(spec.origin) if spec.origin else None
    for folder in spec.submodule_search_locations or ():
        base = Path(folder, *rest)
        for candidate in (base.with_suffix(".py"), base / "__init__.py"):
            if candidate.is_file():
                return candidate
    return None


def _run_registered(name: str, argv: list[str]) -> int:
    """Run the registered command ``name``'s ``main(argv, prog="jrt NAME")`` (its usage
    and errors name the command); a command that is not installed, or whose module cannot
    be imported, is an error that says which and how to get it."""
    entry_point = registered_commands().get(name)
    if entry_point is None:
        present = ", ".join(registered_commands()) or "none"
        print(f"jrt {name}: error: not installed here: no entry point '{name}' in the group "
              f"'{COMMAND_GROUP}' (registered: {present}). It comes with a full install of "
              "jrt, with the packages above the library: pip install -e . in the "
              "repository.", file=sys.stderr)
        return 2
    try:
        command_main = entry_point.load()
    except ModuleNotFoundError as exc:
        print(f"jrt {name}: error: registered as {entry_point.value} ('{COMMAND_GROUP}'), "
              f"but {exc}: reinstall jrt with all its packages and dependencies "
              "(pip install -e . in the repository).", file=sys.stderr)
        return 2
    result = command_main(argv, prog=f"jrt {name}")
    return result if isinstance(result, int) else 0


def main(argv: list[str] | None = None) -> int:
    # The command owns its process: keep freed memory for the next call (jrt._xla).
    jrt.tune_malloc()
    parser = build_parser()
    args, extra = parser.parse_known_args(argv)
    with _notes(args.command):
        if args.command not in LIBRARY_COMMANDS:
            return _run_registered(args.command, extra)
        if extra:
            parser.error(f"unrecognized arguments: {' '.join(extra)}")
        if args.command in CACHED:
            enable_compile_cache(command=f"jrt {args.command}")
        try:
            return args.run(args)
        except (MeshError, RaysFileError, FileNotFoundError, ValueError) as exc:
            print(f"jrt {args.command}: error: {exc}", file=sys.stderr)
            return 2


@contextlib.contextmanager
def _notes(command: str):
    """jrt's own warnings (:class:`jrt.mesh.MeshWarning`: degenerate triangles, polygons
    split into triangles) printed as ``jrt COMMAND: note: ...`` on stderr, every time and
    without Python's source line; other warnings as Python shows them."""
    with warnings.catch_warnings():
        warnings.simplefilter("always", MeshWarning)
        python_show = warnings.showwarning

        def show(message, category, filename, lineno, file=None, line=None):
            if issubclass(category, MeshWarning):
                print(f"jrt {command}: note: {message}", file=sys.stderr)
            else:
                python_show(message, category, filename, lineno, file, line)

        warnings.showwarning = show
        yield


if __name__ == "__main__":
    sys.exit(main())
