"""Running a scene to a USD file: what ``warpfem run`` does, as :func:`run`."""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from warpfem.errors import InputError
from warpfem.io.penetration import Penetration, scene_colliders
from warpfem.scene import Scene
from warpfem.simulation import Simulation

if TYPE_CHECKING:
    import warp as wp

    from warpfem.io.stream import FrameStream
    from warpfem.io.usd import Prop


@dataclass
class RunSummary:
    """What a run did, for the closing summary.

    Attributes:
        output: The USD file written.
        device: Warp device alias.
        frames: Frames simulated (not counting frame 0, the initial pose).
        simulated_seconds: Simulated time (s).
        bodies: Number of bodies.
        tets: Tets over all bodies.
        tet_vertices: Tet vertices over all bodies.
        dense_vertices: Dense vertices over all bodies.
        dense_triangles: Dense triangles over all bodies.
        cg_iterations_per_step: Mean CG iterations per step (over all its solves).
        cg_solves_per_step: Mean CG solves per step.
        cg_residual_max: Largest final relative CG residual.
        cg_capped_frames: Frames in which CG stopped at its iteration cap above its tolerance.
        refined_frames: Frames run at more substeps (1.25, 1.5 or 2 times), their bodies closing fast on each other
            (``[collision] approach_limit``).
        cg_short_solves: Solves (of all frames' steps) that stopped at the cap above the tolerance.
        cg_float32_floor: The relative residual float32 resolves in the run's systems (an estimate); where it
            is above the tolerance the run warned, and ``cg_residual_max`` understates the systems' residual.
        seconds: Wall time (s) per phase: prepare, build, simulate, map (hand-over of frames to the writer),
            write and check (on the writer's thread, overlapping the simulation), wait (the simulation waiting
            for the writer), wall (from the first step to the file written) and close (from the last frame's
            hand-over to the file written: its body check, the writer's last frame and finishing the file,
            waiting for the threads; part of wall); write_cpu: the CPU time of write
            (its wall time less the waits for the interpreter lock and for a core); write_workers: time spent
            authoring and exporting chunks, summed over the writer processes (beside the run; on the writer's
            thread with none).
        step_ms: Milliseconds per frame inside the step: elastic, collision, solve (measured on frames run
            with a device synchronisation at each phase boundary: every frame on the CPU, the first on CUDA,
            whose later frames replay a captured graph).
        contacts_per_step: Mean body-body contacts per step, over the run.
        contacts_max: Most contacts in one step.
        contact_depth_max: Deepest contact the collision stage answered over the run (m).
        penetration: Measured on the dense meshes as written (:mod:`warpfem.io.penetration`), the worst over
            the frames checked: every frame for the ground, spheres and boxes; for mesh obstacles and for bodies
            inside each other frames spaced so that each check takes about a tenth of the run's time (every
            frame where it is cheap), the last one always.
        penetration_end: The same at the last frame.
        penetration_frames: Frames whose bodies were checked against each other.
        ground_frames: Frames checked against the ground and obstacles (every written frame, but for those the
            check's thread skipped to keep up with the run; the last always).
        writer_peak_bytes: The largest peak resident memory of one of the processes that wrote the file (bytes;
            0 when it was written on the writer's thread).
    """

    output: Path
    device: str
    frames: int
    simulated_seconds: float
    bodies: int
    tets: int
    tet_vertices: int
    dense_vertices: int
    dense_triangles: int
    cg_iterations_per_step: float
    cg_solves_per_step: float
    cg_residual_max: float
    cg_capped_frames: int
    cg_short_solves: int
    cg_float32_floor: float = 0.0
    refined_frames: int = 0
    seconds: dict[str, float] = field(default_factory=dict)
    step_ms: dict[str, float] = field(default_factory=dict)
    contacts_per_step: float = 0.0
    contacts_max: int = 0
    contact_depth_max: float = 0.0
    penetration: Penetration = field(default_factory=Penetration)
    penetration_end: Penetration = field(default_factory=Penetration)
    penetration_frames: int = 0
    ground_frames: int = 0
    writer_peak_bytes: int = 0

    @property
    def ms_per_frame(self) -> float:
        """Wall time per frame from the first step to the file written (ms).

        It counts the simulation and whatever part of the writing and the penetration check did not overlap it.
        """
        return 1000.0 * self.seconds.get("wall", 0.0) / max(self.frames, 1)


