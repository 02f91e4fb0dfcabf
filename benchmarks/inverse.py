"""Worked inverse problems: parameters recovered from a target render by gradient descent.

    python -m benchmarks.inverse [--problem glass|lamp|both] [--width 48] [--height 36]
                                 [--steps 150] [--json PATH] [--plot PATH]

``glass``: the glass camel rendered with BK7's Cauchy coefficients (A, B) = (1.50459,
0.004202) is the target; the search starts from fused silica's (1.44826, 0.003506) and
minimises the mean squared difference of the linear images with Adam (optax), in units of
the start values (so that A and B, three orders of magnitude apart, move alike). ``lamp``:
the diffuse camel's lamp, moved by 20 % of the camel's diagonal, is found again from the
render with the lamp where the scene puts it. Each problem's gradients come from
``jrt.wavefront.renderer(..., differentiable=True)`` (``docs/gradients.md``); the record
holds the loss and the parameters at every step and the relative error at the end.
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
    p.add_argument("--problem", default="both", choices=("glass", "lamp", "both"))
    p.add_argument("--width", type=int, default=48)
    p.add_argument("--height", type=int, default=36)
    p.add_argument("--depth", type=int, default=4, help="tree levels of the glass camel")
    p.add_argument("--steps", type=int, default=150, help="Adam steps (default 150)")
    p.add_argument("--rate", type=float, default=0.02, help="Adam's learning rate, in units "
                   "of the start values (default 0.02)")
    p.add_argument("--json", default=None, help="write the record here")
    p.add_argument("--plot", default=None, help="draw the loss and parameter curves here "
                   "(PNG)")
    return p


def descend(render, params, target, put, start, steps, rate):
    """Adam on ``x`` (the parameters in units of ``start``): the loss and ``x * start`` at
    every step."""
    import jax
    import jax.numpy as jnp
    import optax

    scale = jnp.asarray(start, jnp.float32)

    def loss(x):
        image = render(put(params, x * scale))
        return jnp.mean((image - target) ** 2)

    step_fn = jax.jit(jax.value_and_grad(loss))
    optimiser = optax.adam(rate)
    x = jnp.ones_like(scale)
    state = optimiser.init(x)
    losses, values = [], []
    for _ in range(steps):
        value, grad = step_fn(x)
        losses.append(float(value))
        values.append(np.asarray(x * scale).tolist())
        updates, state = optimiser.update(grad, state)
        x = optax.apply_updates(x, updates)
    losses.append(float(loss(x)))
    values.append(np.asarray(x * scale).tolist())
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

    def put(p, ab):
        q = {**p, "materials": {**p["materials"], "glass": {"A": ab[0], "B": ab[1]}}}
        return q

    begun = time.perf_counter()
    losses, values = descend(render, params, jnp.asarray(target), put, start,
                             args.steps, args.rate)
    found = np.asarray(values[-1])
    return {"problem": "glass", "parameters": ["A", "B"], "truth": truth.tolist(),
            "start": start.tolist(), "found": found.tolist(),
            "relative_error": (np.abs(found - truth) / truth).tolist(),
            "losses": losses, "values": values, "seconds": time.perf_counter() - begun}


def lamp_problem(args) -> dict:
    import jax.numpy as jnp

    from jrt import wavefront

    render, params = wavefront.renderer("camel", width=args.width, height=args.height,
                                        differentiable=True)
    truth = np.asarray(params["lamps"][0]["position"], np.float32)
    target = render(params)
    diagonal = float(np.linalg.norm(np.ptp(render.setup.geometry.vertices, axis=0)))
    direction = np.float32([1.0, -0.5, 0.8])
    start = truth + 0.2 * diagonal * direction / np.linalg.norm(direction)

    def put(p, position):
        lamps = [{**p["lamps"][0], "position": position}, *p["lamps"][1:]]
        return {**p, "lamps": lamps}

    begun = time.perf_counter()
    losses, values = descend(render, params, jnp.asarray(target), put, start,
                             args.steps, args.rate)
    found = np.asarray(values[-1])
    return {"problem": "lamp", "parameters": ["x", "y", "z"], "truth": truth.tolist(),
            "start": start.tolist(), "found": found.tolist(),
            "distance_over_diagonal": float(np.linalg.norm(found - truth) / diagonal),
            "start_distance_over_diagonal": 0.2,
            "losses": losses, "values": values, "seconds": time.perf_counter() - begun}


def plot(record: dict, path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    problems = record["problems"]
    fig, axes = plt.subplots(len(problems), 2, figsize=(10, 3.2 * len(problems)),
                             squeeze=False)
    for row, problem in zip(axes, problems, strict=True):
        row[0].semilogy(problem["losses"])
        row[0].set_title(f"{problem['problem']}: loss (mean squared difference)")
        row[0].set_xlabel("Adam step")
        values = np.asarray(problem["values"])
        truth = np.asarray(problem["truth"])
        for k, name in enumerate(problem["parameters"]):
            row[1].plot((values[:, k] - truth[k]) / abs(truth[k]), label=name)
        row[1].axhline(0, color="black", linewidth=0.5)
        row[1].set_title(f"{problem['problem']}: (value - truth) / |truth|")
        row[1].set_xlabel("Adam step")
        row[1].legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    print(f"-> {path}")


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    problems = []
    if args.problem in ("glass", "both"):
        problems.append(glass_problem(args))
    if args.problem in ("lamp", "both"):
        problems.append(lamp_problem(args))
    record = {"kind": "inverse", "command": command_line(PROG, argv),
              "date": time.strftime("%Y-%m-%d"), "width": args.width,
              "height": args.height, "steps": args.steps, "rate": args.rate,
              "problems": problems}
    for p in problems:
        if "relative_error" in p:
            error = "relative errors " + ", ".join(
                f"{n} {e:.2%}" for n, e in zip(p["parameters"], p["relative_error"], strict=True))
        else:
            error = (f"{p['distance_over_diagonal']:.2%} of the diagonal from the truth "
                     "(started at 20 %)")
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
