"""Benchmark: the paper's scenes, piles of N armadillos, a mixed pile, one CG iteration at ~1M tets, bandwidth.

Writes one JSON per run under scripts/results/ (device, driver, Warp version, commit, per-phase ms, sizes,
CG iterations and residual, max penetration) and prints a table. Times are per 1/60 s frame: stepping,
collisions and dense mapping on the device (a captured CUDA graph on GPUs), file output excluded.

    python scripts/bench.py --quick                  # CPU, under a minute: tests the harness itself
    python scripts/bench.py --assets ../shared/assets --cache-dir .warpfem-cache   # the full run (GPU)

Meshes and collision samples must already be in the preprocessing cache where Netgen is not installed (the GPU
machine): ``--prepare-only`` fills it here.
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import json
import math
import os
import platform
import re
import subprocess
import sys
import time
import tomllib
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import warp as wp

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench_check import CHECK_MAX_BODIES, CHECKS_OVER_RUN, DenseCheck  # noqa: E402

import warpfem  # noqa: E402
from warpfem.scene import ObjectConfig  # noqa: E402
from warpfem.simulation import PhaseTimer  # noqa: E402

PILES = (1, 4, 16, 64, 256, 1024)

MIXED = (("armadillo.off", 500), ("horse.ply", 500), ("spot.obj", 500), ("homer.obj", 500))
"""The mixed pile's meshes (in ``--assets``) and their coarse face counts: two of each."""


def environment(device) -> dict:
    """Device, driver, Warp version and commit of this run."""
    commit = os.environ.get("WARPFEM_COMMIT")
    if not commit:
        try:
            commit = subprocess.run(
                ["git", "rev-parse", "HEAD"], capture_output=True, text=True, cwd=ROOT
            ).stdout.strip()
        except OSError:
            commit = "unknown"
    driver = None
    if device.is_cuda:
        try:
            query = ["nvidia-smi", "--query-gpu=driver_version", "--format=csv,noheader"]
            driver = subprocess.run(query, capture_output=True, text=True).stdout.strip().splitlines()[0]
        except (OSError, IndexError):
            driver = "unknown"
    return {
        "device": device.name if device.is_cuda else platform.processor() or "cpu",
        "device_alias": device.alias,
        "driver": driver,
        "warp": wp.config.version,
        "python": platform.python_version(),
        "commit": commit,
        "date": datetime.now(UTC).isoformat(timespec="seconds"),
    }


def pile_body(
    i: int, mesh: str, faces: int, scale: float, rotate: tuple, translate: tuple, young: float
) -> ObjectConfig:
    """Body ``i`` of a pile: the mesh placed as given, Young's modulus ``young`` (Pa), the piles' material."""
    return ObjectConfig(
        name=f"body_{i}",
        mesh=mesh,
        faces=faces,
        scale=scale,
        rotate=rotate,
        translate=translate,
        young=young,
        poisson=0.3,
        density=1000.0,
        damping_stiffness=0.005,
    )


def override(doc: dict, setting: str) -> None:
    """Apply ``section.key=value`` to a scene document (``object.key``, ``obstacle.key``: on every one); the
    value is read as TOML, and a bare word that is not TOML as a string (``solver.elements=quadratic``)."""
    name, _, text = setting.partition("=")
    section, _, key = name.partition(".")
    if not key or not text:
        raise SystemExit(f"--set {setting!r}: expected section.key=value")
    try:
        value = tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        if not re.fullmatch(r"[A-Za-z_][\w.-]*", text):
            raise SystemExit(f"--set {setting!r}: the value {text!r} is neither TOML nor a bare word") from None
        value = text
    if isinstance(doc.get(section), list):
        for entry in doc[section]:
            entry[key] = value
    else:
        doc.setdefault(section, {})[key] = value


def replaced(scene, setting: str):
    """``scene`` (a ``warpfem.Scene``) with ``section.key=value`` set (``object.key`` on every object)."""
    import dataclasses

    doc = {"object": [{}]}
    override(doc, setting)
    section = setting.partition(".")[0]
    values = doc[section][0] if section == "object" else doc[section]
    if section == "object":
        return dataclasses.replace(scene, objects=[dataclasses.replace(o, **values) for o in scene.objects])
    if section == "scene":
        return dataclasses.replace(scene, **values)
    return dataclasses.replace(scene, **{section: dataclasses.replace(getattr(scene, section), **values)})


