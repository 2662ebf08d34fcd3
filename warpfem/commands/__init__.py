"""The CLI's commands, one module each: ``register(subparsers)`` adds a parser whose ``func`` runs it.

To add a command, write ``warpfem/commands/<name>.py`` with ``register`` and add its name to
:data:`COMMANDS`. Helpers shared by commands live here.
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Callable
from pathlib import Path

from warpfem.errors import InputError

COMMANDS = ("run", "prepare")
"""Command modules in the order ``--help`` lists them."""


def default_cache_dir() -> Path:
    """The preprocessing cache: $WARPFEM_CACHE, else $XDG_CACHE_HOME/warpfem, else ~/.cache/warpfem."""
    if os.environ.get("WARPFEM_CACHE"):
        return Path(os.environ["WARPFEM_CACHE"])
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "warpfem"


def cache_dir_of(args: argparse.Namespace) -> Path | None:
    """The cache folder chosen by ``--cache-dir`` / ``--no-cache`` (None: no cache)."""
    return None if args.no_cache else (args.cache_dir or default_cache_dir())


def status_printer(quiet: bool) -> Callable[[str], None]:
    """A callback printing one-line status messages to stderr unless ``quiet``."""

    def say(message: str) -> None:
        if not quiet:
            print(message, file=sys.stderr, flush=True)

    return say


def check_device(name: str | None) -> None:
    """Raise :class:`InputError` if ``name`` is not a Warp device here (None: the default, always fine)."""
    import warp as wp

    if name is None:
        return
    try:
        wp.get_device(name)
    except (ValueError, RuntimeError):
        available = ", ".join(d.alias for d in wp.get_devices())
        raise InputError(f"--device {name}: no such device (available: {available})") from None
