"""The JSON schema of the suite's results (``python -m benchmarks``), and a validator.

    from benchmarks.schema import SCHEMA, validate
    validate(json.load(open("out/bench.json")))   # ValueError naming the first problem

``SCHEMA`` is a JSON Schema (draft 2020-12) as a Python dict. :func:`validate` checks it
with a small built-in interpreter of the keywords used here (no dependency; ``jsonschema``
accepts the same schema), then a few facts a schema cannot state: every record names a
structure of the run, and repetition lists have the length the parameters asked for (a
trace's may be shorter where its calls reached ``parameters.trace_budget_seconds``). The
error names the path of the first problem, e.g. ``$.records[12].seconds.median``.

Layout: ``{"schema", "machine", "parameters", "records": [...], "notes", "wall_seconds"}``
with one record per measurement, told apart by ``kind``:

- ``build``: structure, mesh, triangles, repeats [s], seconds {median, min, max, spread},
  nodes, leaves, depth, references_per_leaf_mean/max, bytes, sah_cost, stats {...};
- ``trace``: structure, set, query, rays, hits, first_call_seconds, compile_seconds,
  repeats [s], seconds, mrays_per_s {median, min, max}, embree_mrays_per_s,
  ratio_to_embree, counters {steps, tests, leaves: {mean, p95, max}};
- ``peer``: peer (embree, trimesh, open3d, mitsuba), status (ok, not installed, failed,
  skipped), note, set, query, rays, threads, repeats, seconds, mrays_per_s,
  ratio_to_embree (numbers null unless ok);
- ``correctness``: structure, set, query, reference (brute), rays, reference_hits,
  mismatches, mismatches_by_field, embree_rays, embree_disagreements, and where the
  mismatches were judged by the float64 oracle, oracle {rays, structure_right, brute_right};
- ``scaling``: structure, set, rays, rows [{mesh, triangles, build_repeats,
  build_seconds, ns_per_n_log2_n, trace_repeats, trace_seconds, mrays_per_s,
  first_call_seconds, embree_mrays_per_s, ratio_to_embree, from_main_run}],
  build_exponent, trace_exponent;
- ``cost_model``: structure, c_ts_ns, c_it_ns, residual, points [{set, query, rays,
  seconds, steps_mean, tests_mean, predicted_seconds}];
- ``heatmap``: structure, set (camera), width, height, block, steps [[...]], tests [[...]]:
  the per-pixel counters of the camera rays, averaged over ``block``² pixel squares
  (row-major, ``height`` rows of ``width`` cells);
- ``turntable``: scene, mesh, frames, width, height, samples, max_depth,
  batched_images_per_s, loop_images_per_s, loop_same_capacities_images_per_s, ratio (batched
  over the faster loop), batch_devices, max_abs_difference (batch against the same-capacities
  loop, radiance), peak_radiance;
- ``trimesh_interface``: mesh, triangles, query (intersects_location, contains_points),
  engine (jrt, embree, trimesh), items (rays or points), threads (null: all cores), repeats,
  seconds, per_second, jrt_speedup (jrt's rate over this engine's); on jrt's record also
  first_call_seconds, found (hits, or points inside), trimesh_items, agree_with_trimesh
  (rays or points of those whose answer equals trimesh's own), agree_with_embree (of all).
"""

from __future__ import annotations

import math
import re

from accel import NAMES
from jrt.scenes import SCENES

STRUCTURES = [name for name in NAMES if name != "brute"]
SETS = ["camera", "shadow", "reflected", "refracted", "incoherent"]
QUERIES = ["closest", "occluded"]
PEERS = ["embree", "trimesh", "open3d", "mitsuba"]
STATUSES = ["ok", "not installed", "failed", "skipped"]

_NUM = {"type": "number"}
_NONNEG = {"type": "number", "minimum": 0}
_POS = {"type": "number", "exclusiveMinimum": 0}
_COUNT = {"type": "integer", "minimum": 0}
_POS_COUNT = {"type": "integer", "minimum": 1}
_STR = {"type": "string"}


