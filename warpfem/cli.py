"""The ``warpfem`` command line: ``run`` a scene, ``prepare`` a mesh.

Exit codes: 0 ok, 1 runtime failure (NaN in the state), 2 bad input, 130 interrupted (frames so far kept).
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from warpfem.errors import InputError, SimulationError

EXAMPLES = """examples:
  warpfem run                                   the default scene (a dense bunny dropped on the ground)
  warpfem run scenes/default.toml --frames 30 --out bunny.usdc --device cpu
  warpfem prepare ../shared/assets/armadillo.off --faces 1000
"""


def default_cache_dir() -> Path:
    """The preprocessing cache: $WARPFEM_CACHE, else $XDG_CACHE_HOME/warpfem, else ~/.cache/warpfem."""
    if os.environ.get("WARPFEM_CACHE"):
        return Path(os.environ["WARPFEM_CACHE"])
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "warpfem"


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="warpfem",
        description="Animate dense surface meshes through simplified tet meshes (Kondo & Kanai) with NVIDIA Warp.",
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    sub = parser.add_subparsers(dest="command", required=True)

    run = sub.add_parser(
        "run",
        help="run a scene and write an animated USD file",
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    run.add_argument("scene", nargs="?", type=Path, help="scene TOML file (default: the shipped default scene)")
    run.add_argument("--out", type=Path, help="output .usdc or .usda (default: <scene name>.usdc here)")
    run.add_argument("--frames", type=int, help="override the scene's frame count")
    run.add_argument("--device", help="cpu or cuda:N (default: cuda:0 when a GPU is present, else cpu)")
    run.add_argument("--cache-dir", type=Path, default=None, help="preprocessing cache (default: ~/.cache/warpfem)")
    run.add_argument("--no-cache", action="store_true", help="preprocess again and store nothing")
    run.add_argument("--quiet", action="store_true", help="no progress output, only the summary")

    prep = sub.add_parser(
        "prepare",
        help="preprocess one mesh and report what it made",
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    prep.add_argument("mesh", help="OBJ, PLY, STL or OFF file, or builtin:bunny")
    prep.add_argument("--faces", type=int, default=1000, help="coarse surface target face count (default 1000)")
    prep.add_argument("--subdivide", type=int, default=0, help="Loop subdivision iterations first (default 0)")
    prep.add_argument("--maxh", type=float, default=0.2, help="Netgen max element size / bbox diagonal (default 0.2)")
    prep.add_argument("--cache-dir", type=Path, default=None, help="preprocessing cache (default: ~/.cache/warpfem)")
    prep.add_argument("--no-cache", action="store_true", help="preprocess again and store nothing")
    return parser


def _status(quiet: bool):
    def say(message: str) -> None:
        if not quiet:
            print(message, file=sys.stderr, flush=True)

    return say


def _check_device(name: str | None) -> None:
    import warp as wp

    if name is None:
        return
    try:
        wp.get_device(name)
    except (ValueError, RuntimeError):
        available = ", ".join(d.alias for d in wp.get_devices())
        raise InputError(f"--device {name}: no such device (available: {available})") from None


def _run(args: argparse.Namespace) -> int:
    from warpfem.scene import default_scene_path, load_scene

    scene = load_scene(args.scene or default_scene_path())
    if args.frames is not None:
        if args.frames < 1:
            raise InputError(f"--frames must be >= 1, got {args.frames}")
        scene = scene.with_frames(args.frames)
    out = args.out or Path(Path(scene.path).stem + ".usdc")
    if out.suffix not in (".usdc", ".usda"):
        raise InputError(f"--out {out}: the output must end in .usdc or .usda")
    if not out.resolve().parent.is_dir():
        raise InputError(f"--out {out}: folder {out.resolve().parent} does not exist")
    _check_device(args.device)
    from tqdm import tqdm

    from warpfem.simulate import run_scene

    cache = None if args.no_cache else (args.cache_dir or default_cache_dir())
    interactive = sys.stderr.isatty() and not args.quiet  # piped stderr carries only errors
    bar = None

    def on_frame() -> None:  # the bar starts with the first frame, after preprocessing
        nonlocal bar
        if bar is None:
            bar = tqdm(total=scene.frames, unit="frame", disable=not interactive, file=sys.stderr, dynamic_ncols=True)
        bar.update(1)

    try:
        summary = run_scene(scene, out, args.device, cache, _status(not interactive), on_frame)
    except KeyboardInterrupt:
        kept = f"; the frames finished so far are in {out}" if out.exists() else "; nothing was written"
        print(f"warpfem: interrupted{kept}", file=sys.stderr)
        return 130
    finally:
        if bar is not None:
            bar.close()
    s = summary.seconds
    rows = [
        ("output", str(summary.output)),
        ("device", summary.device),
        ("frames", f"{summary.frames} ({summary.simulated_seconds:.3g} s simulated)"),
        (
            "wall time per frame",
            f"{summary.ms_per_frame:.2f} ms (simulate {1e3 * s['simulate'] / summary.frames:.2f}, "
            f"map {1e3 * s['map'] / summary.frames:.2f}, write {1e3 * s['write'] / summary.frames:.2f})",
        ),
        ("preprocessing", f"{s['prepare']:.2f} s"),
        ("bodies", str(summary.bodies)),
        ("tets / tet vertices", f"{summary.tets} / {summary.tet_vertices}"),
        ("dense triangles / vertices", f"{summary.dense_triangles} / {summary.dense_vertices}"),
        (
            "CG iterations per step",
            f"{summary.cg_iterations_per_step:.1f} (max residual {summary.cg_residual_max:.2g})",
        ),
    ]
    width = max(len(k) for k, _ in rows)
    for key, value in rows:
        print(f"{key:<{width}}  {value}")
    return 0


def _prepare(args: argparse.Namespace) -> int:
    from warpfem.preprocess import prepare

    if args.faces < 4:
        raise InputError(f"--faces must be >= 4, got {args.faces}")
    if not 0.0 < args.maxh <= 1.0:
        raise InputError(f"--maxh must be in (0, 1], got {args.maxh}")
    cache = None if args.no_cache else (args.cache_dir or default_cache_dir())
    body = prepare(args.mesh, faces=args.faces, subdivide=args.subdivide, maxh=args.maxh, cache_dir=cache)
    width = max(len(k) for k in body.stats)
    for key, value in body.stats.items():
        shown = f"{value:.4g}" if isinstance(value, float) else str(value)
        print(f"{key:<{width}}  {shown}")
    return 0


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``warpfem`` command; returns the exit code."""
    args = _parser().parse_args(argv)
    import warp as wp

    wp.config.log_level = wp.LOG_WARNING  # no banner, no module-load lines
    try:
        return _run(args) if args.command == "run" else _prepare(args)
    except InputError as err:
        print(f"warpfem: error: {err}", file=sys.stderr)
        return 2
    except SimulationError as err:
        print(f"warpfem: {err} (frames before it were written)", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("warpfem: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
