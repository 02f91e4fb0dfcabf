"""What every benchmark script shares: the best-of-n timer and the JSON record writer."""

from __future__ import annotations

import json
import time
from pathlib import Path


def write_record(record: dict, path: str) -> Path:
    """Write ``record`` as indented JSON to ``path`` (folders created) and say where."""
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(record, indent=2))
    print(f"-> {out}")
    return out


def best_time(fn, repeats: int) -> float:
    """The shortest wall time of ``repeats`` calls of ``fn`` (seconds)."""
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return min(times)