def _obj(required: dict, optional: dict | None = None, extra: bool = True) -> dict:
    return {"type": "object", "required": list(required),
            "properties": {**required, **(optional or {})}, "additionalProperties": extra}


def _null(schema: dict) -> dict:
    return {"anyOf": [schema, {"type": "null"}]}


_REF = {name: {"$ref": f"#/$defs/{name}"} for name in (
    "seconds", "rates", "times", "counter", "build", "trace", "peer", "correctness",
    "scaling", "scaling_row", "cost_model", "cost_point", "heatmap", "image", "turntable",
    "trimesh_interface")}

DEFS = {
    "seconds": _obj({"median": _NONNEG, "min": _NONNEG, "max": _NONNEG, "spread": _NONNEG}),
    "rates": _obj({"median": _POS, "min": _POS, "max": _POS}),
    "times": {"type": "array", "items": _POS, "minItems": 1},
    "counter": _obj({"mean": _NONNEG, "p95": _NONNEG, "max": _COUNT}),
    "build": _obj({
        "kind": {"const": "build"}, "structure": {"enum": STRUCTURES}, "mesh": _STR,
        "triangles": _POS_COUNT, "repeats": _REF["times"], "seconds": _REF["seconds"],
        "nodes": _COUNT, "leaves": _COUNT, "depth": _COUNT,
        "references_per_leaf_mean": _NONNEG, "references_per_leaf_max": _NONNEG,
        "bytes": _POS_COUNT, "sah_cost": _null(_NONNEG), "stats": {"type": "object"}}),
    "trace": _obj({
        "kind": {"const": "trace"}, "structure": {"enum": STRUCTURES},
        "set": {"enum": SETS}, "query": {"enum": QUERIES}, "rays": _POS_COUNT,
        "distinct_rays": _POS_COUNT, "hits": _COUNT, "first_call_seconds": _POS,
        "compile_seconds": _NONNEG, "repeats": _REF["times"], "seconds": _REF["seconds"],
        "mrays_per_s": _REF["rates"], "embree_mrays_per_s": _POS, "ratio_to_embree": _POS,
        "counters": _obj({"steps": _REF["counter"], "tests": _REF["counter"],
                          "leaves": _REF["counter"]}),
        "counters_first_call_seconds": _POS}),
    "peer": {
        **_obj({
            "kind": {"const": "peer"}, "peer": {"enum": PEERS}, "status": {"enum": STATUSES},
            "note": _STR, "set": _null({"enum": SETS}), "query": _null({"enum": QUERIES}),
            "rays": _null(_POS_COUNT), "threads": _null(_POS_COUNT),
            "repeats": {"type": "array", "items": _POS},
            "seconds": _null(_REF["seconds"]), "mrays_per_s": _null(_REF["rates"]),
            "ratio_to_embree": _null(_POS)}),
        "if": {"properties": {"status": {"const": "ok"}}},
        "then": {"properties": {
            "set": {"enum": SETS}, "query": {"enum": QUERIES}, "rays": _POS_COUNT,
            "repeats": _REF["times"], "seconds": _REF["seconds"],
            "mrays_per_s": _REF["rates"], "ratio_to_embree": _POS}},
    },
    "correctness": _obj({
        "kind": {"const": "correctness"}, "structure": {"enum": STRUCTURES},
        "set": {"enum": SETS}, "query": {"enum": QUERIES}, "reference": {"const": "brute"},
        "rays": _POS_COUNT, "reference_hits": _COUNT, "mismatches": _COUNT,
        "mismatches_by_field": {"type": "object", "additionalProperties": _COUNT,
                                "minProperties": 1},
        "embree_rays": _POS_COUNT, "embree_disagreements": _COUNT},
        {"oracle": _obj({"rays": _POS_COUNT, "structure_right": _COUNT,
                         "brute_right": _COUNT})}),
    "scaling_row": _obj({
        "mesh": _STR, "triangles": _POS_COUNT, "build_repeats": _REF["times"],
        "build_seconds": _REF["seconds"], "ns_per_n_log2_n": _NONNEG,
        "trace_repeats": _REF["times"], "trace_seconds": _REF["seconds"],
        "mrays_per_s": _REF["rates"], "first_call_seconds": _POS,
        "embree_mrays_per_s": _POS, "ratio_to_embree": _POS,
        "from_main_run": {"type": "boolean"}}),
    "scaling": _obj({
        "kind": {"const": "scaling"}, "structure": {"enum": STRUCTURES},
        "set": {"enum": SETS}, "rays": _POS_COUNT,
        "rows": {"type": "array", "items": _REF["scaling_row"], "minItems": 1},
        "build_exponent": _null(_NUM), "trace_exponent": _null(_NUM)}),
    "cost_point": _obj({
        "set": {"enum": SETS}, "query": {"enum": QUERIES}, "rays": _POS_COUNT,
        "seconds": _POS, "steps_mean": _NONNEG, "tests_mean": _NONNEG,
        "predicted_seconds": _NONNEG}),
    "cost_model": _obj({
        "kind": {"const": "cost_model"}, "structure": {"enum": STRUCTURES},
        "c_ts_ns": _NONNEG, "c_it_ns": _NONNEG, "residual": _null(_NONNEG),
        "points": {"type": "array", "items": _REF["cost_point"], "minItems": 1},
        "fit": _STR, "time_basis": _STR}),
    "image": {"type": "array", "minItems": 1, "items": {
        "type": "array", "minItems": 1, "items": _NONNEG}},
    "heatmap": _obj({
        "kind": {"const": "heatmap"}, "structure": {"enum": STRUCTURES},
        "set": {"const": "camera"}, "width": _POS_COUNT, "height": _POS_COUNT,
        "block": _POS_COUNT, "steps": _REF["image"], "tests": _REF["image"]}),
    "turntable": _obj({
        "kind": {"const": "turntable"}, "scene": _STR, "mesh": _STR, "frames": _POS_COUNT,
        "width": _POS_COUNT, "height": _POS_COUNT, "samples": _POS_COUNT,
        "max_depth": _POS_COUNT, "batched_images_per_s": _POS, "loop_images_per_s": _POS,
        "loop_same_capacities_images_per_s": _POS, "ratio": _POS, "batch_devices": _POS_COUNT,
        "max_abs_difference": _NONNEG, "peak_radiance": _NONNEG}),
    "trimesh_interface": _obj({
        "kind": {"const": "trimesh_interface"}, "mesh": _STR, "triangles": _POS_COUNT,
        "query": {"enum": ["intersects_location", "contains_points"]},
        "engine": {"enum": ["jrt", "embree", "trimesh"]}, "items": _POS_COUNT,
        "threads": _null(_POS_COUNT), "repeats": _REF["times"], "seconds": _REF["seconds"],
        "per_second": _POS, "jrt_speedup": _POS},
        {"first_call_seconds": _POS, "found": _COUNT, "trimesh_items": _null(_POS_COUNT),
         "agree_with_trimesh": _null(_COUNT), "agree_with_embree": _null(_COUNT)}),
}

