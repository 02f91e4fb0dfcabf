"""Numerical stability on stiff and extreme cases: a suite that tries to break jrt.

    python -m benchmarks.stability [-o stability.json] [--quick | --size SIZE] [--cases 1,2,...]
                                   [--structures brute,bvh,...] [--kernels watertight,...]

Nine cases, one module each, each run over kernel x structure pairs and checked against a
**float64 oracle**: jrt's own kernels are dtype-generic and run in float64 when given
float64 arrays under ``jax.enable_x64(True)`` (checked by :func:`float64_kernels_ok`), so
the oracle is the ``watertight`` kernel in float64, by brute force (:func:`brute_hits`), on
the same float32 geometry and rays as the traced ones (so it measures the kernels' and the
structures' own errors, not the rounding of the input).

1. ``closed_mesh``: rays through shared edges and vertices of the closed camel, from
   inside and outside: cracks, double hits (the first crossing reported by 2+ triangles)
   and crossing-parity errors per million rays.
2. ``grazing``: grazing rays (90 deg - 10^-k) and rays lying in a triangle's plane.
3. ``slivers``: degenerate and sliver triangles (the camel's quality < 0.01 slivers,
   synthetic needles and tiny triangles): misses and pass-throughs against a libigl-like
   Möller–Trumbore with a fixed 1e-6 determinant threshold (and libigl 2.6 itself, on a
   sample).
4. ``offsets``: self-intersection of reflected, refracted (n = 1.5) and shadow rays spawned
   at hits, with no offset, a fixed epsilon 1e-4, a scene-scaled epsilon 1e-4 x diagonal,
   the integer-ulp offset of Wächter & Binder (2019) and the renderer's pbrt-v4 offset.
5. ``anywhere``: scale (10^-6..10^6) and translation (10^0..10^7) of the camel: primary hit
   sets against the untranslated float64 reference, case 4's self-hits per method;
   pbrt-style random triangles with coordinates 10^U(-8, 8).
6. ``planes``: axis-parallel rays (+0.0 / -0.0 components) from origins exactly on the
   structures' node, cell and split planes, over axis-aligned flat triangles.
7. ``optics``: total internal reflection at the critical angle +- 1e-6 rad, Brewster,
   normal incidence, entering versus leaving, n = 1.0001 and 4, SF10 dispersion, and a
   glass camel at n = 2.4 trapping light (bounces until the weight falls below 1e-3).
8. ``boundaries``: wavelengths at the ends of the visible range; NaN and infinite inputs
   at the boundary.
9. ``deep_trees``: deep trees and long traversals: stack capacity, overflow reporting
   (probed in subprocesses, so that an XLA abort, or a traversal that runs to its
   iteration budget, cannot take the suite down), and stacks of nearly coplanar layers
   (the tie window is not transitive).

The JSON has, per case, ``records`` (one per kernel x structure, or per check where no
kernel applies: cracks, false hits, NaN, max error against the oracle in float32 ulps of
t, and case-specific fields), ``findings`` (a paragraph computed from those numbers),
``parameters`` and ``seconds``. Case functions (``case1`` ... ``case9``) take their sizes
as arguments so that ``tests/test_stability.py`` runs them small; ``--quick`` runs every
case at a size that takes about two minutes on two cores.

Record fields (against the oracle's first crossing, :func:`compare`): ``cracks`` (the
oracle hits, the traced ray misses, ``misses``, or hits beyond that crossing,
``pass_through``), ``false_hits`` (a hit where the oracle has none, or in front of its
crossing), ``borderline_hits`` (false hits whose point lies within 2^-17 of the coordinates
of the reported triangle: float32 rounding a grazing ray onto an edge, not counted as
false), ``near_origin`` (hits within 2^-12 |origin| of the origin, where a float32 t cannot
be resolved; counted apart), ``nan``, ``max_error_ulps`` (|t - t64| in float32 ulps of
max(t64, |origin|), over the agreeing rays), ``mismatches_vs_brute`` (the structure
against brute force with the same kernel, ties within 2^-20 t allowed).

Traces go through ``jrt.closest_hit`` in fixed chunks of :data:`CHUNK` rays (padding rays
have ``tmax = 0``), so each structure x kernel compiles once for the whole suite.

The modules: ``common`` (meshes and structures, tracing, the kernel x structure pairs from
the structure registry, records and their counts), ``float64_oracle`` (the oracle, the
libigl-like kernel, the comparison), one module per case (above), and ``cli`` (the sizes,
:func:`run`, :func:`main`). This package re-exports the names that the tests, the study
and the report use.
"""

