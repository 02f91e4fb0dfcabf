"""What a gradient of a render costs: the reverse pass against the forward render, in one
process.

    python -m benchmarks.render_gradient [--scene glass-camel] [--width 96] [--height 72]
                                         [--depth 4] [--rounds 5] [--json PATH]

Three programs on the same parameters, each compiled first, then timed in turn
(``benchmarks.common.interleaved_times``): the renderer's forward render
(``jrt.wavefront.renderer``), the same with ``differentiable=True`` (its loops of static
length), and ``jax.value_and_grad`` of a weighted sum of that image with respect to every
parameter. The ratio quoted is the gradient's median time over the forward render's.
"""

from __future__ import annotations

import argparse
import platform
import sys
import time

import numpy as np

import jrt  # noqa: F401  (XLA flags before JAX starts)
from benchmarks.common import command_line, interleaved_times, write_record

PROG = "python -m benchmarks.render_gradient"


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=PROG, description=__doc__.split("\n\n")[0])
    p.add_argument("--scene", default="glass-camel", help="a built-in scene or a TOML file")
    p.add_argument("--width", type=int, default=96)
    p.add_argument("--height", type=int, default=72)
    p.add_argument("--depth", type=int, default=4, help="tree levels (default 4)")
    p.add_argument("--rounds", type=int, default=5, help="timing rounds (default 5)")
    p.add_argument("--json", default=None, help="also write the record here")
    return p


def run(args) -> dict:
    import jax
    import jax.numpy as jnp

    from jrt import wavefront

    size = dict(width=args.width, height=args.height, max_depth=args.depth)
    forward, params = wavefront.renderer(args.scene, **size)
    smooth, _ = wavefront.renderer(args.scene, differentiable=True, **size)
    image = np.asarray(forward(params))  # sizes the capacities (a render outside jit)
    smooth.capacities = forward.capacities
    weights = jnp.asarray(np.random.default_rng(0).uniform(0.5, 1.5, image.shape),
                          jnp.float32)
    gradient = jax.jit(jax.value_and_grad(lambda p: jnp.sum(weights * smooth(p))))
    start = time.perf_counter()
    jax.block_until_ready(gradient(params))
    compile_seconds = time.perf_counter() - start
    jax.block_until_ready(smooth(params))
    times = interleaved_times({
        "forward": lambda: jax.block_until_ready(forward(params)),
        "forward (differentiable)": lambda: jax.block_until_ready(smooth(params)),
        "value_and_grad": lambda: jax.block_until_ready(gradient(params)),
    }, args.rounds)
    medians = {k: float(np.median(v)) for k, v in times.items()}
    return {
        "kind": "render_gradient", "command": command_line(PROG),
        "date": time.strftime("%Y-%m-%d"),
        "machine": {"platform": platform.platform(), "jax": jax.__version__,
                    "devices": [str(d) for d in jax.devices()]},
        "scene": args.scene, **size, "rounds": args.rounds, "seconds": times,
        "median_seconds": medians, "gradient_compile_seconds": compile_seconds,
        "rays_per_level": list(forward.last_stats.rays_per_level),
        "ratio_gradient_to_forward": medians["value_and_grad"] / medians["forward"],
        "ratio_gradient_to_differentiable_forward":
            medians["value_and_grad"] / medians["forward (differentiable)"],
    }


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    record = run(args)
    m = record["median_seconds"]
    print(f"{record['scene']} {args.width}x{args.height}, depth {args.depth}, rays per level "
          f"{record['rays_per_level']} (median of {args.rounds} rounds, in turn):")
    for name, seconds in m.items():
        print(f"  {name:<26} {seconds * 1e3:9.1f} ms")
    print(f"  gradient / forward: {record['ratio_gradient_to_forward']:.2f}x "
          f"(/ differentiable forward: "
          f"{record['ratio_gradient_to_differentiable_forward']:.2f}x); gradient compiled in "
          f"{record['gradient_compile_seconds']:.1f} s")
    if args.json:
        write_record(record, args.json)
    return 0


if __name__ == "__main__":
    sys.exit(main())
