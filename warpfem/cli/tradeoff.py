"""``warpfem tradeoff``: measure time per frame against error over the knobs that cost time."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from warpfem.cli.common import check_device
from warpfem.errors import InputError

EXAMPLES = """examples:
  warpfem tradeoff --quick --out results     CPU-sized sweep (a few minutes): results/tradeoff.csv, .png
  warpfem tradeoff --device cuda:0 --out results-gpu   the full sweep (finer converged run)
"""


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``tradeoff`` command to the CLI's subparsers."""
    cmd = sub.add_parser(
        "tradeoff",
        help="sweep CG, mesh and time-step settings; write time per frame against error (CSV, PNG)",
        description=(
            "Simulate a clamped cantilever settling under gravity with each setting of the knobs that cost "
            "time (CG iterations / tolerance, coarse-mesh resolution, substeps) and report time per frame "
            "against error: the trajectory against a converged run and the final sag against NGSolve."
        ),
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    cmd.add_argument("--quick", action="store_true", help="the small sweep, a few minutes on the CPU")
    cmd.add_argument("--out", type=Path, default=Path("."), help="folder for tradeoff.csv and tradeoff.png")
    cmd.add_argument("--device", help="cpu or cuda:N (default: cuda:0 when a GPU is present, else cpu)")
    cmd.add_argument("--quiet", action="store_true", help="no progress output, only the table")
    cmd.add_argument(
        "--reference-sag",
        type=float,
        help="NGSolve's converged sag in m, computed elsewhere (for a machine without NGSolve); skips that solve",
    )
    cmd.add_argument("--no-plot", action="store_true", help="write tradeoff.csv only (no matplotlib needed)")
    cmd.add_argument("--plot-from", type=Path, help="only draw tradeoff.png into --out from an existing tradeoff.csv")
    cmd.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    """Run the sweep named by ``args``, write the CSV and the plot, print the table; returns the exit code."""
    out = args.out
    if out.exists() and not out.is_dir():
        raise InputError(f"--out {out}: not a folder")
    if not out.resolve().parent.is_dir():
        raise InputError(f"--out {out}: folder {out.resolve().parent} does not exist")
    from warpfem.study import tradeoff as T

    if not args.no_plot:
        T.pyplot()  # matplotlib is an optional extra: say so before the sweep, not after it
    if args.plot_from is not None:
        if not args.plot_from.is_file():
            raise InputError(f"--plot-from {args.plot_from}: no such file")
        out.mkdir(exist_ok=True)
        T.plot(out / "tradeoff.png", T.read_csv(args.plot_from), f"warpfem tradeoff ({args.plot_from.parent.name})")
        print(f"wrote {out / 'tradeoff.png'}", file=sys.stderr)
        return 0
    if args.reference_sag is not None and not args.reference_sag > 0:
        raise InputError(f"--reference-sag must be > 0 m, got {args.reference_sag}")
    check_device(args.device)
    import warp as wp

    device = wp.get_device(args.device or ("cuda:0" if wp.is_cuda_available() else "cpu"))
    scene = T.BeamScene()
    settings, reference = T.quick_settings() if args.quick else T.full_settings()
    settings = settings + list(T.PRESET_SETTINGS.values())

    def say(message: str) -> None:
        if not args.quiet:
            print(message, file=sys.stderr, flush=True)

    rows, ref, ngsolve_sag = T.sweep(scene, settings, reference, device.alias, say, args.reference_sag)
    out.mkdir(exist_ok=True)
    T.write_csv(out / "tradeoff.csv", rows)
    title = (
        f"warpfem tradeoff ({'quick' if args.quick else 'full'}, {device.alias}): cantilever "
        f"{scene.beam.length:g} m, E {scene.beam.young:.0e} Pa, {scene.frames} frames; "
        f"converged run: {reference.label}"
    )
    if not args.no_plot:
        T.plot(out / "tradeoff.png", rows, title)
    sag_ref = T.tip_sag(scene, ref.points[-1])
    print(f"NGSolve converged nonlinear sag {ngsolve_sag * 1e3:.2f} mm; converged run's sag {sag_ref * 1e3:.2f} mm")
    print(f"{'setting':<48} {'tets':>6} {'ms/frame':>9} {'CG it/step':>10} {'traj mm':>8} {'sag err':>8}  front")
    for r in rows:
        print(
            f"{r.run.setting.knob + ': ' + r.run.setting.label:<48} {r.run.tets:>6} {r.run.ms_per_frame:>9.2f} "
            f"{r.run.cg_iterations_per_step:>10.1f} {r.trajectory_error * 1e3:>8.2f} {100 * r.sag_error:>7.1f}%"
            f"  {'*' if r.pareto else ''}"
        )
    say("contact sweep: penalty stiffness " + ", ".join(f"{k:.0e}" for k in T.PENALTIES))
    contact = T.contact_sweep(device.alias)
    T.write_contact_csv(out / "tradeoff-contact.csv", contact)
    if not args.no_plot:
        T.plot_contact(out / "tradeoff-contact.png", contact, f"penalty stiffness: cube on cube ({device.alias})")
    print(f"{'penalty (1/s^2)':<16} {'ms/frame':>9} {'impact mm':>10} {'rest mm':>8} {'CG it/step':>10}  front")
    for r in contact:
        print(
            f"{r.stiffness:<16.0e} {r.ms_per_frame:>9.2f} {1e3 * r.impact_depth:>10.3f} {1e3 * r.resting_depth:>8.4f}"
            f" {r.cg_iterations_per_step:>10.1f}  {'*' if r.pareto else ''}"
        )
    print(f"wrote the CSVs{'' if args.no_plot else ' and plots'} in {out}", file=sys.stderr)
    return 0