def run(
    scene: Scene,
    out: str | Path,
    frames: int | None = None,
    device: str | None = None,
    cache_dir: str | Path | None = None,
    cache: bool = True,
    overwrite: bool = False,
    save_every: float | None = 10.0,
    progress: Callable[[str, str], None] | None = None,
    warn: Callable[[str], None] | None = None,
    every: int = 1,
) -> RunSummary:
    """Run ``scene`` and write its dense meshes to ``out`` (USD), as ``warpfem run`` does.

    Args:
        scene: A validated scene.
        out: Target ``.usdc`` or ``.usda`` file, written atomically; on an interrupt (Ctrl-C) or NaN the
            frames finished so far are kept in a valid file.
        frames: Override the scene's frame count.
        device: ``"cpu"`` or ``"cuda:N"`` (default: ``cuda:0`` when there is a GPU, else the CPU).
        cache_dir: The preprocessing cache (default: ``$WARPFEM_CACHE``, else ``~/.cache/warpfem``).
        cache: False preprocesses again and stores nothing.
        progress: Receives ``(object name, message)`` as each preprocessing stage starts.
        warn: Receives one-line warnings (see :class:`~warpfem.simulation.Simulation`).
        overwrite: Whether an existing ``out`` may be replaced.
        save_every: Longest time between chunks of the file on disk (s), so a killed process keeps the frames
            up to the last chunk; None: chunks by size only (see :class:`~warpfem.io.usd.UsdWriter`).
        every: Write every ``every``-th frame and the last (time codes stay frame numbers); the simulation
            still steps every frame.

    Returns:
        The run's summary.

    Raises:
        InputError: A bad scene, mesh, output path or device (one line).
        SimulationError: The state became NaN/Inf (the frames before it are in the file).
    """
    if frames is not None:
        if frames < 1:
            raise InputError(f"frames must be >= 1, got {frames}")
        scene = scene.with_frames(frames)
    out = Path(out)
    check_output(out, overwrite)
    if isinstance(every, bool) or not isinstance(every, int) or every < 1:
        raise InputError(f"every must be an integer >= 1, got {every!r}")
    sim = Simulation(scene, device=device, cache_dir=cache_dir, cache=cache, progress=progress, warn=warn)
    return record(sim, out, overwrite=overwrite, save_every=save_every, every=every)


def check_output(out: Path, overwrite: bool, option: str = "out", overwrite_flag: str = "overwrite=True") -> None:
    """Raise :class:`InputError` (naming ``option``) before anything runs if ``out`` cannot be written.

    It must end in ``.usdc`` or ``.usda``, its folder exist, and a file there (or its clips folder) may be
    replaced only with ``overwrite`` (``overwrite_flag`` names how to ask for it).
    """
    from warpfem.io.usd import clips_folder

    if out.suffix.lower() not in (".usdc", ".usda"):
        raise InputError(f"{option} {out}: the output must end in .usdc or .usda")
    if not out.resolve().parent.is_dir():
        raise InputError(f"{option} {out}: folder {out.resolve().parent} does not exist")
    if out.is_file() and not overwrite:
        raise InputError(f"{option} {out}: the file exists; pass {overwrite_flag} to replace it")
    clips = clips_folder(out)
    if clips.exists() and not overwrite:
        raise InputError(f"{option} {out}: its clips folder {clips} exists; pass {overwrite_flag} to replace it")


