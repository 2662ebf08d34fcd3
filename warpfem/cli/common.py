"""The CLI's commands, one module each: ``register(subparsers)`` adds a parser whose ``func`` runs it.

To add a command, write ``warpfem/commands/<name>.py`` with ``register`` and add its name to
:data:`COMMANDS`. Helpers shared by commands live here.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import signal
import sys
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from warpfem.errors import InputError

COMMANDS = ("run", "render", "prepare", "warmup", "info", "tradeoff")
"""Command modules in the order ``--help`` lists them."""


EXIT_INTERRUPTED = 130
"""Exit code after Ctrl-C (SIGINT), the frames finished so far kept."""

EXIT_TERMINATED = 143
"""Exit code after SIGTERM (128 + 15), the frames finished so far kept."""


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised like Ctrl-C so that everything computed so far is saved on the way out."""


class StopRequest:
    """The first SIGINT or SIGTERM seen inside :func:`stop_signals` (None: none yet)."""

    def __init__(self) -> None:
        self.signum: int | None = None

    def check(self) -> None:
        """Raise the interrupt again if a signal came, in case code in between swallowed the first raise."""
        if self.signum is not None:
            raise _interrupt(self.signum)


def _interrupt(signum: int) -> KeyboardInterrupt:
    return Terminated("terminated (SIGTERM)") if signum == signal.SIGTERM else KeyboardInterrupt()


@contextlib.contextmanager
def stop_signals() -> Iterator[StopRequest]:
    """Inside the block, SIGINT raises ``KeyboardInterrupt`` and SIGTERM raises :class:`Terminated`.

    Later signals are ignored, so a second Ctrl-C or SIGTERM cannot break the saving of the frames so far
    (SIGKILL still can; see :mod:`warpfem.io.usd`). Long loops should call the yielded request's
    ``check()`` now and then: a library may catch the first raise (USD's module loader does). Outside the
    main thread (where Python cannot set handlers) the block runs unchanged.
    """
    request = StopRequest()
    if threading.current_thread() is not threading.main_thread():
        yield request
        return

    def handler(signum: int, _frame: object) -> None:
        if request.signum is None:
            request.signum = signum
            raise _interrupt(signum)

    previous = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    for s in previous:
        signal.signal(s, handler)
    try:
        yield request
    finally:
        for s, h in previous.items():
            signal.signal(s, signal.SIG_DFL if h is None else h)


def stopped(err: KeyboardInterrupt, kept: list[Path], what: str = "frames finished") -> int:
    """Report a stop by Ctrl-C or SIGTERM in one line on stderr; returns the exit code (130 or 143).

    Args:
        err: The interrupt caught.
        kept: Output paths that may hold what was done so far (those that exist are named).
        what: What they hold, for the message.
    """
    done = [str(p) for p in kept if p is not None and p.exists()]
    saved = f"; the {what} so far are in {' and '.join(done)}" if done else "; nothing was written"
    terminated = isinstance(err, Terminated)
    print(f"warpfem: {'terminated' if terminated else 'interrupted'}{saved}", file=sys.stderr)
    return EXIT_TERMINATED if terminated else EXIT_INTERRUPTED


def cache_dir_of(args: argparse.Namespace) -> Path | None:
    """The cache folder chosen by ``--cache-dir`` / ``--no-cache`` (None: no cache)."""
    from warpfem.prep.pipeline import default_cache_dir

    return None if args.no_cache else (args.cache_dir or default_cache_dir())


def check_device(name: str | None) -> None:
    """Raise :class:`InputError` naming ``--device`` if ``name`` is not a Warp device here (None: fine)."""
    from warpfem.simulation import check_device as check

    check(name, "--device")


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
    from warpfem.io.render import Camera, auto_camera

    auto = auto_camera(lo, hi, up_axis, aspect, flags["fov"])
    return Camera(flags["position"] or auto.position, flags["target"] or auto.target, auto.up, flags["fov"])