def pile(scene: warpfem.Scene, n: int, mesh: str, faces: int, scale: float = 0.0066) -> warpfem.Scene:
    """``scene`` with N 1 m armadillos (or any mesh) in layers of a 4x4 grid, each turned about y, dropped."""
    rng = np.random.default_rng(n)
    side = min(4, math.ceil(math.sqrt(n)))
    objects = []
    for i in range(n):
        layer, cell = divmod(i, side * side)
        row, col = divmod(cell, side)
        rotate = (0.0, float(rng.uniform(0, 360)), 0.0)
        translate = (1.1 * (col - (side - 1) / 2), 0.7 + 1.1 * layer, 1.1 * (row - (side - 1) / 2))
        objects.append(pile_body(i, mesh, faces, scale, rotate, translate, 1e6))
    return dataclasses.replace(scene, objects=objects)


def mixed_pile(
    scene: warpfem.Scene,
    meshes: list[tuple[str, int]],
    copies: int = 2,
    sizes: tuple[float, float] = (0.8, 1.5),
    youngs: tuple[float, float] = (3e5, 1e7),
    side: int | None = None,
) -> warpfem.Scene:
    """``scene`` with ``copies`` of each ``(mesh, faces)``, in a 1.1 m grid, each turned about y, dropped 0.2 m.

    Sizes (bounding-box diagonals, m) and Young's moduli (Pa) are spread evenly (the moduli on a log scale)
    over the bodies, in orders that do not pair the largest with the stiffest. ``side``: bodies a row and a
    column of each layer (default: as few layers as a grid of at most 4 x 4 allows); layers stand 1.6 m apart,
    so a small ``side`` stacks the bodies onto each other.
    """
    from warpfem.build import euler_rotation
    from warpfem.prep.surface import read_triangles, source_file

    n = copies * len(meshes)
    rng = np.random.default_rng(n)
    side = side or min(4, math.ceil(math.sqrt(n)))
    size = np.linspace(*sizes, n)
    young = np.geomspace(*youngs, n)[rng.permutation(n)]
    bounds = {mesh: read_triangles(source_file(mesh) or mesh)[0] for mesh, _ in meshes}
    objects = []
    for i in range(n):
        mesh, faces = meshes[i % len(meshes)]
        layer, cell = divmod(i, side * side)
        row, col = divmod(cell, side)
        lo, hi = bounds[mesh].min(axis=0), bounds[mesh].max(axis=0)
        scale = size[i] / float(np.linalg.norm(hi - lo))
        rotate = (0.0, float(rng.uniform(0, 360)), 0.0)
        centre = scale * euler_rotation(rotate) @ ((lo + hi) / 2)
        height = 0.2 + scale * (hi[1] - lo[1]) / 2 + 1.6 * layer
        target = np.array([1.1 * (col - (side - 1) / 2), height, 1.1 * (row - (side - 1) / 2)])
        translate = tuple(float(t) for t in target - centre)
        objects.append(pile_body(i, mesh, faces, scale, rotate, translate, float(young[i])))
    return dataclasses.replace(scene, objects=objects)


def comma_list(text: str, convert, valid, expected: str) -> list:
    """Comma-separated values of ``text`` ('' for none), each ``convert``-ed and ``valid``; else an argparse error."""
    try:
        values = [convert(part) for part in text.split(",") if part.strip()]
    except ValueError:
        values = None
    if values is None or not all(valid(v) for v in values):
        raise argparse.ArgumentTypeError(f"expected comma-separated {expected}, got '{text}'")
    return values


def int_list(text: str) -> list[int]:
    """An argparse type: comma-separated positive integers ('' for none)."""
    return comma_list(text, int, lambda v: v > 0, "positive integers")


def comma_list_of_counts(text: str) -> list[int]:
    """An argparse type: comma-separated integers >= 0 ('' for none)."""
    return comma_list(text, int, lambda k: k >= 0, "integers >= 0")


