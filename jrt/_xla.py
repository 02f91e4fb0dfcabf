"""XLA:CPU settings jrt needs, applied before JAX starts its CPU backend.

``--xla_cpu_use_fusion_emitters=false``: XLA:CPU's newer fusion emitters compile the
triangle-test fusions inside ``lax.scan``/``while_loop`` bodies to code 4-6x slower than
the classic emitter (measured on the camel, jax 0.10.2: Möller–Trumbore brute force at 120
vs 790 M tests/s on one core). Flags are read when the backend starts, so this only takes
effect if jrt is imported before the first JAX computation; an explicit setting of the
same flag in ``XLA_FLAGS`` is left as it is.
"""

from __future__ import annotations

import os

_FLAGS = ("--xla_cpu_use_fusion_emitters=false",)


def apply() -> None:
    current = os.environ.get("XLA_FLAGS", "")
    for flag in _FLAGS:
        name = flag.split("=")[0]
        if name not in current:
            current = f"{current} {flag}".strip()
    os.environ["XLA_FLAGS"] = current


apply()
