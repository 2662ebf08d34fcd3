"""``warpfem run``: run a scene, write an animated USD file and optionally a rendered preview."""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import sys
import time
from pathlib import Path
from typing import Any

from warpfem.cli.common import (
    StopRequest,
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
  warpfem run                                    the default scene (a dense bunny dropped on the ground)
  warpfem run scenes/default.toml --frames 30 --out bunny.usdc --device cpu
  warpfem run --frames 10 --device cpu --preview out.gif     a quick look on any machine
  warpfem run --preview out.mp4 --size 640x480               H.264 video beside the USD file
  warpfem run --preview frames/ --quiet --json               PNG frames, a JSON summary for scripts

exit codes: 0 ok, 1 the simulation failed (NaN/Inf), 2 bad input (or not enough memory), 130 interrupted,
143 terminated (SIGTERM); after 1, 130 and 143 the USD file holds every frame finished. A killed run
(SIGKILL) keeps every chunk on disk: the frames up to --save-every seconds back.
"""


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``run`` command to the CLI's subparsers."""
    run = sub.add_parser(
        "run",
        help="run a scene and write an animated USD file (and a preview video)",
        description="Run a scene (default: the shipped default scene) and write its dense meshes as animated USD; "
        "with --preview also render them (headless, on the simulation's device) to an mp4, a gif or PNG frames.",
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    run.add_argument("scene", nargs="?", type=Path, help="scene TOML file (default: the shipped default scene)")
    run.add_argument("--out", type=Path, help="output .usdc or .usda (default: <scene name>.usdc here)")
    run.add_argument("--overwrite", action="store_true", help="replace --out if it exists (else: an error)")
    run.add_argument(
        "--save-every",
        type=float,
        default=10.0,
        metavar="SECONDS",
        help="write the frames so far to disk at least this often, as a chunk of value clips beside --out, so a "
        "killed run keeps them (default 10)",
    )
    run.add_argument("--frames", type=int, help="override the scene's frame count")
    run.add_argument(
        "--every", type=int, default=1, metavar="N", help="write every Nth frame and the last (all are simulated)"
    )
    run.add_argument("--device", help="cpu or cuda:N (default: cuda:0 when a GPU is present, else cpu)")
    run.add_argument("--cache-dir", type=Path, default=None, help="preprocessing cache (default: ~/.cache/warpfem)")
    run.add_argument("--no-cache", action="store_true", help="preprocess again and store nothing")
    run.add_argument("--preview", type=Path, help="also render to FILE.mp4, FILE.gif or a new FOLDER of PNG frames")
    add_camera_flags(run)
    add_output_flags(run)
    run.set_defaults(func=main)


def _build(args: argparse.Namespace, scene: Any, device: str, show: bool) -> Any:
    """The scene's :class:`~warpfem.Simulation`, preprocessing under a progress bar over objects."""
    from tqdm import tqdm

    from warpfem.simulation import Simulation

    with tqdm(total=len(scene.objects), unit="object", desc="preparing", disable=not show, file=sys.stderr) as bar:
        names: list[str] = []

        def progress(name: str, message: str) -> None:
            if name not in names:
                names.append(name)
                bar.n = len(names) - 1
            bar.set_postfix_str(f"{name}: {message}"[-70:])

        sim = Simulation(
            scene,
            device=device,
            cache_dir=args.cache_dir,
            cache=not args.no_cache,
            progress=progress,
            warn=None if args.quiet else (lambda message: print(f"warpfem: {message}", file=sys.stderr, flush=True)),
            notify=None if args.quiet else (lambda message: tqdm.write(f"warpfem: {message}", file=sys.stderr)),
        )
        bar.n = len(scene.objects)
    return sim


def _simulate(
    args: argparse.Namespace,
    scene: Any,
    out: Path,
    device: str,
    size: tuple[int, int],
    flags: dict[str, Any],
    stop: StopRequest,
) -> tuple[Any, float]:
    """Prepare, simulate and (with ``--preview``) render; returns the run summary and the render seconds.

    On an interrupt or a failure the USD file and the preview keep the frames finished so far; ``stop`` is
    checked after preprocessing and after every frame.
    """
    from tqdm import tqdm

    from warpfem.io.render import AUTO_MARGIN, PreviewWriter, Renderer, framing_box
    from warpfem.runner import record

    show = shows_progress(args)
    render_seconds = 0.0
    with contextlib.ExitStack() as stack:
        sim = _build(args, scene, device, show)
        stop.check()
        bar = stack.enter_context(
            tqdm(total=scene.frames, unit="frame", desc="simulating", disable=not show, file=sys.stderr)
        )
        preview = renderer = None
        if args.preview is not None:
            ground = scene.ground.height if scene.ground.enabled else None
            obstacles = sim.obstacles_at(0.0)
            faces = [body.dense_faces for body in sim.model.bodies] + [o.faces for o in obstacles]
            renderer = Renderer(faces, *size, device=device, up_axis=scene.up_axis, ground=ground)
            preview = stack.enter_context(PreviewWriter(args.preview, scene.fps, size))

        def on_points(frame: int, points: list[Any]) -> None:
            nonlocal render_seconds
            clock = time.perf_counter()
            if renderer.camera is None:  # framed on the bodies; obstacles may reach out of the picture
                lo, hi = framing_box(points, scene.up_axis, renderer.ground, AUTO_MARGIN)
                renderer.camera = make_camera(flags, lo, hi, scene.up_axis, size[0] / size[1])
            shapes = [o.vertices @ o.matrix[:3, :3].T + o.matrix[:3, 3] for o in sim.obstacles_at(frame / scene.fps)]
            preview.add(renderer.render([*points, *shapes]))
            render_seconds += time.perf_counter() - clock

        def on_frame() -> None:
            stop.check()
            bar.update(1)
            if bar.n == scene.frames:
                bar.set_description("writing")

        summary = record(
            sim,
            out,
            overwrite=args.overwrite,
            save_every=args.save_every,
            on_frame=on_frame,
            on_points=on_points if preview else None,
            every=args.every,
        )
        if preview is not None:
            preview.close()
    return summary, render_seconds


def _identity(path: Path | None) -> tuple[int, int, int] | None:
    """What tells a file at ``path`` from the one there before an atomic replace (None: no file)."""
    if path is None or not path.exists():
        return None
    st = path.stat()
    return st.st_dev, st.st_ino, st.st_mtime_ns


def main(args: argparse.Namespace) -> int:
    """Run the scene named by ``args``; returns the exit code."""
    from warpfem.io.render import parse_size, preview_kind
    from warpfem.runner import check_output
    from warpfem.scene import default_scene_path, load_scene

    scene = load_scene(args.scene or default_scene_path())
    if args.frames is not None:
        if args.frames < 1:
            raise InputError(f"--frames must be >= 1, got {args.frames}")
        scene = scene.with_frames(args.frames)
    out = args.out or Path(Path(scene.path).stem + ".usdc")
    check_output(out, args.overwrite, "--out", "--overwrite")
    if args.preview is not None and args.preview.is_file() and not args.overwrite:
        raise InputError(f"--preview {args.preview}: the file exists; pass --overwrite to replace it")
    if args.every < 1:
        raise InputError(f"--every must be >= 1, got {args.every}")
    if not (args.save_every >= 0 and args.save_every < float("inf")):
        raise InputError(f"--save-every must be a number of seconds >= 0, got {args.save_every}")
    size = parse_size(args.size)
    flags = camera_flags(args)
    # the scene's [camera] fills in what the command line left unset
    flags["position"] = flags["position"] or scene.camera.position
    flags["target"] = flags["target"] or scene.camera.target
    flags["fov"] = args.fov if args.fov is not None else scene.camera.fov
    if args.preview is not None:
        preview_kind(args.preview)
    check_device(args.device)
    import warp as wp

    device = args.device or ("cuda:0" if wp.is_cuda_available() else "cpu")
    import pxr.Sdf  # noqa: F401  loaded before signals are caught: a signal inside USD's module loader breaks it
    import pxr.UsdGeom  # noqa: F401

    before = _identity(out), _identity(args.preview)
    try:
        with stop_signals() as stop:
            summary, render_seconds = _simulate(args, scene, out, device, size, flags, stop)
    except KeyboardInterrupt as err:  # name only what this run wrote, not a file --overwrite would have replaced
        written = [p for p, old in zip((out, args.preview), before, strict=True) if _identity(p) != old]
        return stopped(err, written)
    except FileExistsError as err:  # a file appeared at --out during the run
        raise InputError(str(err)) from None
    print_summary(*_report(summary, args.preview, size, render_seconds), args.json)
    return 0


def _penetration_text(summary: Any) -> str:
    """The independent check's worst over the run and at the end, bodies and ground, in one line."""
    worst, end = summary.penetration, summary.penetration_end

    def body(p: Any) -> str:
        return f"{1e3 * p.depth:.2f} mm ({100 * p.relative:.2f} %{', ' + p.inside if p.inside else ''})"

    def at(frame: int) -> str:
        return f" at frame {frame}" if frame >= 0 else ""

    checked = summary.penetration_frames
    bodies = "bodies - (a single body)"
    if checked:
        bodies = f"bodies {body(worst)}{at(worst.frame)} over {checked} frames checked, {body(end)} at the end"
    return (
        f"{bodies}; below the ground or in obstacles {1e3 * worst.below_ground:.2f} mm "
        f"({100 * worst.below_relative:.2f} %){at(worst.below_frame)} over {summary.ground_frames} frames checked, "
        f"{1e3 * end.below_ground:.2f} mm at the end"
    )


def _report(
    summary: Any, preview: Path | None, size: tuple[int, int], render_seconds: float
) -> tuple[list[tuple[str, str]], dict[str, Any]]:
    """The closing summary as table rows and as the ``--json`` object."""
    s = summary.seconds
    per = 1e3 / summary.frames
    render_ms = per * render_seconds
    render = f", render {render_ms:.2f}" if preview else ""
    rows = [
        ("output", str(summary.output)),
        ("preview", f"{preview} ({size[0]}x{size[1]}, {render_ms:.1f} ms per frame)" if preview else "none"),
        ("device", summary.device),
        ("frames", f"{summary.frames} ({summary.simulated_seconds:.3g} s simulated)"),
        (
            "wall time per frame",
            f"{summary.ms_per_frame:.2f} ms to the file written (simulate {per * s['simulate']:.2f}, "
            f"map {per * s['map']:.2f}{render}; on the writer's thread: write {per * s['write']:.2f}, "
            f"check {per * s['check']:.2f}; waiting for the writer {per * s['wait']:.2f})",
        ),
        ("preprocessing", f"{s['prepare']:.2f} s"),
        ("compiling kernels", f"{s['compile']:.2f} s (first run only; else loading them)"),
        ("bodies", str(summary.bodies)),
        ("tets / tet vertices", f"{summary.tets} / {summary.tet_vertices}"),
        ("dense triangles / vertices", f"{summary.dense_triangles} / {summary.dense_vertices}"),
        (
            "CG iterations per step",
            f"{summary.cg_iterations_per_step:.1f} in {summary.cg_solves_per_step:.2f} solves (max residual "
            f"{summary.cg_residual_max:.2g}, float32 floor about {summary.cg_float32_floor:.1g}; "
            + (
                f"at its cap above its tolerance in {summary.cg_short_solves} solves over {summary.cg_capped_frames} "
                f"of {summary.frames} frames)"
                if summary.cg_short_solves
                else "every solve within its tolerance before its cap)"
            ),
        ),
        ("frames at more substeps", f"{summary.refined_frames} of {summary.frames} (bodies closing fast)"),
        ("step phases per frame", ", ".join(f"{k} {v:.2f} ms" for k, v in summary.step_ms.items()) or "n/a"),
        ("contacts per step", f"{summary.contacts_per_step:.1f} (most {summary.contacts_max})"),
        ("penetration (dense meshes)", _penetration_text(summary)),
    ]
    data = {
        **dataclasses.asdict(summary),
        "output": str(summary.output),
        "preview": str(preview) if preview else None,
        "preview_size": list(size) if preview else None,
        "ms_per_frame": summary.ms_per_frame,
        "seconds": {**s, "render": render_seconds},
    }
    return rows, data
