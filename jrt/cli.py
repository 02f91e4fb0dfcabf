"""The ``jrt`` command line: ``jrt trace`` and ``jrt render``."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

import accel
import jrt  # noqa: F401  (applies the XLA flags before JAX starts)
from jrt.data import camel_path
from jrt.kernels import DEFAULT_KERNEL, KERNELS
from jrt.mesh import MeshError, load_mesh
from jrt.rays_io import RaysFileError, load_rays, save_hits


def _mesh(arg: str | None):
    """A path, or a short name of the project's meshes (camel, camel-19k)."""
    if arg is None or arg in ("camel", "camel-19k"):
        return load_mesh(camel_path(arg or "camel"))
    return load_mesh(arg)


def _cmd_trace(args) -> int:
    from jrt.trace import as_numpy, closest_hit, occluded

    mesh = _mesh(args.mesh)
    origins, directions, tmax = load_rays(args.rays)
    print(mesh.summary())
    structure = accel.build(args.accel, mesh.vertices, mesh.faces)
    start = time.perf_counter()
    if args.any_hit:
        result = {"occluded": np.asarray(occluded(structure, origins, directions, tmax,
                                                  kernel=args.kernel))}
        summary = f"{int(result['occluded'].sum()):,} occluded"
    else:
        result = as_numpy(closest_hit(structure, origins, directions, kernel=args.kernel,
                                      tmax=tmax))
        summary = f"{int((result['triangle'] >= 0).sum()):,} hits"
    seconds = time.perf_counter() - start
    out = save_hits(args.output, **result)
    n = len(origins)
    print(f"{n:,} rays, {summary}, {seconds:.2f} s ({n / seconds / 1e6:.3f} Mrays/s, "
          f"compile included) -> {out}")
    return 0


def _cmd_render(args) -> int:
    from skimage import io

    from jrt.camera import frame_mesh
    from jrt.render import render_lambert, to_srgb8

    mesh = _mesh(args.mesh)
    print(mesh.summary())
    structure = accel.build(args.accel, mesh.vertices, mesh.faces)
    camera = frame_mesh(mesh.vertices, width=args.width, height=args.height, vfov=args.vfov,
                        azimuth=args.azimuth, elevation=args.elevation)
    image, stats = render_lambert(mesh, structure, camera, kernel=args.kernel,
                                  shadows=not args.no_shadows, ambient=args.ambient)
    out = Path(args.output)
    out.parent.mkdir(parents=True, exist_ok=True)
    io.imsave(out, to_srgb8(image), check_contrast=False)
    print(f"{args.accel}/{args.kernel} {stats.summary()} (compile included) -> {out}")
    return 0


def _positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be a positive integer, got {text}")
    return value


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="jrt", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)

    def common(p):
        p.add_argument("--kernel", choices=tuple(KERNELS), default=DEFAULT_KERNEL,
                       help=f"ray-triangle kernel (default {DEFAULT_KERNEL})")
        p.add_argument("--accel", choices=accel.NAMES, default="bvh",
                       help="acceleration structure (default bvh; brute is the oracle)")

    trace = sub.add_parser("trace", help="closest hits (or occlusion) of rays from a file")
    trace.add_argument("mesh", help="mesh file (OFF/OBJ/PLY/STL), or 'camel' / 'camel-19k'")
    trace.add_argument("rays",
                       help=".npz with origins, directions float32 [N,3], optional tmax [N]")
    trace.add_argument("-o", "--output", required=True, help="output .npz of hits")
    trace.add_argument("--any-hit", action="store_true",
                       help="write 'occluded' (any hit before tmax) instead of closest hits")
    common(trace)
    trace.set_defaults(run=_cmd_trace)

    render = sub.add_parser("render", help="render a mesh (default: the camel) to a PNG")
    render.add_argument("mesh", nargs="?", default=None,
                        help="mesh file or 'camel' / 'camel-19k' (default camel)")
    render.add_argument("-o", "--output", default="camel.png", help="PNG path (default camel.png)")
    render.add_argument("--width", type=_positive_int, default=640)
    render.add_argument("--height", type=_positive_int, default=480)
    render.add_argument("--vfov", type=float, default=30.0, help="vertical field of view, degrees")
    render.add_argument("--azimuth", type=float, default=50.0, help="degrees around the up axis")
    render.add_argument("--elevation", type=float, default=20.0, help="degrees above the horizon")
    render.add_argument("--ambient", type=float, default=0.15, help="ambient share in [0, 1]")
    render.add_argument("--no-shadows", action="store_true", help="skip the shadow rays")
    common(render)
    render.set_defaults(run=_cmd_render)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.run(args)
    except (MeshError, RaysFileError, FileNotFoundError, ValueError) as exc:
        print(f"jrt {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
