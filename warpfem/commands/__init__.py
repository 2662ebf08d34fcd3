"""The CLI's commands, one module each: ``register(subparsers)`` adds a parser whose ``func`` runs it.

To add a command, write ``warpfem/commands/<name>.py`` with ``register`` and add its name to
:data:`COMMANDS`. Helpers shared by commands live here.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path
from typing import Any

from warpfem.errors import InputError

COMMANDS = ("run", "render", "prepare", "info", "tradeoff")
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


def add_output_flags(parser: argparse.ArgumentParser, progress: bool = True) -> None:
    """Add ``--quiet`` (when the command shows progress) and ``--json`` to a command's parser."""
    if progress:
        parser.add_argument("--quiet", action="store_true", help="no progress output, only the summary")
    parser.add_argument("--json", action="store_true", help="print the summary as one JSON object (for scripts)")


def shows_progress(args: argparse.Namespace) -> bool:
    """Whether to draw progress bars: stderr is a terminal and neither ``--quiet`` nor ``--json`` was given."""
    return sys.stderr.isatty() and not getattr(args, "quiet", False) and not getattr(args, "json", False)


def print_summary(rows: list[tuple[str, str]], data: dict[str, Any], as_json: bool) -> None:
    """Print the closing summary: an aligned two-column table, or ``data`` as JSON with ``as_json``."""
    if as_json:
        print(json.dumps(data, indent=2, default=str))
        return
    width = max(len(k) for k, _ in rows)
    for key, value in rows:
        print(f"{key:<{width}}  {value}")


def parse_vec3(text: str, option: str) -> tuple[float, float, float]:
    """``"x,y,z"`` as three finite floats.

    Raises:
        InputError: Anything else, naming ``option``.
    """
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        values = ()
    if len(values) != 3 or not all(abs(v) < float("inf") for v in values):
        raise InputError(f"{option} {text}: expected three numbers x,y,z")
    return values  # type: ignore[return-value]


def add_camera_flags(parser: argparse.ArgumentParser) -> None:
    """Add the preview image and camera options shared by ``run`` and ``render``."""
    parser.add_argument("--size", default="480x360", help="preview WIDTHxHEIGHT in pixels, even (default 480x360)")
    parser.add_argument("--camera", metavar="X,Y,Z", help="camera position in m (default: framing all bodies)")
    parser.add_argument("--target", metavar="X,Y,Z", help="point the camera looks at (default: centre of the bodies)")
    parser.add_argument("--fov", type=float, help="vertical field of view, degrees (default: the scene's, else 35)")


def camera_flags(args: argparse.Namespace) -> dict[str, Any]:
    """Check ``--camera``/``--target``/``--fov`` up front; returns them parsed (None where not given).

    Raises:
        InputError: A malformed vector, a field of view outside (0, 180) or the camera at its target.
    """
    if args.fov is not None and not 0.0 < args.fov < 180.0:
        raise InputError(f"--fov must be in (0, 180) degrees, got {args.fov}")
    flags = {
        "position": parse_vec3(args.camera, "--camera") if args.camera else None,
        "target": parse_vec3(args.target, "--target") if args.target else None,
        "fov": args.fov if args.fov is not None else 35.0,
    }
    if flags["position"] is not None and flags["position"] == flags["target"]:
        raise InputError("--camera and --target are the same point")
    return flags


def make_camera(flags: dict[str, Any], lo: Any, hi: Any, up_axis: str, aspect: float) -> Any:
    """The preview camera: the flags from :func:`camera_flags` where given, else one framing the box [lo, hi]."""
    from warpfem.render import Camera, auto_camera

    auto = auto_camera(lo, hi, up_axis, aspect, flags["fov"])
    return Camera(flags["position"] or auto.position, flags["target"] or auto.target, auto.up, flags["fov"])
