"""``warpfem prepare``: preprocess one mesh and report what it made."""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import numpy as np

from warpfem.cli.common import add_output_flags, cache_dir_of, print_summary
from warpfem.errors import InputError
from warpfem.presets import PRESETS

EXAMPLES = """examples:
  warpfem prepare ../shared/assets/armadillo.off --faces 1000
  warpfem prepare builtin:bunny --subdivide 2 --faces 500 --no-cache
  warpfem prepare bunny.obj --json                            the report as JSON, for scripts
  warpfem prepare bunny.obj --quality high                    the body the "high" preset simulates

exit codes: 0 ok, 2 bad input (unreadable or broken mesh, bad option, a stage failing on this mesh)
"""


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``prepare`` command to the CLI's subparsers."""
    prep = sub.add_parser(
        "prepare",
        help="preprocess one mesh and report what it made",
        description="Load, simplify, tetrahedralize and embed one mesh; print coarse faces, tets, coverage, timings.",
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    prep.add_argument("mesh", help="OBJ, PLY, STL, OFF or USD file, or builtin:bunny")
    prep.add_argument("--prim", help="the UsdGeom.Mesh prim of a USD file (default: its only mesh)")
    prep.add_argument(
        "--quality",
        choices=sorted(PRESETS),
        help="a scene's [solver] quality preset: its faces, maxh, tets across and tet budget, where not given",
    )
    prep.add_argument("--faces", type=int, default=None, help="coarse surface target face count (default 1000)")
    prep.add_argument("--subdivide", type=int, default=0, help="Loop subdivision iterations first (default 0)")
    prep.add_argument("--maxh", type=float, default=None, help="Netgen max element size / bbox diagonal (default 0.2)")
    prep.add_argument("--cache-dir", type=Path, default=None, help="preprocessing cache (default: ~/.cache/warpfem)")
    prep.add_argument("--no-cache", action="store_true", help="preprocess again and store nothing")
    prep.add_argument("--timeout", type=float, default=120.0, help="time limit per stage in s (default 120)")
    prep.add_argument(
        "--budget",
        type=float,
        default=60.0,
        help="time budget of the whole preparation in s: no retry starts after it (default 60)",
    )
    prep.add_argument(
        "--shells",
        default="merge",
        help="several closed shells: merge (default), largest, error, or K (keep the K-th largest, from 0)",
    )
    prep.add_argument(
        "--max-hole", type=float, default=None, help="largest hole closed, relative to the bbox diagonal (default 0.25)"
    )
    prep.add_argument(
        "--tets-across",
        type=float,
        default=None,
        help="tets across the thinnest parts, as the scene key tets_across (default 0: --faces and --maxh alone)",
    )
    prep.add_argument(
        "--max-tets", type=int, default=None, help="the tet budget of --tets-across, as the scene key (default 50000)"
    )
    add_output_flags(prep, progress=False)
    prep.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    """Preprocess the mesh named by ``args`` and print its report; returns the exit code."""
    from warpfem.prep.pipeline import prepare
    from warpfem.scene import MAX_TETS_RANGE, TETS_ACROSS_MAX

    _fill_sizes(args)
    if args.faces < 4:
        raise InputError(f"--faces must be >= 4, got {args.faces}")
    if not 0.0 < args.maxh <= 1.0:
        raise InputError(f"--maxh must be in (0, 1], got {args.maxh}")
    if not (0 < args.timeout < float("inf")):
        raise InputError(f"--timeout must be a number of seconds > 0, got {args.timeout}")
    if not (0 < args.budget < float("inf")):
        raise InputError(f"--budget must be a number of seconds > 0, got {args.budget}")
    if args.max_hole is not None and args.max_hole < 0:
        raise InputError(f"--max-hole must be >= 0, got {args.max_hole}")
    if not 0.0 <= args.tets_across <= TETS_ACROSS_MAX:
        raise InputError(f"--tets-across must be in [0, {TETS_ACROSS_MAX:g}], got {args.tets_across}")
    low, high = MAX_TETS_RANGE
    if not low <= args.max_tets <= high:
        raise InputError(f"--max-tets must be in [{low}, {high}], got {args.max_tets}")
    shells = args.shells
    if shells not in ("merge", "largest", "error"):
        if not shells.isdigit():
            raise InputError(f"--shells must be merge, largest, error or a shell index, got {shells!r}")
        shells = int(shells)
    cache = cache_dir_of(args)
    body = prepare(
        args.mesh,
        faces=args.faces,
        subdivide=args.subdivide,
        maxh=args.maxh,
        cache_dir=cache,
        timeout_s=args.timeout,
        budget_s=args.budget,
        shells=shells,
        max_hole=args.max_hole,
        prim=args.prim,
        across=args.tets_across,
        max_tets=args.max_tets,
    )
    diagonal = float(np.linalg.norm(np.ptp(body.dense_vertices, axis=0)))
    print_summary(report_rows(body.stats, diagonal), body.stats, args.json)
    return 0


SIZES = ("faces", "maxh", "tets_across", "max_tets")
"""The sizing options, named as the scene's object keys."""


def _fill_sizes(args: argparse.Namespace) -> None:
    """Set each sizing option not given from ``--quality``'s preset, else from the object key's default."""
    from warpfem.scene import ObjectConfig

    preset = PRESETS[args.quality] if args.quality else {}
    defaults = {f.name: f.default for f in dataclasses.fields(ObjectConfig)}
    for key in SIZES:
        if getattr(args, key) is None:
            setattr(args, key, preset.get(key, defaults[key]))


CACHE = {"hit": "hit (read; the times below are those of the run that filled it)", "miss": "miss (stored)"}

NAMED = frozenset(
    "mesh cache repairs dense_vertices dense_faces dense_intersecting_pairs coarse_vertices coarse_faces rung "
    "failed_rungs tets tet_vertices maxh_absolute tet_min_dihedral_deg tet_min_radius_ratio volume_ratio "
    "cage_volume_ratio cage_offset cage_outside cage_outside_max hausdorff hausdorff_relative "
    "hausdorff_dense_to_coarse hausdorff_coarse_to_dense embedding_coverage embedding_outside_max embedding_max_error "
    "max_depth thickness thickness_relative tets_across max_tets sizing_capped".split()
)
"""The statistics :func:`report_rows` words itself; any other is listed as it is."""


def report_rows(s: dict, diagonal: float) -> list[tuple[str, str]]:
    """``prepare``'s statistics ``s`` as labelled rows with their units (``--json`` gives them raw).

    Lengths are in the mesh file's units, each also as a share of the dense mesh's bounding-box diagonal.
    """

    def length(key: str) -> str:
        value = float(s[key])
        return f"{value:.4g} ({100 * value / diagonal:.2f} %)" if diagonal > 0 else f"{value:.4g}"

    rows = [
        ("mesh", str(s["mesh"])),
        ("cache", CACHE.get(s["cache"], str(s["cache"]))),
        ("repairs", str(s["repairs"])),
        ("size", f"bounding-box diagonal {diagonal:.4g} (the mesh file's units; lengths below also as % of it)"),
        (
            "dense surface",
            f"{s['dense_vertices']:,} vertices, {s['dense_faces']:,} triangles, "
            f"{s['dense_intersecting_pairs']:,} pairs of them intersecting",
        ),
        ("coarse surface", f"{s['coarse_vertices']:,} vertices, {s['coarse_faces']:,} triangles"),
        ("rung", f"{s['rung']}; failed before it: {s['failed_rungs']}"),
        (
            "tets",
            f"{s['tets']:,} on {s['tet_vertices']:,} vertices, Netgen's largest size {length('maxh_absolute')}; "
            f"smallest dihedral angle {s['tet_min_dihedral_deg']:.3g} deg, smallest radius ratio "
            f"{s['tet_min_radius_ratio']:.3g} (1 for a regular tet)",
        ),
    ]
    if "tets_across" in s:
        capped = ", capped by the budget" if s["sizing_capped"] else ""
        across = f"{s['tets_across']} tets across it, budget {s['max_tets']:,} tets{capped}"
        rows.append(("sizing", f"thinnest part {length('thickness')}, {across}"))
    rows += [
        ("volume", f"tets {s['volume_ratio']:.4g}x the dense surface's, cage {s['cage_volume_ratio']:.4g}x"),
        (
            "cage",
            f"pushed out by at most {length('cage_offset')}; {100 * s['cage_outside']:.2f} % of dense points "
            f"still outside it, by at most {length('cage_outside_max')}",
        ),
        (
            "hausdorff",
            f"{length('hausdorff')}: dense to coarse {length('hausdorff_dense_to_coarse')}, coarse to dense "
            f"{length('hausdorff_coarse_to_dense')}",
        ),
        (
            "embedding",
            f"{100 * s['embedding_coverage']:.2f} % of dense vertices inside a tet, the rest at most "
            f"{length('embedding_outside_max')} outside theirs; rebuilt within {s['embedding_max_error']:.2g} of "
            "the diagonal",
        ),
        ("deepest tet vertex", f"{length('max_depth')} below the coarse surface"),
    ]
    seconds = [(k.removeprefix("seconds_").replace("_", " "), v) for k, v in s.items() if k.startswith("seconds_")]
    rows.append(("seconds", ", ".join(f"{k} {v:.3g}" for k, v in seconds)))
    rest = [(k, v) for k, v in s.items() if k not in NAMED and not k.startswith("seconds_")]
    return rows + [(k, f"{v:.4g}" if isinstance(v, float) else str(v)) for k, v in rest]
