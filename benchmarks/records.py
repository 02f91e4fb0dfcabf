"""Writing a benchmark's JSON record, the same way for every script."""

from __future__ import annotations

import json
from pathlib import Path


def write_record(record: dict, path: str) -> Path:
    """Write ``record`` as indented JSON to ``path`` (folders created) and say where."""
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(record, indent=2))
    print(f"-> {out}")
    return out