KINDS = ["build", "trace", "peer", "correctness", "scaling", "cost_model", "heatmap",
         "turntable", "trimesh_interface"]

SCHEMA = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "title": "jrt benchmark suite results",
    **_obj({
        "schema": {"const": "jrt-bench/1"},
        "machine": _obj({
            "cpu": _STR, "cores": _POS_COUNT, "os": _STR, "python": _STR,
            "device": _obj({"requested": _null({"enum": ["cpu", "gpu"]}), "platform": _STR,
                            "kind": _STR, "count": _POS_COUNT,
                            "devices": {"type": "array", "items": _STR, "minItems": 1}}),
            "versions": _obj({k: _null(_STR) for k in (
                "jax", "numpy", "embreex", "trimesh", "igl", "colour")}),
            "git_commit": _null({"type": "string", "pattern": "^[0-9a-f]{40}$"}),
            "date": {"type": "string", "pattern": r"^\d{4}-\d\d-\d\dT"}}),
        "parameters": _obj({
            "quick": {"type": "boolean"}, "mesh": _STR, "triangles": _POS_COUNT,
            "structures": {"type": "array", "items": {"enum": STRUCTURES}, "minItems": 1},
            "kernel": _STR, "camera": {"type": "object"}, "camera_rays": _POS_COUNT,
            "rays": _POS_COUNT,
            "sets": {"type": "array", "minItems": 1, "items": _obj({
                "name": {"enum": SETS}, "query": {"enum": QUERIES}, "rays": _POS_COUNT,
                "distinct_rays": _POS_COUNT})},
            "builds": _POS_COUNT, "repeats": _POS_COUNT, "brute_rays": _POS_COUNT,
            "trimesh_rays": _COUNT, "scaling_meshes": _COUNT, "scaling_builds": _POS_COUNT,
            "scaling_repeats": _POS_COUNT, "embree_threads": _POS_COUNT},
            {"scene": _null({"enum": list(SCENES)}), "trace_budget_seconds": _POS}),
        "records": {"type": "array", "minItems": 1, "items": {
            "type": "object", "required": ["kind"],
            "properties": {"kind": {"enum": KINDS}},
            "allOf": [{"if": {"properties": {"kind": {"const": k}}}, "then": _REF[k]}
                      for k in KINDS]}},
        "notes": {"type": "array", "items": _STR},
        "wall_seconds": _POS}),
    "$defs": DEFS,
}