def record(
    sim: Simulation,
    out: Path,
    overwrite: bool = False,
    save_every: float | None = 10.0,
    on_frame: Callable[[], None] | None = None,
    on_points: Callable[[int, list[np.ndarray]], None] | None = None,
    every: int = 1,
) -> RunSummary:
    """Step ``sim`` through its scene's frames from where it is, writing the dense meshes to ``out``.

    The file is written and the penetration checked on a background thread while the next frames simulate
    (:class:`~warpfem.io.stream.FrameStream`); the simulation waits only when the writer is a few frames behind.

    Args:
        sim: A simulation at frame 0.
        out: Target ``.usdc`` or ``.usda`` file (see :func:`run`).
        overwrite: Whether an existing ``out`` may be replaced.
        save_every: Longest time between chunks of the file on disk (s); None: chunks by size only.
        on_frame: Called once per finished frame, on the calling thread.
        on_points: Called as ``on_points(frame, points)`` with each written frame's dense points (one (n_i, 3)
            array per body), frame 0 included, on the calling thread; its time is not in the summary.
        every: Write (map, check, hand to ``on_points``) every ``every``-th frame and the last.
    """
    from warpfem.io.stream import FrameStream
    from warpfem.io.usd import UsdWriter
    from warpfem.io.usd_layers import moving_paths

    scene = sim.scene
    check = _Check(sim)
    bodies = [(b.name, b.dense_faces) for b in sim.model.bodies]
    props, poses = _props(sim)
    try:
        writer = UsdWriter(
            out,
            bodies,
            fps=scene.fps,
            up_axis=scene.up_axis,
            overwrite=overwrite,
            save_every=save_every,
            props=props,
            final_frame=scene.frames,
        )
    except (ValueError, OSError) as err:
        raise InputError(str(err)) from None

    transforms = _by_frame(poses, scene.fps, every) if moving_paths(props) else lambda frame: []

    def write(frame: int, points: list[np.ndarray], boxes: np.ndarray) -> None:
        writer.add_frame(frame, points, transforms(frame), extents=boxes)
        if frame == scene.frames:  # the file is finished here, beside the last frame's body check
            writer.close()

    seconds = {**sim.seconds, "simulate": 0.0, "map": 0.0}
    with writer:  # an error before the first frame leaves nothing, the writer's staged files included
        clock = time.perf_counter()
        sim.capture()  # before the writer's thread waits on the device: no capture may be active then
        stream = FrameStream(sim, [("write", write), ("check", check.ground)], skippable=("check",))
        seconds["build"] = seconds.get("build", 0.0) + time.perf_counter() - clock
        started = check.started = time.perf_counter()
        with stream:
            handed_over = _stream_frames(sim, stream, check, seconds, on_frame, on_points, every)
        clock, cpu = time.perf_counter(), time.thread_time()  # after an early stop the writer writes what is left here
    ended = time.perf_counter()
    seconds["write"] = stream.seconds["write"] + ended - clock
    seconds["write_cpu"] = stream.cpu_seconds["write"] + time.thread_time() - cpu
    seconds["write_workers"] = writer.export_seconds
    seconds["check"] = stream.seconds["check"] + check.seconds
    seconds["wait"] = stream.waited
    seconds["wall"] = ended - started
    seconds["close"] = ended - handed_over
    summary = _summary(sim, out, seconds, check)
    summary.writer_peak_bytes = writer.writer_peak_bytes
    return summary


def _props(sim: Simulation) -> tuple[list[Prop], Callable[[float], list[np.ndarray]]]:
    """The obstacles and handles to write beside the bodies, and the moving ones' transforms at a time (s).

    An obstacle without keys is written with its fixed transform. The transforms are the matrices of
    ``sim.obstacles_at`` and ``sim.handles_at``, worked out without the meshes those build: the writer's thread
    asks for them every frame, holding the interpreter lock.
    """
    from warpfem.io.usd import Prop
    from warpfem.sim.integrate import collider_pose

    obstacles = list(sim.solver.obstacles)
    still = [getattr(c, "motion", None) is None for c in obstacles]
    props = [
        Prop(f"obstacles/{o.name}", o.vertices, o.faces, matrix=o.matrix if fixed else None)
        for o, fixed in zip(sim.obstacles_at(0.0), still, strict=True)
    ]
    props += [Prop(f"handles/{h.name}", h.vertices, h.faces, guide=True) for h in sim.handles_at(0.0)]
    moving = [c for c, fixed in zip(obstacles, still, strict=True) if not fixed]
    handles = [h.motion for h in sim.solver.handles]

    def poses(time: float) -> list[np.ndarray]:
        return [*(collider_pose(c, time) for c in moving), *(motion.matrix(time) for motion in handles)]

    return props, poses