def tolerance_list(text: str) -> list[float]:
    """An argparse type: comma-separated CG tolerances in (0, 1) ('' for none)."""
    return comma_list(text, float, lambda v: 0.0 < v < 1.0, "tolerances between 0 and 1")


def end_gap(a: np.ndarray, b: np.ndarray) -> dict:
    """Largest and root-mean-square distance (m) between two runs' final positions, point by point."""
    gap = np.linalg.norm(a - b, axis=1)
    return {"max_m": float(gap.max()), "rms_m": float(np.sqrt(np.mean(gap**2)))}


def build(scene, device, cache_dir: Path, cg_path: str | None = None) -> warpfem.Simulation:
    """The simulation of ``scene`` (``cg_path``: see ``Solver``)."""
    return warpfem.Simulation(scene, device=device, cache_dir=cache_dir, cg_path=cg_path)


def output_ms(sim: warpfem.Simulation, frames: int = 30) -> float:
    """Milliseconds per frame to write the dense meshes (file output, outside the frame time).

    Copy to the host, a USD time sample per body, and the .usdc file written at the end (amortised over
    ``frames`` frames), in a temporary folder.
    """
    import tempfile

    from warpfem.io.usd import UsdWriter

    bodies = [(b.name, b.dense_faces) for b in sim.model.bodies]
    with tempfile.TemporaryDirectory() as folder:
        t0 = time.perf_counter()
        with UsdWriter(Path(folder) / "bench.usdc", bodies, fps=60.0, save_every=None) as writer:
            for frame in range(frames):
                writer.add_frame(frame, sim.dense_points())
        return 1000.0 * (time.perf_counter() - t0) / frames


def settle_deviation(scene, device, cache_dir: Path, frames: int, cg_path: str | None = None) -> dict:
    """How far the bench settings end from a converged run of the same scene (tet vertices, m).

    Converged: 4x the substeps and CG to a relative residual of 1e-6. Both run ``frames`` frames from the
    same start; a settled pile that ends where the converged one does was not bought with accuracy.
    """
    converged = converged_cg(scene, 4 * scene.substeps)
    ends = []
    for settings in (scene, converged):
        sim = build(settings, device, cache_dir, cg_path)
        for _ in range(frames):
            sim.advance()
        ends.append(sim.states[0].x.numpy())
    return {
        "frames": frames,
        "converged_substeps": converged.substeps,
        "converged_cg_tolerance": CONVERGED_CG,
        **end_gap(*ends),
    }


CONVERGED_CG = 1.0e-6
"""Relative CG tolerance of the converged runs the accuracy figures compare against."""


def cg_to(scene, tolerance: float, **solver):
    """``scene`` with CG run to the relative ``tolerance`` (and any other ``SolverConfig`` fields given)."""
    config = dataclasses.replace(scene.solver, cg_mode="tolerance", cg_tolerance=tolerance, **solver)
    return dataclasses.replace(scene, solver=config)


def converged_cg(scene, substeps: int):
    """``scene`` with CG run to :data:`CONVERGED_CG` (at most 1,000 iterations) at ``substeps`` per frame."""
    return dataclasses.replace(cg_to(scene, CONVERGED_CG, cg_iterations=1000), substeps=substeps)


def frame_error(sim: warpfem.Simulation, scene, device, cache_dir: Path, cg_path: str | None = None) -> dict:
    """How far one frame from ``sim``'s current state ends from the same frame with CG converged (tet vertices, m).

    Same state, same substeps, so this is the error of the bench's CG settings alone, one frame's worth:
    unlike a whole run's end (``settle_deviation``), it does not grow with how chaotic the scene is. ``sim``
    is left at the state it started from.
    """
    start = snapshot(sim)
    sim.advance()
    ours = sim.states[0].x.numpy().copy()  # on the CPU numpy() is a view of the array the next line overwrites
    sim.states[0].assign(start)
    reference = build(converged_cg(scene, scene.substeps), device, cache_dir, cg_path)
    reference.states[0].assign(start)
    reference.advance()
    return {"converged_cg_tolerance": CONVERGED_CG, **end_gap(ours, reference.states[0].x.numpy())}


