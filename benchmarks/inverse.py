"""Worked inverse problems: parameters recovered from a target image by gradient descent.

    python -m benchmarks.inverse [--problem glass|depth|both] [--width 48] [--height 36]
                                 [--steps 150] [--quick] [--json PATH] [--plot PATH]

``glass``: the glass camel rendered with BK7's Cauchy coefficients (A, B) = (1.50459,
0.004202) is the target; the search starts from fused silica's (1.44826, 0.003506) and
minimises the mean squared difference of the linear images with Adam (optax), in units of
the start values (so that A and B, three orders of magnitude apart, move alike); the
gradients come from ``jrt.wavefront.renderer(..., differentiable=True)``. ``depth``: the
19k camel translated by 5 % of its diagonal and scaled by 1.05 is found again from a
depth image of the camel where it was built (``t`` of ``jrt.closest_hit`` on
``jrt.refit`` of its BVH). See ``docs/gradients.md``; the record (``"kind": "inverse"``,
which ``reports.report`` draws) holds the loss and the parameters at every step and the
error at the end. ``--quick`` (what ``jrt study --quick`` runs): the depth problem alone,
at 32x24 pixels.
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np

import jrt  # noqa: F401  (XLA flags before JAX starts)
from benchmarks.common import command_line, write_record

PROG = "python -m benchmarks.inverse"


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=PROG, description=__doc__.split("\n\n")[0])
    p.add_argument("--problem", default="both", choices=("glass", "depth", "both"))
    p.add_argument("--width", type=int, default=48)
    p.add_argument("--height", type=int, default=36)
    p.add_argument("--depth", type=int, default=4, help="tree levels of the glass camel")
    p.add_argument("--steps", type=int, default=150, help="Adam steps (default 150)")
    p.add_argument("--rate", type=float, default=0.02, help="Adam's learning rate, in units "
                   "of the start values (default 0.02)")
    p.add_argument("--quick", action="store_true", help="the depth problem alone at 32x24 "
                   "(a smoke test: seconds instead of a minute)")
    p.add_argument("--json", default=None, help="write the record here")
    p.add_argument("--plot", default=None, help="draw the loss and parameter curves here "
                   "(PNG)")
    return p


def descend(image_of, target, start, unit, steps, rate):
    """Adam on ``x``, the parameters ``start + x * unit`` (so that parameters of different
    magnitudes move alike), from ``x = 0``, minimising the mean squared difference of
    ``image_of(parameters)`` and ``target``: the loss and the parameters at every step."""
    import jax
    import jax.numpy as jnp
    import optax

    start, unit = jnp.asarray(start, jnp.float32), jnp.asarray(unit, jnp.float32)

    def value_of(x):
        return start + x * unit

    def loss(x):
        return jnp.mean((image_of(value_of(x)) - target) ** 2)

    step_fn = jax.jit(jax.value_and_grad(loss))
    # Cosine decay to 1 % of the rate: large steps first, then small ones that settle in
    # the minimum (a glass image is very sensitive to A, and its loss is rugged).
    optimiser = optax.adam(optax.cosine_decay_schedule(rate, steps, alpha=0.01))
    x = jnp.zeros_like(start)
    state = optimiser.init(x)
    losses, values = [], []
    for _ in range(steps):
        value, grad = step_fn(x)
        losses.append(float(value))
        values.append(np.asarray(value_of(x)).tolist())
        updates, state = optimiser.update(grad, state)
        x = optax.apply_updates(x, updates)
    losses.append(float(loss(x)))
    values.append(np.asarray(value_of(x)).tolist())
    return losses, values


def glass_problem(args) -> dict:
    import jax.numpy as jnp

    from jrt import wavefront
    from jrt.optics import GLASSES

    render, params = wavefront.renderer("glass-camel", width=args.width, height=args.height,
                                        max_depth=args.depth, differentiable=True)
    truth = np.float32(GLASSES["BK7"])
    glass = params["materials"]["glass"]
    assert np.allclose([float(glass["A"]), float(glass["B"])], truth)
    target = render(params)  # also sizes the levels
    start = np.float32(GLASSES["fused silica"])

    def image_of(ab):
        glass = {"A": ab[0], "B": ab[1]}
        return render({**params, "materials": {**params["materials"], "glass": glass}})

    begun = time.perf_counter()
    losses, values = descend(image_of, jnp.asarray(target), start, start, args.steps,
                             args.rate)
    found = np.asarray(values[-1])
    return {"problem": "glass", "parameters": ["A", "B"], "truth": truth.tolist(),
            "start": start.tolist(), "found": found.tolist(),
            "relative_error": (np.abs(found - truth) / truth).tolist(),
            "losses": losses, "values": values, "seconds": time.perf_counter() - begun}


def depth_problem(args) -> dict:
    """The 19k camel moved (translated by 5 % of its diagonal, scaled by 1.05) recovered
    from a depth image of the camel where it was built: ``t`` of the camera rays through
    ``jrt.refit`` of its BVH, differentiated with respect to the translation and the scale
    (module docstring)."""
    import jax.numpy as jnp

    import accel
    from jrt.camera import camera_rays, frame_mesh
    from jrt.mesh import load_mesh

    mesh = load_mesh(jrt.mesh_path("camel-19k"))
    vertices, faces = jnp.asarray(mesh.vertices), mesh.faces
    centre = vertices.mean(axis=0)
    structure = accel.build("bvh", mesh.vertices, faces)
    origins, directions = camera_rays(frame_mesh(mesh.vertices, args.width, args.height))
    far = np.float32(3 * mesh.diagonal)  # the depth of a pixel that sees nothing

    def depth(x):
        moved = (vertices - centre) * x[3] + centre + x[:3]
        hits = jrt.closest_hit(jrt.refit(structure, moved, faces), origins, directions)
        return jnp.where(hits.triangle >= 0, hits.t, far)

    truth = np.float32([0.0, 0.0, 0.0, 1.0])
    target = depth(jnp.asarray(truth))
    offset = 0.05 * mesh.diagonal / np.sqrt(3)
    start = np.float32([offset, -offset, offset, 1.05])

    begun = time.perf_counter()
    unit = np.float32([offset, offset, offset, 0.05])
    losses, values = descend(lambda x: depth(x) / mesh.diagonal, target / mesh.diagonal,
                             start, unit, args.steps, args.rate)
    found = np.asarray(values[-1])
    error = np.abs(found - truth)
    return {"problem": "depth", "parameters": ["tx", "ty", "tz", "scale"],
            "truth": truth.tolist(), "start": start.tolist(), "found": found.tolist(),
            "translation_error_over_diagonal": float(np.linalg.norm(error[:3])
                                                     / mesh.diagonal),
            "scale_error": float(error[3]), "losses": losses, "values": values,
            "seconds": time.perf_counter() - begun}


def draw(record: dict, fig) -> None:
    """The loss (left) and each parameter's distance to the truth in units of its start
    distance (right) against the Adam step, one row of axes a problem, on ``fig``."""
    problems = record["problems"]
    axes = fig.subplots(len(problems), 2, squeeze=False)
    for row, problem in zip(axes, problems, strict=True):
        row[0].semilogy(problem["losses"])
        row[0].set_title(f"{problem['problem']}: loss (mean squared difference)")
        row[0].set_xlabel("Adam step")
        values = np.asarray(problem["values"])
        truth, start = np.asarray(problem["truth"]), np.asarray(problem["start"])
        for k, name in enumerate(problem["parameters"]):
            row[1].plot((values[:, k] - truth[k]) / abs(start[k] - truth[k]), label=name)
        row[1].axhline(0, color="black", linewidth=0.5)
        row[1].set_title(f"{problem['problem']}: (value - truth) / |start - truth|")
        row[1].set_xlabel("Adam step")
        row[1].legend()


def figure_size(record: dict) -> tuple[float, float]:
    return 10.0, 3.2 * len(record["problems"])


def plot(record: dict, path: str) -> None:
    from matplotlib.figure import Figure  # no pyplot: no global backend or figure state

    fig = Figure(figsize=figure_size(record))
    draw(record, fig)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    print(f"-> {path}")


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    if args.quick:
        args.problem, args.width, args.height = "depth", 32, 24
    problems = []
    if args.problem in ("glass", "both"):
        problems.append(glass_problem(args))
    if args.problem in ("depth", "both"):
        problems.append(depth_problem(args))
    record = {"kind": "inverse", "command": command_line(PROG, argv),
              "date": time.strftime("%Y-%m-%d"), "width": args.width,
              "height": args.height, "steps": args.steps, "rate": args.rate,
              "quick": bool(args.quick), "problems": problems}
    for p in problems:
        if "relative_error" in p:
            error = "relative errors " + ", ".join(
                f"{n} {e:.2%}" for n, e in zip(p["parameters"], p["relative_error"], strict=True))
        else:
            error = (f"translation {p['translation_error_over_diagonal']:.3%} of the "
                     f"diagonal from the truth (started at 5 %), scale off by "
                     f"{p['scale_error']:.3%} (started at 5 %)")
        print(f"{p['problem']}: loss {p['losses'][0]:.3g} -> {p['losses'][-1]:.3g} in "
              f"{len(p['losses']) - 1} steps ({p['seconds']:.0f} s); found "
              f"{np.round(p['found'], 6).tolist()}, truth {np.round(p['truth'], 6).tolist()}: "
              f"{error}")
    if args.json:
        write_record(record, args.json)
    if args.plot:
        plot(record, args.plot)
    return 0


if __name__ == "__main__":
    sys.exit(main())