def _by_frame(poses: Callable[[float], list[np.ndarray]], fps: float, every: int) -> Callable[[int], list[np.ndarray]]:
    """``poses`` at a frame's time (``frame / fps``), worked out for the next 64 written frames at a time.

    The writer's thread asks for them between frames, when its code and data have left the caches: a block of
    frames costs about what one frame did there.
    """
    block: dict[int, list[np.ndarray]] = {}

    def at(frame: int) -> list[np.ndarray]:
        if frame not in block:
            block.clear()
            block.update((f, poses(f / fps)) for f in range(frame, frame + 64 * every, every))
        return block[frame]

    return at


def _stream_frames(
    sim: Simulation,
    stream: FrameStream,
    check: _Check,
    seconds: dict[str, float],
    on_frame: Callable[[], None] | None,
    on_points: Callable[[int, list[np.ndarray]], None] | None,
    every: int,
) -> float:
    """Step every frame of ``sim``'s scene, handing frame 0, every ``every``-th and the last to ``stream``.

    The bodies are checked against each other where ``check`` says so, after the frame is handed over.
    Returns when (``time.perf_counter``) the last frame was handed over.
    """
    frames, handed_over = sim.scene.frames, 0.0
    for frame in range(frames + 1):
        t0 = time.perf_counter()
        if frame:
            sim.step_frame(profile=not sim.device.is_cuda or frame == 1)
        t1 = time.perf_counter()
        seconds["simulate"] += t1 - t0
        if frame % every == 0 or frame == frames:
            stream.submit(frame)
            handed_over = time.perf_counter()
            seconds["map"] += handed_over - t1
            if check.bodies_due(frame):
                check.bodies_now(frame, *stream.on_device)
            if on_points:
                on_points(frame, sim.dense_points())
        if frame and on_frame:
            on_frame()
    return handed_over


