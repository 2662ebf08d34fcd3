"""``warpfem info``: versions of Warp, CUDA and the dependencies, and the devices found."""

from __future__ import annotations

import argparse
import platform
import sys

from warpfem.cli.common import add_output_flags, print_summary

EXAMPLES = """examples:
  warpfem info                                   what a bug report needs
  warpfem info --json                            the same, machine-readable

exit codes: 0 ok
"""

DEPENDENCIES = (
    "warpfem",
    "warp-lang",
    "numpy",
    "scipy",
    "trimesh",
    "meshio",
    "ngsolve",
    "usd-core",
    "libigl",
    "tqdm",
    "pillow",
    "imageio-ffmpeg",
)
"""Distributions whose versions ``info`` reports."""


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``info`` command to the CLI's subparsers."""
    cmd = sub.add_parser(
        "info",
        help="print Warp, CUDA, device and dependency versions",
        description="Print the versions of Python, Warp, CUDA (driver and toolkit), ffmpeg and every dependency, "
        "the Warp devices and whether a GPU was found.",
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_output_flags(cmd, progress=False)
    cmd.set_defaults(func=main)


def _version(dist: str) -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version(dist)
    except PackageNotFoundError:
        return "not installed"


def _ffmpeg() -> str:
    """The version of the ffmpeg binary that imageio-ffmpeg ships (used for mp4 previews)."""
    try:
        import imageio_ffmpeg

        return imageio_ffmpeg.get_ffmpeg_version()
    except (ImportError, RuntimeError) as err:
        return f"unavailable ({err})"


def _dotted(version: tuple[int, int] | None) -> str | None:
    return ".".join(str(v) for v in version) if version else None


def main(args: argparse.Namespace) -> int:
    """Print the report; returns 0."""
    import warp as wp

    wp.init()
    cuda = wp.get_cuda_devices()
    devices = [
        {
            "alias": d.alias,
            "name": d.name,
            "memory_gib": round(d.total_memory / 2**30, 1) if d.is_cuda else None,
            "arch": f"sm_{d.arch}" if d.is_cuda else None,
        }
        for d in wp.get_devices()
    ]
    driver = _dotted(wp.get_cuda_driver_version())
    toolkit = _dotted(wp.get_cuda_toolkit_version())
    data = {
        "python": sys.version.split()[0],
        "platform": platform.platform(),
        "gpu_found": bool(cuda),
        "default_device": "cuda:0" if cuda else "cpu",
        "cuda_driver": driver,
        "cuda_toolkit": toolkit,
        "devices": devices,
        "ffmpeg": _ffmpeg(),
        "versions": {dist: _version(dist) for dist in DEPENDENCIES},
    }
    rows = [
        ("python", f"{data['python']} ({data['platform']})"),
        ("GPU found", f"yes ({len(cuda)} CUDA device{'s' * (len(cuda) > 1)})" if cuda else "no (runs on the CPU)"),
        ("default device", data["default_device"]),
        ("CUDA driver / toolkit", f"{driver or 'not available'} / {toolkit or 'none'}"),
    ]
    for d in devices:
        extra = f", {d['arch']}, {d['memory_gib']} GiB" if d["arch"] else ""
        rows.append((f"device {d['alias']}", f"{d['name']}{extra}"))
    rows.append(("ffmpeg (mp4 previews)", data["ffmpeg"]))
    rows += [(dist, v) for dist, v in data["versions"].items()]
    print_summary(rows, data, args.json)
    return 0