# --- A small interpreter of the keywords above ----------------------------------------------


_TYPES = {
    "object": lambda x: isinstance(x, dict),
    "array": lambda x: isinstance(x, list),
    "string": lambda x: isinstance(x, str),
    "boolean": lambda x: isinstance(x, bool),
    "null": lambda x: x is None,
    "integer": lambda x: (isinstance(x, int) and not isinstance(x, bool))
    or (isinstance(x, float) and x.is_integer()),
    "number": lambda x: isinstance(x, int | float) and not isinstance(x, bool)
    and math.isfinite(x),
}


def _resolve(schema: dict, root: dict) -> dict:
    while "$ref" in schema:
        ref = schema["$ref"]
        if not ref.startswith("#/"):
            raise ValueError(f"schema: only local references are supported, got {ref}")
        node = root
        for part in ref[2:].split("/"):
            node = node[part]
        schema = node
    return schema


def _errors(value, schema: dict, path: str, root: dict):
    """Yield (path, message) for each violation, depth first, in document order."""
    schema = _resolve(schema, root)
    if "type" in schema:
        types = schema["type"] if isinstance(schema["type"], list) else [schema["type"]]
        if not any(_TYPES[t](value) for t in types):
            yield path, f"expected {' or '.join(types)}, got {type(value).__name__} {value!r:.60}"
            return
    if "const" in schema and value != schema["const"]:
        yield path, f"expected {schema['const']!r}, got {value!r:.60}"
    if "enum" in schema and value not in schema["enum"]:
        yield path, f"expected one of {schema['enum']}, got {value!r:.60}"
    if "anyOf" in schema:
        if not any(next(_errors(value, s, path, root), None) is None for s in schema["anyOf"]):
            first = next(_errors(value, schema["anyOf"][0], path, root))
            yield first[0], f"{first[1]} (or null)" if len(schema["anyOf"]) == 2 else first[1]
    for sub in schema.get("allOf", ()):
        yield from _errors(value, sub, path, root)
    if "if" in schema and next(_errors(value, schema["if"], path, root), None) is None:
        if "then" in schema:
            yield from _errors(value, schema["then"], path, root)
    elif "if" in schema and "else" in schema:
        yield from _errors(value, schema["else"], path, root)
    if isinstance(value, int | float) and not isinstance(value, bool):
        if "minimum" in schema and value < schema["minimum"]:
            yield path, f"expected >= {schema['minimum']}, got {value}"
        if "exclusiveMinimum" in schema and value <= schema["exclusiveMinimum"]:
            yield path, f"expected > {schema['exclusiveMinimum']}, got {value}"
        if "maximum" in schema and value > schema["maximum"]:
            yield path, f"expected <= {schema['maximum']}, got {value}"
    if isinstance(value, str) and "pattern" in schema:
        if not re.search(schema["pattern"], value):
            yield path, f"expected a string matching {schema['pattern']}, got {value!r:.60}"
    if isinstance(value, dict):
        for key in schema.get("required", ()):
            if key not in value:
                yield f"{path}.{key}", "required field is missing"
        if len(value) < schema.get("minProperties", 0):
            yield path, f"expected at least {schema['minProperties']} fields"
        properties = schema.get("properties", {})
        extra = schema.get("additionalProperties", True)
        for key, item in value.items():
            if key in properties:
                yield from _errors(item, properties[key], f"{path}.{key}", root)
            elif extra is False:
                yield f"{path}.{key}", "field not allowed here"
            elif isinstance(extra, dict):
                yield from _errors(item, extra, f"{path}.{key}", root)
    if isinstance(value, list):
        if len(value) < schema.get("minItems", 0):
            yield path, f"expected at least {schema['minItems']} items, got {len(value)}"
        if "items" in schema:
            for i, item in enumerate(value):
                yield from _errors(item, schema["items"], f"{path}[{i}]", root)