class _Check:
    """The independent penetration check along a run.

    The ground, spheres and boxes on every written frame it keeps up with (it skips to the newest when frames
    wait for it, the last always), on a thread of its own (NumPy), and there too mesh obstacles (Warp's CPU
    kernels, which release the interpreter lock) on the last frame and on frames spaced so that they take about
    a tenth of the run's time.
    Bodies inside each other the same way, on the simulation's device, launched from the stepping thread
    between frames and read at the next check. Only the stepping thread touches the device: Warp's reads of
    CUDA arrays swap the device's current stream, a state of the whole device, which a second thread doing
    the same could leave on another stream.
    """

    SHARE = 0.1

    def __init__(self, sim: Simulation) -> None:
        import warp as wp

        from warpfem.io.penetration import PenetrationCheck
        from warpfem.kernels import penetration

        wp.load_module(penetration, device=sim.device)  # compiled here, not inside the first check's time
        if not sim.device.is_cpu and any(o.kind == "mesh" for o in sim.scene.obstacles):
            wp.load_module(penetration, device="cpu")  # the mesh obstacles' check runs there
        self.body_check = PenetrationCheck([b.dense_faces for b in sim.model.bodies], sim.body_names, sim.device)
        self.counts = [b.dense_count for b in sim.model.bodies]
        self.sim = sim
        self.bodies = len(sim.model.bodies) > 1
        self.ground_worst = self.ground_end = self.body_worst = self.body_end = Penetration()
        self.frames_checked = self.ground_frames = 0
        self.next = self.next_mesh = 1
        self.pending: int | None = None  # the frame of a body check launched and not yet read
        self.seconds = 0.0
        self.started = time.perf_counter()  # set again by the run as it starts stepping

    def ground(self, frame: int, points: list[np.ndarray], boxes: np.ndarray) -> None:
        """Check frame ``frame``'s dense meshes against the ground and obstacles (any thread).

        Mesh obstacles (a winding number or closest-point query per point) on the frames spaced like the bodies'
        checks, the last always; the ground, spheres and boxes every frame. ``boxes``: the bodies' bounds from the
        device (an axis-aligned ground reads its lowest point off them).
        """
        last = frame == self.sim.scene.frames
        ground, obstacles = scene_colliders(self.sim, frame / self.sim.fps)
        meshes = any(o.mesh is not None for o in obstacles)
        due = last or frame >= self.next_mesh
        if meshes and not due:
            obstacles = [o for o in obstacles if o.mesh is None]
        clock = time.perf_counter()
        result = self.body_check.measure(points, ground, obstacles, bodies=False, boxes=boxes)
        result = replace(result, below_frame=frame if result.below_relative > 0.0 else -1)
        if meshes and due and frame > 0:
            self.next_mesh = self._next(frame, time.perf_counter() - clock)
        self.ground_worst = self.ground_worst.worst(result)
        self.ground_frames += 1
        if last:
            self.ground_end = result

    def bodies_due(self, frame: int) -> bool:
        """Whether the bodies are checked against each other at frame ``frame`` (written)."""
        return self.bodies and (frame == self.sim.scene.frames or (frame >= self.next and frame > 0))

    def bodies_now(self, frame: int, dense: wp.array, bounds: wp.array) -> None:
        """Check the bodies against each other at frame ``frame`` (the stepping thread only).

        ``dense`` and ``bounds``: the frame's mapped dense points and the bodies' boxes, on the device, as the
        frame stream has them (:attr:`~warpfem.io.stream.FrameStream.on_device`).

        The check queues on the device after the frame and is read at the next check (the last frame's at
        once), so the stepping thread waits for neither; the dense points never pass through the host. Its
        cost, for spacing the checks, is the thread's time and the previous check's device time; the first
        check, which builds the bodies' trees, is followed by another at the next frame to measure a check's
        own cost. The ground and obstacles of this frame are :meth:`ground`'s, on the other thread.
        """
        first = self.frames_checked == 0
        clock = time.perf_counter()
        self._collect()
        self.body_check.start_bodies(dense, self.counts, bounds)
        self.pending = frame
        if frame == self.sim.scene.frames:
            self._collect()
        cost = time.perf_counter() - clock
        self.seconds += cost
        self.frames_checked += 1
        self.next = frame + 1 if first else self._next(frame, cost + self.body_check.device_seconds)

    def _collect(self) -> None:
        """Read the body check launched last, if any, into the worst and the last frame's figures."""
        if self.pending is None:
            return
        result = self.body_check.collect_bodies()
        result = replace(result, frame=self.pending if result.relative > 0.0 else -1)
        self.body_worst = self.body_worst.worst(result)
        if self.pending == self.sim.scene.frames:
            self.body_end = result
        self.pending = None

    def _next(self, frame: int, cost: float) -> int:
        """The next frame due for a check that cost ``cost`` s at ``frame``: a tenth of the run's time."""
        elapsed = time.perf_counter() - self.started
        return frame + max(1, math.ceil(cost / (self.SHARE * elapsed / frame)))

    @property
    def worst(self) -> Penetration:
        return self.body_worst.worst(self.ground_worst)

    @property
    def end(self) -> Penetration:
        return self.body_end.worst(self.ground_end)


def _summary(sim: Simulation, out: Path, seconds: dict[str, float], check: _Check) -> RunSummary:
    model, totals, timer = sim.model, sim.totals, sim.phase_timer
    return RunSummary(
        output=out,
        device=sim.device.alias,
        frames=sim.frame,
        simulated_seconds=sim.time,
        bodies=len(model.bodies),
        tets=model.tet_count,
        tet_vertices=model.vertex_count,
        dense_vertices=model.dense_count,
        dense_triangles=sum(len(b.dense_faces) for b in model.bodies),
        cg_iterations_per_step=totals.cg_iterations / max(totals.steps, 1),
        cg_solves_per_step=totals.cg_solves / max(totals.steps, 1),
        cg_residual_max=totals.cg_residual_max,
        cg_capped_frames=totals.cg_capped_frames,
        cg_short_solves=totals.cg_short_solves,
        cg_float32_floor=totals.cg_float32_floor,
        refined_frames=totals.refined_frames,
        seconds=seconds,
        step_ms={k: 1000.0 * v / max(timer.frames, 1) for k, v in timer.seconds.items()},
        contacts_per_step=totals.contacts / max(totals.steps, 1),
        contacts_max=totals.contacts_max,
        contact_depth_max=totals.deepest_contact,
        penetration=check.worst,
        penetration_end=check.end,
        penetration_frames=check.frames_checked,
        ground_frames=check.ground_frames,
    )
