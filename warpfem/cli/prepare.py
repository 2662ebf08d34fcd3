"""``warpfem prepare``: preprocess one mesh and report what it made."""

from __future__ import annotations

import argparse
from pathlib import Path

from warpfem.cli.common import add_output_flags, cache_dir_of, print_summary
from warpfem.errors import InputError

EXAMPLES = """examples:
  warpfem prepare ../shared/assets/armadillo.off --faces 1000
  warpfem prepare builtin:bunny --subdivide 2 --faces 500 --no-cache
  warpfem prepare bunny.obj --json                            the report as JSON, for scripts

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
    prep.add_argument("--faces", type=int, default=1000, help="coarse surface target face count (default 1000)")
    prep.add_argument("--subdivide", type=int, default=0, help="Loop subdivision iterations first (default 0)")
    prep.add_argument("--maxh", type=float, default=0.2, help="Netgen max element size / bbox diagonal (default 0.2)")
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
    add_output_flags(prep, progress=False)
    prep.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    """Preprocess the mesh named by ``args`` and print its report; returns the exit code."""
    from warpfem.prep.pipeline import prepare

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
    )
    rows = [(key, f"{value:.4g}" if isinstance(value, float) else str(value)) for key, value in body.stats.items()]
    print_summary(rows, body.stats, args.json)
    return 0