def _facts(results: dict):
    """What the schema cannot say: structures of the run, repetition counts."""
    params = results["parameters"]
    structures = set(params["structures"])
    for i, rec in enumerate(results["records"]):
        path = f"$.records[{i}]"
        if "structure" in rec and rec["structure"] not in structures:
            yield f"{path}.structure", (f"{rec['structure']!r} is not among the run's "
                                        f"structures {sorted(structures)}")
        if rec["kind"] == "heatmap":
            for key in ("steps", "tests"):
                rows = rec[key]
                if len(rows) != rec["height"] or any(len(r) != rec["width"] for r in rows):
                    yield f"{path}.{key}", (f"expected {rec['height']} rows of {rec['width']} "
                                            f"cells (height x width)")
        if rec["kind"] == "build" and len(rec["repeats"]) != params["builds"]:
            yield f"{path}.repeats", (f"expected {params['builds']} builds "
                                      f"(parameters.builds), got {len(rec['repeats'])}")
        timed = rec["kind"] == "trace" or (rec["kind"] == "peer" and rec["peer"] != "trimesh"
                                          and rec["status"] == "ok")
        # A structure's timed calls stop early once they have taken the trace budget.
        budget = params.get("trace_budget_seconds") if rec["kind"] == "trace" else None
        cut = (budget is not None and 1 <= len(rec["repeats"]) < params["repeats"]
               and sum(rec["repeats"]) >= budget)
        if timed and len(rec["repeats"]) != params["repeats"] and not cut:
            yield f"{path}.repeats", (f"expected {params['repeats']} repeats "
                                      f"(parameters.repeats), or fewer whose sum reaches "
                                      f"parameters.trace_budget_seconds, got "
                                      f"{len(rec['repeats'])}")


def validate(results) -> None:
    """Raise ValueError naming the path of the first problem; None when ``results`` fit."""
    for path, message in _errors(results, SCHEMA, "$", SCHEMA):
        raise ValueError(f"{path}: {message}")
    for path, message in _facts(results):
        raise ValueError(f"{path}: {message}")