def time_scene(
    scene,
    device,
    cache_dir: Path,
    frames: int,
    warmup: int = 2,
    cg_path: str | None = None,
    accuracy: bool = False,
    check_bodies: int = CHECK_MAX_BODIES,
    check_every: int = 0,
) -> dict:
    """Per-frame time of stepping + dense mapping, phase split, sizes and accuracy figures.

    With ``accuracy``, also the error of one frame from where the timed frames end against converged CG
    (:func:`frame_error`). ``check_bodies``, ``check_every``: see :class:`DenseCheck`.
    """
    sim = build(scene, device, cache_dir, cg_path)
    model, solver = sim.model, sim.solver

    def frame(timer=None):
        sim.advance(timer)
        sim.map_dense()

    check = DenseCheck(sim, 1 + warmup + frames, 2 + warmup, check_bodies, check_every)
    frame(PhaseTimer(device))  # a frame run directly (also compiles everything)
    check.after(1)
    for f in range(warmup):
        frame()  # captures the graph on CUDA
        check.after(2 + f)
    start = snapshot(sim)
    sim.read_stats()  # from here on: the timed frames
    refined, steps = sim.totals.refined_frames, sim.totals.steps
    wp.synchronize_device(device)
    t0 = time.perf_counter()
    for f in range(frames):
        frame()
        check.after(2 + warmup + f)
    wp.synchronize_device(device)
    ms = 1000.0 * (time.perf_counter() - t0) / frames
    stats = sim.read_stats(frames)
    dense = sim.dense.numpy()
    lowest = float(dense[:, 1].min()) if scene.up_axis == "Y" else float(dense[:, 2].min())
    end = sim.states[0].x.numpy().copy()  # a view on the CPU, which the rerun below would overwrite
    checked = check.result()
    phase_ms = phase_split(sim, start, frames, device)
    rerun_gap = end_gap(end, sim.states[0].x.numpy())["max_m"]
    error = frame_error(sim, scene, device, cache_dir, cg_path) if accuracy else None
    # the kernel profile where the timed frames ended (bodies in contact, not in the air)
    kernels = kernel_profile(lambda: frame(PhaseTimer(device))) if device.is_cuda else None
    return {
        "ms_per_frame": ms,
        "fps": 1000.0 / ms,
        "phase_ms": {**phase_ms, "output": output_ms(sim)},
        "phase_rerun_gap_m": rerun_gap,
        "collision_prepare_overlapped": solver.overlapped,
        **({"kernel_ms": kernels} if kernels else {}),
        "frames_timed": frames,
        "cg_path": solver.cg.mode,
        "cg_tolerance": scene.solver.stop_tolerance,
        **({"frame_error": error} if error else {}),
        "cg_grid_blocks": solver.cg.grid_blocks if solver.cg.mode == "grid" else None,
        "substeps": scene.substeps,
        "refined_frames": sim.totals.refined_frames - refined,
        "steps_timed": sim.totals.steps - steps,
        "bodies": len(model.bodies),
        "tets": model.tet_count,
        "tet_vertices": model.vertex_count,
        "dense_vertices": model.dense_count,
        "dense_triangles": int(sum(len(b.dense_faces) for b in model.bodies)),
        "cg_iterations_per_step": stats.cg_iterations,
        "cg_solves_per_step": stats.cg_solves,
        "rotation_updates": scene.solver.rotation_updates,
        "cg_residual_max": stats.cg_residual,
        "cg_float32_floor": sim.totals.cg_float32_floor,
        "contacts_max_per_step": stats.contacts_max,
        "contact_depth_max_m": stats.deepest_contact,
        "dense_penetration_m": checked["end"]["depth"],
        "dense_check": checked,
        "lowest_dense_point_m": lowest,
    }


def snapshot(sim: warpfem.Simulation) -> warpfem.State:
    """A copy of the simulation's current state (the start of the timed frames)."""
    copy = sim.model.state()
    copy.assign(sim.states[0])
    return copy