from benchmarks.stability.anywhere import (
    ANYWHERE_UP_TO,
    case5,
    random_triangle_reintersection,
    transformed,
)
from benchmarks.stability.boundaries import bad_rays, boundary_checks, case8, nan_ray_outcomes
from benchmarks.stability.cli import (
    CASE_FUNCTIONS,
    CASE_TITLES,
    CASES,
    PROG,
    SIZES,
    _json_safe,
    main,
    quick_params,
    run,
    standard_params,
)
from benchmarks.stability.closed_mesh import (
    aimed_rays,
    case1,
    closed_mesh_rays,
    strictly_inside,
    winding_numbers,
)
from benchmarks.stability.common import (
    BUILD_MEMORY_LIMIT,
    CHUNK,
    KERNEL_NAMES,
    TIE,
    build,
    build_guarded,
    combos,
    default_combos,
    load,
    mismatches_vs,
    record,
    summary,
    trace,
    with_mismatches_vs_brute,
)
from benchmarks.stability.deep_trees import (
    case9,
    deep_chain,
    probe_worker,
    stack_probe,
    stacked_layers,
)
from benchmarks.stability.float64_oracle import (
    BORDER,
    LIBIGL_EPSILON,
    NEAR,
    brute_hits,
    compare,
    float64_kernels_ok,
    libigl_like,
    oracle,
    outside_distance,
    pairwise_hits,
    ulp32,
)
from benchmarks.stability.grazing import case2, grazing_rays, grazing_scene
from benchmarks.stability.offsets import (
    METHOD_LABELS,
    METHODS,
    case4,
    pbrt_offset_numpy,
    renderer_offset,
    secondary_rays,
    self_intersection,
    spawn,
    surface_frame,
    ulp_offset,
)
from benchmarks.stability.optics import _findings7, case7, glass_trapping, optics_checks
from benchmarks.stability.planes import case6, lattice_scene, plane_rays
from benchmarks.stability.slivers import (
    case3,
    libigl_first_hits,
    sliver_rays,
    synthetic_degenerates,
    triangle_quality,
)

# _json_safe and _findings7 are read by tests/test_report.py (a case 7 made of the
# optics checks alone); the rest of the package uses neither.
__all__ = [
    "ANYWHERE_UP_TO", "BORDER", "BUILD_MEMORY_LIMIT", "CASES", "CASE_FUNCTIONS",
    "CASE_TITLES", "CHUNK", "KERNEL_NAMES", "LIBIGL_EPSILON", "METHODS", "METHOD_LABELS",
    "NEAR", "PROG", "SIZES", "TIE", "_findings7", "_json_safe", "aimed_rays", "bad_rays",
    "boundary_checks", "brute_hits", "build", "build_guarded", "case1", "case2", "case3",
    "case4", "case5", "case6", "case7", "case8", "case9", "closed_mesh_rays", "combos",
    "compare", "deep_chain", "default_combos", "float64_kernels_ok", "glass_trapping",
    "grazing_rays", "grazing_scene", "lattice_scene", "libigl_first_hits", "libigl_like",
    "load", "main", "mismatches_vs", "nan_ray_outcomes", "optics_checks", "oracle",
    "outside_distance", "pairwise_hits", "pbrt_offset_numpy", "plane_rays", "probe_worker",
    "quick_params", "random_triangle_reintersection", "record", "renderer_offset", "run",
    "secondary_rays", "self_intersection", "sliver_rays", "spawn", "stack_probe",
    "stacked_layers", "standard_params", "strictly_inside", "summary", "surface_frame",
    "synthetic_degenerates", "trace", "transformed", "triangle_quality", "ulp32",
    "ulp_offset", "winding_numbers", "with_mismatches_vs_brute",
]
