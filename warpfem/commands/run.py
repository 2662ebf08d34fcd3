"""``warpfem run``: run a scene and write an animated USD file."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from warpfem.commands import cache_dir_of, check_device, status_printer
from warpfem.errors import InputError

EXAMPLES = """examples:
  warpfem run                                    the default scene (a dense bunny dropped on the ground)
  warpfem run scenes/default.toml --frames 30 --out bunny.usdc --device cpu
"""


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``run`` command to the CLI's subparsers."""
    run = sub.add_parser(
        "run",
        help="run a scene and write an animated USD file",
        description="Run a scene (default: the shipped default scene) and write its dense meshes as animated USD.",
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
    run.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    """Run the scene named by ``args``; returns the exit code."""
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
    check_device(args.device)
    from tqdm import tqdm

    from warpfem.simulate import run_scene

    cache = cache_dir_of(args)
    interactive = sys.stderr.isatty() and not args.quiet  # piped stderr carries only errors
    bar = None

    def on_frame() -> None:  # the bar starts with the first frame, after preprocessing
        nonlocal bar
        if bar is None:
            bar = tqdm(total=scene.frames, unit="frame", disable=not interactive, file=sys.stderr, dynamic_ncols=True)
        bar.update(1)

    try:
        summary = run_scene(scene, out, args.device, cache, status_printer(not interactive), on_frame)
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