def phase_split(sim: warpfem.Simulation, start: warpfem.State, frames: int, device) -> dict:
    """Milliseconds per frame of each phase (elastic, collision, solve, map) along the timed frames.

    The timed frames are run again from their ``start`` state, phase by phase, so the split sees the same
    contacts and CG iterations as the frame time (a split taken at one state, such as the settled end, does
    not add up to it). On CUDA each phase of a frame is its own captured graph, timed on the device by events
    recorded between the replays (the host does not wait); on the CPU, synchronised wall-clock laps.
    """
    sim.states[0].assign(start)
    work = [
        *sim.frame_phases(overlap=False),  # each phase its own graph: the collision stage's prepare in its own
        ("map", sim.map_dense),
    ]
    if device.is_cuda:
        launchers = []
        for name, phase in work:
            with wp.ScopedCapture(device=device) as capture:
                phase()
            launchers.append((name, lambda graph=capture.graph: wp.capture_launch(graph)))
        events = [wp.Event(device, enable_timing=True) for _ in range(frames * len(work) + 1)]
        marks = iter(events)
        wp.record_event(next(marks))
        for _ in range(frames):
            for _, launch in launchers:
                launch()
                wp.record_event(next(marks))
        wp.synchronize_device(device)
        laps = [wp.get_event_elapsed_time(a, b) for a, b in itertools.pairwise(events)]
    else:
        laps = []
        for _ in range(frames):
            for _, phase in work:
                t0 = time.perf_counter()
                phase()
                laps.append(1000.0 * (time.perf_counter() - t0))
    out: dict[str, float] = {}
    for (name, _), lap in zip(itertools.cycle(work), laps, strict=False):
        out[name] = out.get(name, 0.0) + lap / frames
    return out


def kernel_profile(frame, top: int = 24) -> dict:
    """GPU time (ms) and launch count per kernel of one frame run directly (not captured), slowest first.

    Direct launches time each kernel on the device alone, without the launch gaps a graph removes, so the
    list says which kernel's arithmetic or memory traffic to attack; launches per frame say what a graph
    still pays per node.
    """
    wp.timing_begin(cuda_filter=wp.TIMING_KERNEL | wp.TIMING_KERNEL_BUILTIN | wp.TIMING_MEMSET)
    frame()
    results = wp.timing_end()
    table: dict[str, dict] = {}
    for r in results:
        row = table.setdefault(r.name, {"ms": 0.0, "launches": 0})
        row["ms"] += r.elapsed
        row["launches"] += 1
    ranked = sorted(table.items(), key=lambda kv: -kv[1]["ms"])
    out = dict(ranked[:top])
    out["total"] = {"ms": sum(r["ms"] for r in table.values()), "launches": sum(r["launches"] for r in table.values())}
    return out


