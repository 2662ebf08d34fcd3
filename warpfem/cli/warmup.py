"""``warpfem warmup``: compile every Warp kernel module of warpfem ahead of any run."""

from __future__ import annotations

import argparse
import sys
import time

from warpfem.cli.common import add_output_flags, check_device, print_summary

EXAMPLES = """examples:
  warpfem warmup                                 every device here (the CPU and each GPU)
  warpfem warmup --device cuda:0                 one GPU only
  warpfem warmup --json                          what was compiled, for scripts

exit codes: 0 ok, 2 no such device
"""


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``warmup`` command to the CLI's subparsers."""
    cmd = sub.add_parser(
        "warmup",
        help="compile every Warp kernel module ahead of any run (a first run otherwise compiles its own)",
        description="Compile (or load, where Warp's kernel cache has them) every Warp module of warpfem in every "
        "block size the code launches it with, so that no later run, preprocessing or preview compiles anything. "
        "Preprocessing's modules run on the CPU and are compiled for it only.",
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    cmd.add_argument("--device", default="all", help="cpu, cuda:N or all (default: all, the CPU and each GPU)")
    add_output_flags(cmd)
    cmd.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    """Compile and report; returns 0."""
    import warp as wp

    from warpfem.compilation import warmup

    if args.device != "all":
        check_device(args.device)
    clock = time.perf_counter()
    quiet = args.quiet or args.json
    loads = warmup(
        None if args.device == "all" else [args.device],
        notify=None if quiet else (lambda message: print(f"warpfem: {message}", file=sys.stderr, flush=True)),
    )
    seconds = time.perf_counter() - clock
    rows = [
        (f"{load.module} on {load.device}" + (f", blocks of {load.block_dim}" if load.block_dim > 1 else ""),
         f"{'compiled' if load.compiled else 'cached'} ({load.seconds:.2f} s)")
        for load in loads
    ]  # fmt: skip
    compiled = sum(load.compiled for load in loads)
    rows.append(("total", f"{compiled} of {len(loads)} compiled in {seconds:.1f} s"))
    rows.append(("kernel cache", str(wp.config.kernel_cache_dir)))
    data = {
        "modules": [vars(load) for load in loads],
        "compiled": compiled,
        "seconds": seconds,
        "kernel_cache": str(wp.config.kernel_cache_dir),
    }
    print_summary(rows, data, args.json)
    return 0
