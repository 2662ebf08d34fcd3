"""``warpfem render``: render an animated USD file (as ``warpfem run`` writes them) to a video or PNG frames."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from warpfem.cli.common import (
    add_camera_flags,
    add_output_flags,
    camera_flags,
    check_device,
    make_camera,
    print_summary,
    shows_progress,
    stop_signals,
    stopped,
)
from warpfem.errors import InputError

EXAMPLES = """examples:
  warpfem render default.usdc                    writes default.mp4 here
  warpfem render anim.usdc --out anim.gif --size 320x240 --device cpu
  warpfem render anim.usdc --out frames/ --camera 2,1.5,3 --target 0,0.4,0
  warpfem render anim.usdz --out still/ --no-ground --json

exit codes: 0 ok, 2 bad input (missing or unreadable file, bad option, --out exists), 130 interrupted,
143 terminated (SIGTERM); after 130 and 143 the frames rendered so far are kept
"""


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``render`` command to the CLI's subparsers."""
    cmd = sub.add_parser(
        "render",
        help="render an animated USD file to an mp4, a gif or PNG frames",
        description="Render every UsdGeom.Mesh of a USD file at each time sample (headless Warp ray casting, "
        "no display needed) to an mp4, a gif or a folder of PNG frames. The camera frames all meshes over "
        "the whole animation unless --camera/--target say otherwise.",
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    cmd.add_argument("usd", type=Path, help="animated .usdc, .usda or .usd file")
    cmd.add_argument("--out", type=Path, help="FILE.mp4, FILE.gif or a new FOLDER for PNG frames (default: <name>.mp4)")
    cmd.add_argument("--overwrite", action="store_true", help="replace the --out file if it exists (else: an error)")
    cmd.add_argument("--device", help="cpu or cuda:N (default: cuda:0 when a GPU is present, else cpu)")
    cmd.add_argument("--ground-height", type=float, default=0.0, help="ground plane height along up, m (default 0)")
    cmd.add_argument("--no-ground", action="store_true", help="draw no ground plane")
    add_camera_flags(cmd)
    add_output_flags(cmd)
    cmd.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    """Render the USD file named by ``args``; returns the exit code."""
    from warpfem.io.render import PreviewWriter, parse_size, preview_kind, read_usd

    out = args.out or Path(args.usd.stem + ".mp4")
    size = parse_size(args.size)
    flags = camera_flags(args)
    preview_kind(out)
    if out.is_file() and not args.overwrite:
        raise InputError(f"--out {out}: the file exists; pass --overwrite to replace it")
    check_device(args.device)
    anim = read_usd(args.usd)
    import numpy as np
    import warp as wp
    from tqdm import tqdm

    from warpfem.io.render import Renderer, framing_box

    device = args.device or ("cuda:0" if wp.is_cuda_available() else "cpu")
    ground = None if args.no_ground else args.ground_height
    show = shows_progress(args)
    lo, hi = framing_box([np.stack(anim.bounds())], anim.up_axis, ground)
    camera = make_camera(flags, lo, hi, anim.up_axis, size[0] / size[1])
    renderer = Renderer(anim.faces, *size, device=device, camera=camera, up_axis=anim.up_axis, ground=ground)
    clock = time.perf_counter()
    render_seconds = 0.0
    try:
        with (
            stop_signals() as stop,
            PreviewWriter(out, anim.fps, size) as writer,
            tqdm(anim.times, unit="frame", desc="rendering", disable=not show, file=sys.stderr) as bar,
        ):
            for t in bar:
                stop.check()
                points = anim.points(t)
                tick = time.perf_counter()
                image = renderer.render(points)
                render_seconds += time.perf_counter() - tick
                writer.add(image)
    except KeyboardInterrupt as err:
        return stopped(err, [out], "frames rendered")
    frames = len(anim.times)
    rows = [
        ("output", f"{out} ({writer.kind}, {size[0]}x{size[1]}, {anim.fps:g} fps)"),
        ("input", f"{args.usd} ({len(anim.names)} meshes, {sum(len(f) for f in anim.faces)} triangles)"),
        ("device", renderer.device.alias),
        ("frames", str(frames)),
        ("render per frame", f"{1e3 * render_seconds / frames:.1f} ms"),
        ("wall time", f"{time.perf_counter() - clock:.2f} s"),
    ]
    data = {
        "output": str(out),
        "format": writer.kind,
        "size": list(size),
        "input": str(args.usd),
        "meshes": anim.names,
        "triangles": sum(len(f) for f in anim.faces),
        "device": renderer.device.alias,
        "frames": frames,
        "fps": anim.fps,
        "render_ms_per_frame": 1e3 * render_seconds / frames,
        "seconds": time.perf_counter() - clock,
    }
    print_summary(rows, data, args.json)
    return 0