def cg_at_scale(
    device, cells: tuple[int, int, int], iterations: int = 50, chunks: tuple[int, ...] = (1, 2, 4, 8, 64)
) -> dict:
    """Time of one fixed-count CG iteration on a box of ~1M tets, and the streaming bandwidth in the same run.

    The per-iteration-launch path is timed for each ``chunks`` entry (nonzero blocks per thread of the
    product; 64 is in effect a thread per row), the persistent grid path at the device's default chunk;
    ``cg_iteration_us`` is the faster of the two.
    """
    from warpfem.prep.shapes import box_tet_mesh
    from warpfem.sim import cg as cg_module

    V, T = box_tet_mesh((0, 0, 0), (1.0, 1.0, 1.0), cells)
    b = warpfem.ModelBuilder()
    warpfem.add_body(b, "block", V, T, 1e6, 0.3, 1000.0, pinned=V[:, 1] < 1e-9)
    model = b.finalize(device)
    solver = warpfem.Solver(model, ground=None, collision=None, cg_iterations=iterations, cg_tolerance=0.0)
    s0, s1 = model.state(), model.state()
    solver.step(s0, s1, 1 / 240)  # assemble and compile
    kind = "cuda" if device.is_cuda else "cpu"
    default = cg_module.CHUNK[kind]

    def iteration_us(chunk: int, path: str = "launches") -> float:
        cg = cg_module.CGSolver(model.row_start, model.cols, model.free, iterations, device, mode=path, chunk=chunk)
        x = wp.zeros_like(s1.v)

        def solve():
            cg.solve(solver.matrix, solver.diag_inv, solver.rhs, x)

        if device.is_cuda:
            with wp.ScopedCapture(device=device) as capture:
                solve()
            run = lambda: wp.capture_launch(capture.graph)  # noqa: E731
        else:
            run = solve
        run()
        wp.synchronize_device(device)
        reps = 20 if device.is_cuda else 2
        t0 = time.perf_counter()
        for _ in range(reps):
            run()
        wp.synchronize_device(device)
        return 1e6 * (time.perf_counter() - t0) / (reps * iterations)

    by_chunk = {str(c): iteration_us(c) for c in chunks}  # the per-iteration launches
    by_path = {"launches": by_chunk.get(str(default)) or iteration_us(default), "grid": iteration_us(default, "grid")}
    path = min(by_path, key=by_path.get)
    per_iteration_us = by_path[path]

    nnz = model.nnz_blocks  # stored: the upper triangle
    n = model.vertex_count
    full = 2 * nnz - n  # blocks of the whole symmetric matrix, as a general BSR product (bsr_mv) reads them
    # bytes one SpMV must move: blocks (36 B) + column ids (4 B) + row offsets, p gathered (12 B per row
    # at best), q written (12 B); the yardstick is the whole matrix, ours reads the upper triangle
    spmv_bytes = full * 40 + (n + 1) * 4 + 2 * n * 12
    stored_bytes = nnz * 40 + (n + 1) * 4 + 2 * n * 12
    a = wp.zeros(64 * 1024 * 1024, dtype=wp.vec4, device=device)  # 1 GiB
    c = wp.zeros_like(a)
    wp.copy(c, a)
    wp.synchronize_device(device)
    t0 = time.perf_counter()
    copies = 20 if device.is_cuda else 1
    for _ in range(copies):
        wp.copy(c, a)
    wp.synchronize_device(device)
    bandwidth = 2 * a.capacity * copies / (time.perf_counter() - t0)
    return {
        "tets": model.tet_count,
        "vertices": n,
        "nnz_blocks": full,
        "stored_blocks": nnz,
        "cg_iteration_us": per_iteration_us,
        "cg_path": path,
        "cg_iteration_us_by_path": by_path,
        "cg_iteration_us_by_chunk": by_chunk,
        "chunk": default,
        "spmv_bytes": spmv_bytes,
        "stream_bandwidth_GBps": bandwidth / 1e9,
        "spmv_floor_us": 1e6 * spmv_bytes / bandwidth,
        "ratio_to_spmv_floor": per_iteration_us / (1e6 * spmv_bytes / bandwidth),
        "stored_spmv_floor_us": 1e6 * stored_bytes / bandwidth,
    }


