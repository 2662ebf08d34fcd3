"""End-to-end benchmark: what a user waits for, the USD file written, beside the simulation alone.

Each case runs in a child process through ``warpfem.run`` (the real writer on its background thread, to a
real file). The floor any writer pays is measured in the same run: the writer's thread also writes a
frame's points raw (one ``pwritev``) to a file in the same folder, timed apart, before the writer takes the
frame on every other sampled frame and after it on the rest, so that the floor waits for the interpreter lock
and for a core beside the simulation as the writer does, at the same moments of the frame. Every frame is
sampled up to ``RAW_SAMPLE_BYTES`` of points, one frame in ``ceil(bytes / RAW_SAMPLE_BYTES)`` above, so that
measuring the floor does not slow the writer it is set against; the same bytes written again alone after the
run are reported too (raw alone). Per frame: wall (first step to file
written), simulate, write (wall and CPU) and check (on threads beside it), waiting for the writer, the raw
write (wall and CPU), and the time the writer processes spent authoring and exporting (summed over them, in
parallel with the rest); the child's peak resident memory and the largest of its writer processes'; the
file's size on disk; per run, close: the ms from the last frame's hand-over to the file written (part of wall).
One JSON per run under scripts/results/.

    python scripts/bench_end_to_end.py --quick                # CPU: the default scene and paper C, 30 frames
    python scripts/bench_end_to_end.py --assets ../shared/assets --cache-dir .warpfem-cache   # GPU: all cases

Cases: the paper scenes (a, b, c), piles of N armadillos (pile64, pile256...), any shipped scene by name
(default, shake, slide), or the writer alone taking frames of N points as fast as it can (writerN; the
default scene has 97602), with the CPU time of the caller and of the writer processes. Meshes must
already be in the preprocessing cache where Netgen is not installed (``--prepare-only`` fills it here).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from datetime import UTC, datetime
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "scripts"))
sys.path.insert(0, str(ROOT))

PAPER = {"a": "paper_a_armadillo_stack", "b": "paper_b_four_horses", "c": "paper_c_two_bodies"}

RAW_SAMPLE_BYTES = 8 << 20
"""Frames of points up to this size get the raw floor written beside every frame; larger ones beside one frame
in ``ceil(size / RAW_SAMPLE_BYTES)``, so that the floor's own writes do not hold up the writer's thread they are
set against (docs/performance.md)."""


def case_scene(case: str, assets: Path, frames: int):
    """The scene of ``case`` (a, b, c, pileN, or a shipped scene's name) with ``frames`` frames."""
    import bench

    import warpfem

    if case in PAPER:
        scene = bench.load_with_assets(ROOT / "scenes" / f"{PAPER[case]}.toml", assets)
    elif case.startswith("pile") and case[4:].isdigit():
        defaults = warpfem.load_scene(ROOT / "scenes" / "default.toml")
        scene = bench.pile(defaults, int(case[4:]), str((assets / "armadillo.off").resolve()), 500)
    elif (ROOT / "scenes" / f"{case}.toml").is_file():
        scene = warpfem.load_scene(ROOT / "scenes" / f"{case}.toml")
    else:
        raise SystemExit(f"unknown case '{case}': expected a, b, c, pileN or a scene of scenes/")
    return scene.with_frames(frames)


def raw_write_seconds(path: Path, frame_bytes: int, frames: int) -> float:
    """Seconds to write ``frames`` buffers of ``frame_bytes`` to ``path`` with plain writes (page cache, no sync)."""
    import numpy as np

    buffer = np.random.default_rng(0).random(frame_bytes // 4 + 1, dtype=np.float32)[: frame_bytes // 4]
    clock = time.perf_counter()
    with open(path, "wb") as f:
        for _ in range(frames):
            f.write(buffer.data)
    seconds = time.perf_counter() - clock
    path.unlink()
    return seconds


class RawBeside:
    """The raw floor in the run: sampled frames' points written again, raw, on the writer's thread beside it.

    Installed by wrapping :class:`~warpfem.io.stream.FrameStream`'s ``write`` consumer; the frame stream times
    both together, so the writer's own time is the stream's less :attr:`seconds`. :attr:`samples` frames were
    written raw, one in ``stride`` (see ``RAW_SAMPLE_BYTES``).
    """

    def __init__(self, path: Path) -> None:
        self.path, self.fd, self.offset = path, -1, 0
        self.seconds = self.cpu_seconds = 0.0
        self.samples, self.stride = 0, 0

    def per_frame_ms(self) -> tuple[float, float]:
        """The raw write's wall and CPU ms per sampled frame."""
        n = max(self.samples, 1)
        return 1e3 * self.seconds / n, 1e3 * self.cpu_seconds / n

    def install(self) -> None:
        """Have every frame stream made from now on write the ``write`` consumer's frames raw too."""
        from warpfem.io import stream

        original, raw = stream.FrameStream.__init__, self

        def init(self, sim, consumers, skippable=()):
            consumers = [(name, raw.after(c) if name == "write" else c) for name, c in consumers]
            original(self, sim, consumers, skippable)

        stream.FrameStream.__init__ = init

    def after(self, consume):
        """``consume`` and, on sampled frames, the raw write of the frame's points: first on every other one."""
        calls = [0]

        def both(frame, points, boxes):
            if not self.stride:
                self.stride = max(1, -(-sum(p.nbytes for p in points) // RAW_SAMPLE_BYTES))
            sampled = calls[0] % self.stride == 0
            calls[0] += 1
            first = sampled and self.samples % 2 == 0
            if first:
                self.write(points)
            consume(frame, points, boxes)
            if sampled and not first:
                self.write(points)

        return both

    def write(self, points):
        """Append ``points`` to the raw file with one ``pwritev``, timed."""
        clock, cpu = time.perf_counter(), time.thread_time()
        if self.fd < 0:
            self.fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        self.offset += os.pwritev(self.fd, points, self.offset)
        self.seconds += time.perf_counter() - clock
        self.cpu_seconds += time.thread_time() - cpu
        self.samples += 1

    def close(self) -> None:
        """Close and remove the raw file."""
        if self.fd >= 0:
            os.close(self.fd)
        self.path.unlink(missing_ok=True)


def writer_case(vertices: int, args: argparse.Namespace) -> dict:
    """The writer alone: ``args.frames`` + 1 frames of one body of ``vertices`` points, as fast as it takes them.

    Each frame differs from the last (as a simulation's do: usd-core's crate stores a repeated array once).
    """
    import numpy as np

    from warpfem.io.usd import UsdWriter

    rng = np.random.default_rng(0)
    points = rng.random((vertices, 3), dtype=np.float32)
    faces = rng.integers(0, vertices, (2 * vertices, 3))
    out = Path(args.workdir) / f"writer{vertices}.usdc"
    writer = UsdWriter(out, [("body", faces)], fps=60.0)
    time.sleep(1.0)  # as in a run, the writer processes start while the simulation is built
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    clock, cpu = time.perf_counter(), time.process_time()
    with writer:
        for frame in range(args.frames + 1):
            points[frame % vertices] += 1.0
            writer.add_frame(frame, [points])
    write, cpu = time.perf_counter() - clock, time.process_time() - cpu
    after = resource.getrusage(resource.RUSAGE_CHILDREN)  # the writer processes, waited for on closing
    writers_cpu = after.ru_utime + after.ru_stime - children.ru_utime - children.ru_stime
    raw = raw_write_seconds(out.with_suffix(".raw"), 12 * vertices, args.frames + 1)
    per = {"wall": 1e3 * write / args.frames, "write": 1e3 * write / args.frames, "write_cpu": 1e3 * cpu / args.frames}
    per.update(simulate=0.0, check=0.0, wait=0.0, write_workers=1e3 * writer.export_seconds / args.frames)
    return {
        "case": f"writer{vertices}",
        "frames": args.frames,
        "dense_vertices": vertices,
        "ms_per_frame": per,
        "raw_write_ms_per_frame": 1e3 * raw / args.frames,
        "raw_alone_ms_per_frame": 1e3 * raw / args.frames,
        "write_over_raw": write / raw,
        "cpu_ms_per_frame": {"caller": 1e3 * cpu / args.frames, "writers": 1e3 * writers_cpu / args.frames},
        "writers": writer.workers,
        "file_bytes": out.stat().st_size + sum(p.stat().st_size for p in out.with_suffix(".clips").glob("*")),
        "clips": writer.chunks > 0,
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "writer_peak_rss_mb": writer.writer_peak_bytes / 2**20,
    }


def run_case(case: str, args: argparse.Namespace) -> dict:
    """Run one case in this process and return its figures."""
    import warpfem
    import warpfem.io.usd as usd
    from warpfem.io.usd import clips_folder

    if args.switch_interval is not None:
        sys.setswitchinterval(args.switch_interval / 1e3)
    if args.writers is not None:  # what UsdWriter asks for by default
        usd.default_workers = lambda *_: args.writers
    if args.queue_mb is not None:  # frames in flight: the stream's pinned buffers, the writers' shared memory
        from warpfem.io import stream, usd_workers

        stream.QUEUE_BYTES = args.queue_mb << 20
        usd_workers.QUEUE_BYTES = args.queue_mb << 19
    if case.startswith("writer") and case[6:].isdigit():
        return writer_case(int(case[6:]), args)
    scene = case_scene(case, args.assets, args.frames)
    folder = Path(args.workdir)
    out = folder / f"{case}.usdc"
    beside = RawBeside(folder / f"{case}.beside.raw")
    beside.install()
    clock = time.perf_counter()
    try:
        summary = warpfem.run(scene, out, device=args.device, cache_dir=args.cache_dir, overwrite=True)
    finally:
        beside.close()
    command = time.perf_counter() - clock
    seconds = dict(summary.seconds)
    seconds["write"] -= beside.seconds  # the stream timed the raw write with the writer's
    seconds["write_cpu"] -= beside.cpu_seconds
    alone = raw_write_seconds(folder / f"{case}.raw", 12 * summary.dense_vertices, summary.frames + 1)
    clips = clips_folder(out)
    size = out.stat().st_size + (sum(p.stat().st_size for p in clips.glob("*")) if clips.is_dir() else 0)
    per = {k: 1e3 * v / summary.frames for k, v in seconds.items() if k not in ("prepare", "build")}
    raw_ms, raw_cpu_ms = beside.per_frame_ms()
    return {
        "case": case,
        "frames": summary.frames,
        "bodies": summary.bodies,
        "tets": summary.tets,
        "dense_vertices": summary.dense_vertices,
        "ms_per_frame": per,
        "close_ms": 1e3 * seconds.get("close", 0.0),
        "raw_write_ms_per_frame": raw_ms,
        "raw_write_cpu_ms_per_frame": raw_cpu_ms,
        "raw_sampled_frames": beside.samples,
        "raw_alone_ms_per_frame": 1e3 * alone / summary.frames,
        "write_over_raw": per["write"] / raw_ms,
        "write_cpu_over_raw_cpu": per["write_cpu"] / raw_cpu_ms,
        "write_over_raw_alone": seconds["write"] / alone,
        "writers": usd.default_workers(12 * summary.dense_vertices),
        "wall_over_larger_of_simulate_and_write": seconds["wall"] / max(seconds["simulate"], seconds["write"]),
        "seconds": {k: summary.seconds[k] for k in ("prepare", "build") if k in summary.seconds},
        "command_seconds": command,
        "file_bytes": size,
        "clips": clips.is_dir(),
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "writer_peak_rss_mb": summary.writer_peak_bytes / 2**20,
        "penetration": {"relative": summary.penetration.relative, "below_ground": summary.penetration.below_ground},
        "cg_iterations_per_step": summary.cg_iterations_per_step,
    }


def prepare_cases(args: argparse.Namespace) -> int:
    """Fill ``args.cache_dir`` with what the cases build from (prepared meshes, collision samples), as
    ``scripts/bench.py --prepare-only`` does, for a machine without Netgen."""
    from warpfem.build import prepare_scene, scene_samples

    for case in args.cases.split(","):
        if not (case.startswith("writer") and case[6:].isdigit()):
            scene = case_scene(case, args.assets, 1)
            scene_samples(scene, prepare_scene(scene, args.cache_dir), args.cache_dir)
            print(f"{case}: prepared", flush=True)
    return 0


def at_least(minimum: int):
    """An argparse type: an integer >= ``minimum``."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            value = minimum - 1
        if value < minimum:
            raise argparse.ArgumentTypeError(f"expected an integer >= {minimum}, got '{text}'")
        return value

    return parse


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="CPU: the default scene and paper C, 30 frames")
    parser.add_argument("--device", default=None)
    parser.add_argument("--assets", type=Path, default=ROOT.parent / "shared" / "assets")
    parser.add_argument("--cache-dir", type=Path, default=ROOT / ".warpfem-cache")
    parser.add_argument("--out", type=Path, default=ROOT / "scripts" / "results")
    parser.add_argument("--frames", type=at_least(1), default=120)
    parser.add_argument("--cases", default="a,b,c,default,shake,slide,pile64,pile256")
    parser.add_argument("--workdir", type=Path, default=None, help="where the files go (default: a temp folder)")
    parser.add_argument("--writers", type=at_least(0), help="writer processes (0: none)")
    parser.add_argument(
        "--queue-mb",
        type=at_least(1),
        help="MB of pinned buffers for frames in flight, and half that of the writers' shared memory (default 768)",
    )
    parser.add_argument("--switch-interval", type=float, help="the interpreter's thread switch interval (ms)")
    parser.add_argument(
        "--prepare-only",
        action="store_true",
        help="prepare every case's meshes and collision samples into --cache-dir (on the CPU) and stop",
    )
    parser.add_argument("--one", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.quick:
        args.device, args.frames, args.cases = args.device or "cpu", 30, "default,c"
    if args.prepare_only:
        return prepare_cases(args)
    if args.one:
        print(json.dumps(run_case(args.one, args)))
        return 0

    import warp as wp
    from bench import environment

    wp.config.log_level = wp.LOG_WARNING
    device = wp.get_device(args.device or ("cuda:0" if wp.is_cuda_available() else "cpu"))
    results = {
        "environment": environment(device),
        "mode": "end-to-end",
        "frames": args.frames,
        "raw_sample_bytes": RAW_SAMPLE_BYTES,
        "runs": [],
    }
    results["switch_interval_ms"] = args.switch_interval or 1e3 * sys.getswitchinterval()
    with tempfile.TemporaryDirectory(dir=args.workdir) as folder:
        for case in args.cases.split(","):
            cmd = [sys.executable, __file__, "--one", case, "--device", device.alias, "--frames", str(args.frames)]
            cmd += ["--assets", str(args.assets), "--cache-dir", str(args.cache_dir), "--workdir", folder]
            cmd += [] if args.writers is None else ["--writers", str(args.writers)]
            cmd += [] if args.queue_mb is None else ["--queue-mb", str(args.queue_mb)]
            cmd += [] if args.switch_interval is None else ["--switch-interval", str(args.switch_interval)]
            done = subprocess.run(cmd, capture_output=True, text=True, env={**os.environ, "PYTHONUNBUFFERED": "1"})
            if done.returncode != 0:
                results["runs"].append({"case": case, "error": done.stderr.strip().splitlines()[-1:]})
                print(f"{case}: failed: {done.stderr.strip()[-500:]}")
                continue
            run = json.loads(done.stdout.strip().splitlines()[-1])
            results["runs"].append(run)
            ms = run["ms_per_frame"]
            if "cpu_ms_per_frame" in run:
                print(
                    f"{case:11s} CPU ms/frame: caller {run['cpu_ms_per_frame']['caller']:.2f}, writer processes "
                    f"{run['cpu_ms_per_frame']['writers']:.2f}"
                )
            print(
                f"{case:11s} wall {ms['wall']:8.2f} ms/frame  simulate {ms['simulate']:7.2f}  write {ms['write']:7.2f}"
                f" (CPU {ms['write_cpu']:5.2f})  raw {run['raw_write_ms_per_frame']:5.2f}"
                f" (alone {run['raw_alone_ms_per_frame']:5.2f})  write/raw {run['write_over_raw']:4.2f}"
                f"  writers {run['writers']}"
                f" {ms['write_workers']:7.2f}  check {ms['check']:7.2f}  wait {ms['wait']:6.2f}"
                f"  close {run.get('close_ms', 0.0):6.1f} ms"
                f"  peak {run['peak_rss_mb']:5.0f} + {run['writers']} x {run['writer_peak_rss_mb']:4.0f} MB"
                f"  file {run['file_bytes'] / 2**20:7.0f} MB"
            )
    args.out.mkdir(parents=True, exist_ok=True)
    stamp = datetime.now(UTC).strftime("%Y%m%dT%H%M%SZ")
    path = args.out / f"bench-end-to-end-{device.alias.replace(':', '')}-{stamp}.json"
    path.write_text(json.dumps(results, indent=1))
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
