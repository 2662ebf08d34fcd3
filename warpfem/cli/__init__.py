"""The ``warpfem`` command line; each command lives in :mod:`warpfem.cli.common`.

Exit codes: 0 ok, 1 runtime failure (NaN in the state), 2 bad input, 130 interrupted (frames so far kept).
"""

from __future__ import annotations

import argparse
import importlib
import sys
from typing import NoReturn

from warpfem.cli.common import COMMANDS
from warpfem.errors import InputError, SimulationError

EPILOG = """exit codes: 0 ok, 1 the simulation failed (NaN/Inf), 2 bad input, 130 interrupted
examples:
  warpfem run                                    the default scene (a dense bunny dropped on the ground)
  warpfem run scenes/default.toml --frames 30 --out bunny.usdc --device cpu
  warpfem run --frames 10 --device cpu --preview out.gif
  warpfem render default.usdc --out default.mp4  render a USD file written here or elsewhere
  warpfem prepare ../shared/assets/armadillo.off --faces 1000
  warpfem info                                   Warp, CUDA, devices and dependency versions
every command has --help with its own examples; docs/cli.md describes them all
"""


class UsageError(Exception):
    """A command line argparse cannot read (an unknown option, a value of the wrong type or choice)."""


class _Parser(argparse.ArgumentParser):
    """argparse's parser, its errors one line (the usage is in ``--help``) raised to :func:`main`."""

    def error(self, message: str) -> NoReturn:
        raise UsageError(f"{message} (see: {self.prog} --help)")


def _parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="warpfem",
        description="Animate dense surface meshes through simplified tet meshes (Kondo & Kanai) with NVIDIA Warp.",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    sub = parser.add_subparsers(dest="command", required=True)
    for name in COMMANDS:
        importlib.import_module(f"warpfem.cli.{name}").register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``warpfem`` command; returns the exit code."""
    try:
        args = _parser().parse_args(argv)
    except UsageError as err:
        print(f"warpfem: error: {err}", file=sys.stderr)
        return 2
    import warp as wp

    wp.config.log_level = wp.LOG_WARNING  # no banner, no module-load lines
    try:
        return args.func(args)
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