def _parser() -> argparse.ArgumentParser:
    """The command line's options."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="CPU, small: test the harness in under a minute")
    parser.add_argument("--device", default=None)
    parser.add_argument("--assets", type=Path, default=ROOT.parent / "shared" / "assets")
    parser.add_argument("--cache-dir", type=Path, default=ROOT / ".warpfem-cache")
    parser.add_argument("--out", type=Path, default=ROOT / "scripts" / "results")
    parser.add_argument("--frames", type=int, default=120)
    parser.add_argument(
        "--label", default="", help="a name for this run, kept in the JSON and its file name (letters, digits, . _ -)"
    )
    parser.add_argument(
        "--check-bodies",
        type=int,
        default=CHECK_MAX_BODIES,
        help=f"scenes of more bodies get the dense penetration check at the end only (default {CHECK_MAX_BODIES})",
    )
    parser.add_argument(
        "--check-every",
        type=int,
        default=0,
        help=f"frames between dense penetration checks over the run (1: every frame; default: {CHECKS_OVER_RUN} "
        "checks spread over it); each timed frame checked is held on the device until the timing ends",
    )
    parser.add_argument("--piles", type=int_list, default=",".join(map(str, PILES)))
    parser.add_argument("--prepare-only", action="store_true", help="fill the cache and stop")
    parser.add_argument("--skip", default="", help="comma list of parts to skip: paper,piles,mixed,cg")
    parser.add_argument(
        "--cg-paths",
        default="auto",
        help="comma list of CG paths to time every scene with: grid (one persistent launch; grid:B on B "
        "blocks), launches (two per iteration), auto (by size, the default)",
    )
    parser.add_argument(
        "--deviation",
        type=int_list,
        default="1,4",
        help="comma list of pile sizes whose settled state is compared with a converged run ('' for none)",
    )
    parser.add_argument(
        "--paper-substeps",
        type=int_list,
        default="",
        help="comma list: also run each paper scene at these substeps per frame (the speed/accuracy trade)",
    )
    parser.add_argument(
        "--rotation-updates",
        type=comma_list_of_counts,
        default="",
        help="comma list: also run every scene with at most these rotation updates per step ([solver] "
        "rotation_updates; the cost of implicit Euler at the step's end)",
    )
    parser.add_argument(
        "--paper-tolerances",
        type=tolerance_list,
        default="",
        help="comma list: also run each paper scene with CG to these relative tolerances (the speed/accuracy "
        "trade; every paper run reports its one-frame error against converged CG)",
    )
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="SECTION.KEY=VALUE",
        help="set a scene key in every scene of the run (object.KEY on every object; the value read as TOML)",
    )
    return parser


def _full_work(args: argparse.Namespace, skip: set[str], defaults: warpfem.Scene) -> list:
    """The full run's scenes as (kind, size, scene): the paper's (and their variants), the piles, the mixed piles."""
    armadillo = str((args.assets / "armadillo.off").resolve())
    work = []
    if "paper" not in skip:
        for name in ("paper_a_armadillo_stack", "paper_b_four_horses", "paper_c_two_bodies"):
            scene = load_with_assets(ROOT / "scenes" / f"{name}.toml", args.assets)
            work.append((name, len(scene.objects), scene))
            for k in args.paper_substeps:
                if k != scene.substeps:
                    work.append((name, len(scene.objects), dataclasses.replace(scene, substeps=k)))
            for tolerance in args.paper_tolerances:
                if scene.solver.stop_tolerance != tolerance:
                    work.append((name, len(scene.objects), cg_to(scene, tolerance)))
    if "piles" not in skip:
        work += [("pile", n, pile(defaults, n, armadillo, 500)) for n in args.piles]
    if "mixed" not in skip:
        meshes = [(str((args.assets / name).resolve()), faces) for name, faces in MIXED]
        work.append(("mixed", 2 * len(MIXED), mixed_pile(defaults, meshes)))
        # the same meshes stacked four layers high on a 2 x 2 grid, so different bodies press on each other
        work.append(("mixed", 4 * len(MIXED), mixed_pile(defaults, meshes, copies=4, side=2)))
    return work


def _set_and_vary(work: list, args: argparse.Namespace) -> list:
    """``work`` with every ``--set`` applied (validated), plus each scene at each ``--rotation-updates``."""
    try:
        for setting in args.set:
            work = [(kind, n, replaced(scene, setting)) for kind, n, scene in work]
        for _, _, scene in work:
            scene.validate()
    except (warpfem.InputError, TypeError, AttributeError) as err:  # a bad value, an unknown section or key
        raise SystemExit(f"bench: --set: {err}") from None
    return work + [
        (kind, n, dataclasses.replace(scene, solver=dataclasses.replace(scene.solver, rotation_updates=k)))
        for kind, n, scene in list(work)
        for k in args.rotation_updates
        if k != scene.solver.rotation_updates
    ]


def _time_all(work: list, cg_paths: list[str], args: argparse.Namespace, device, frames: int) -> list[dict]:
    """Each scene of ``work`` timed on each CG path, one printed line each (and its kernels on CUDA)."""
    runs = []
    for (kind, n, scene), cg_path in itertools.product(work, cg_paths):
        t0 = time.perf_counter()
        path = None if cg_path == "auto" else cg_path
        measured = kind not in ("pile", "mixed") or (kind == "pile" and n in args.deviation)
        run = time_scene(
            scene,
            device,
            args.cache_dir,
            frames,
            cg_path=path,
            accuracy=measured,
            check_bodies=args.check_bodies,
            check_every=args.check_every,
        )
        if kind == "pile" and n in args.deviation and cg_path == cg_paths[0]:
            run["settle_deviation"] = settle_deviation(scene, device, args.cache_dir, frames, path)
        run.update(kind=kind, n=n, wall_s=time.perf_counter() - t0)
        runs.append(run)
        print(
            f"{kind:28s} N={n:5d} {cg_path:8s} sub={run['substeps']} tets={run['tets']:8d} "
            f"dense tris={run['dense_triangles']:10d} "
            f"{run['ms_per_frame']:9.2f} ms/frame  CG to {run['cg_tolerance']:g}: "
            f"{run['cg_iterations_per_step']:6.1f} it/step {run['cg_solves_per_step']:4.2f} solves "
            f"upd={run['rotation_updates']}  "
            f"pen {1e3 * run['dense_penetration_m']:6.1f} mm",
            flush=True,
        )
        for name, row in run.get("kernel_ms", {}).items():
            print(f"    {row['ms']:8.3f} ms {row['launches']:6d} launches  {name[:90]}", flush=True)
    return runs


def main(argv=None) -> int:
    parser = _parser()
    args = parser.parse_args(argv)
    wp.config.log_level = wp.LOG_WARNING
    device = wp.get_device(args.device or ("cpu" if args.quick else ("cuda:0" if wp.is_cuda_available() else "cpu")))
    skip = set(filter(None, args.skip.split(",")))
    cg_paths = [p for p in args.cg_paths.split(",") if p]
    if args.check_bodies < 0:
        parser.error(f"--check-bodies: expected a body count >= 0, got {args.check_bodies}")
    if args.check_every < 0:
        parser.error(f"--check-every: expected a frame count >= 0, got {args.check_every}")
    if not re.fullmatch(r"[\w.-]*", args.label, re.ASCII):
        parser.error(f"--label: expected letters, digits, '.', '_' or '-', got {args.label!r}")
    if not cg_paths or not all(re.fullmatch(r"auto|launches|grid(:[1-9][0-9]*)?", p) for p in cg_paths):
        parser.error(f"--cg-paths: expected a comma list of auto, launches, grid or grid:B, got '{args.cg_paths}'")
    parts = {"paper", "piles", "mixed", "cg"}
    if skip - parts:
        parser.error(f"--skip: unknown part(s) {', '.join(sorted(skip - parts))}")
    scene_defaults = warpfem.load_scene(ROOT / "scenes" / "default.toml")
    results = {"environment": environment(device), "mode": "quick" if args.quick else "full", "runs": []}
    if args.label:
        results["label"] = args.label
    if args.quick:
        work = [("pile", n, pile(scene_defaults, n, "builtin:bunny", 300, scale=0.5)) for n in (1, 2)]
        ball = str(ROOT / "tests" / "data" / "golden" / "ball.obj")
        work.append(("mixed", 2, mixed_pile(scene_defaults, [("builtin:bunny", 300), (ball, 120)], copies=1)))
        frames, cg_cells = 5, (8, 8, 8)
    else:
        work, frames, cg_cells = _full_work(args, skip, scene_defaults), args.frames, (60, 60, 52)
    work = _set_and_vary(work, args)
    results["settings"] = args.set
    if args.prepare_only:  # the meshes and the collision samples a run builds from (as warpfem.Simulation does)
        from warpfem.build import prepare_scene, scene_samples

        for _, _, scene in work:
            scene_samples(scene, prepare_scene(scene, args.cache_dir), args.cache_dir)
        return 0
    results["runs"] = _time_all(work, cg_paths, args, device, frames)
    if "cg" not in skip:
        results["cg_at_scale"] = cg_at_scale(device, cg_cells)
        print("CG at scale:", json.dumps(results["cg_at_scale"]), flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    stamp = datetime.now(UTC).strftime("%Y%m%dT%H%M%SZ")
    label = f"{args.label}-" if args.label else ""
    path = args.out / f"bench-{results['mode']}-{label}{device.alias.replace(':', '')}-{stamp}.json"
    path.write_text(json.dumps(results, indent=1))
    print(f"wrote {path}")
    return 0


def load_with_assets(path: Path, assets: Path) -> warpfem.Scene:
    """The scene file at ``path`` with each object's mesh taken from the folder ``assets`` (same file name)."""
    doc = tomllib.loads(path.read_text())
    for obj in doc.get("object", []):
        obj["mesh"] = str((assets / Path(obj["mesh"]).name).resolve())
    return warpfem.Scene.from_dict(doc, base_dir=path.parent, name=path.name)


if __name__ == "__main__":
    sys.exit(main())
