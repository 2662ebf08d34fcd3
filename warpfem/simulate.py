"""Running a scene: preprocess its bodies, build the model, step frames, map dense meshes, write USD."""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import warp as wp

from warpfem.collision import CollisionSettings
from warpfem.embedding import map_dense
from warpfem.errors import InputError, SimulationError
from warpfem.fem import RotationWatch
from warpfem.integrate import Box, Ground, Sphere
from warpfem.model import Model, ModelBuilder
from warpfem.preprocess import PreparedBody, prepare
from warpfem.scene import ObjectConfig, SceneConfig
from warpfem.solver import Solver

FAST_TURN = 0.03
"""Rotation per step (rad) past which a body gains visible energy (docs/tradeoff.md): warned about once."""


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
        cg_iterations_per_step: Mean CG iterations per step.
        cg_residual_max: Largest final relative CG residual.
        seconds: Wall time per phase (s): prepare, build, simulate, map, write.
        step_ms: Milliseconds per frame inside the step: elastic, collision, solve (measured on frames run
            with a device synchronisation at each phase boundary: every frame on the CPU, the first on CUDA,
            whose later frames replay a captured graph).
        contacts_per_step: Mean body-body contacts per step, over the run.
        contacts_max: Most contacts in one step.
        contact_depth_max: Deepest contact over the run (m).
        dense_penetration: Deepest dense vertex inside another body's tet mesh at the last frame (m).
        dense_penetration_relative: The same relative to the smallest body's size.
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
    cg_residual_max: float
    seconds: dict[str, float] = field(default_factory=dict)
    step_ms: dict[str, float] = field(default_factory=dict)
    contacts_per_step: float = 0.0
    contacts_max: int = 0
    contact_depth_max: float = 0.0
    dense_penetration: float = 0.0
    dense_penetration_relative: float = 0.0

    @property
    def ms_per_frame(self) -> float:
        """Wall time per frame of simulation, mapping and writing (ms)."""
        work = self.seconds.get("simulate", 0) + self.seconds.get("map", 0) + self.seconds.get("write", 0)
        return 1000.0 * work / max(self.frames, 1)


def euler_rotation(degrees: tuple[float, float, float]) -> np.ndarray:
    """Rotation matrix of XYZ Euler angles in degrees: about x first, then y, then z (R = Rz Ry Rx)."""
    ax, ay, az = (math.radians(a) for a in degrees)
    rx = np.array([[1, 0, 0], [0, math.cos(ax), -math.sin(ax)], [0, math.sin(ax), math.cos(ax)]])
    ry = np.array([[math.cos(ay), 0, math.sin(ay)], [0, 1, 0], [-math.sin(ay), 0, math.cos(ay)]])
    rz = np.array([[math.cos(az), -math.sin(az), 0], [math.sin(az), math.cos(az), 0], [0, 0, 1]])
    return rz @ ry @ rx


def add_prepared_body(builder: ModelBuilder, obj: ObjectConfig, prepared: PreparedBody) -> None:
    """Place a preprocessed body in the world (scale, rotate, translate) and add it to ``builder``."""
    rot = euler_rotation(obj.rotate)
    offset = np.asarray(obj.translate, dtype=np.float64)

    def place(points: np.ndarray) -> np.ndarray:
        return obj.scale * points @ rot.T + offset

    tet_x = place(prepared.tet_vertices)
    pinned = None
    if obj.pin_min is not None:
        pinned = np.all((tet_x >= np.asarray(obj.pin_min)) & (tet_x <= np.asarray(obj.pin_max)), axis=1)
    builder.add_body(
        obj.name,
        tet_x,
        prepared.tets,
        young=obj.young,
        poisson=obj.poisson,
        density=obj.density,
        damping_mass=obj.damping_mass,
        damping_stiffness=obj.damping_stiffness,
        velocity=obj.velocity,
        pinned=pinned,
        dense_vertices=place(prepared.dense_vertices),
        dense_faces=prepared.dense_faces,
        embed_tet=prepared.embed_tet,
        embed_bary=prepared.embed_bary,
        vertex_depth=obj.scale * prepared.vertex_depth,
        vertex_grad=prepared.vertex_grad @ rot.T,
        surface_faces=prepared.boundary_faces,
        self_collision=obj.self_collision,
        collision_spacing=obj.collision_spacing,
    )


def ground_of(scene: SceneConfig) -> Ground | None:
    """The scene's ground plane in solver terms, or None."""
    if not scene.ground.enabled:
        return None
    up = (0.0, 1.0, 0.0) if scene.up_axis == "Y" else (0.0, 0.0, 1.0)
    g = scene.ground
    return Ground(height=g.height, stiffness=g.stiffness, friction=g.friction, up=up)


def obstacles_of(scene: SceneConfig) -> list[Sphere | Box]:
    """The scene's static spheres and boxes in solver terms."""
    return [
        Sphere(o.center, o.radius, o.stiffness, o.friction)
        if o.kind == "sphere"
        else Box(o.center, o.half_extents, o.stiffness, o.friction)
        for o in scene.obstacles
    ]


def solver_of(scene: SceneConfig, model: Model, cg_path: str | None = None) -> Solver:
    """The solver a scene asks for (``cg_path``: see :class:`Solver`)."""
    c = scene.collision
    return Solver(
        model,
        gravity=scene.gravity,
        ground=ground_of(scene),
        obstacles=obstacles_of(scene),
        cg_iterations=scene.solver.cg_iterations,
        cg_tolerance=scene.solver.stop_tolerance,
        collision=CollisionSettings(stiffness=c.stiffness, friction=c.friction) if c.enabled else None,
        cg_path=cg_path,
    )


class PhaseTimer:
    """Wall time per phase (s), measured by synchronising the device at each phase boundary."""

    def __init__(self, device) -> None:
        self.device = device
        self.seconds: dict[str, float] = {}
        self._last = time.perf_counter()

    def start(self) -> None:
        """Synchronise and start timing the next phase."""
        wp.synchronize_device(self.device)
        self._last = time.perf_counter()

    def lap(self, phase: str) -> None:
        """Synchronise and add the time since the last lap (or start) to ``phase``."""
        wp.synchronize_device(self.device)
        now = time.perf_counter()
        self.seconds[phase] = self.seconds.get(phase, 0.0) + now - self._last
        self._last = now


class Simulation:
    """A model, its solver and states, advanced one output frame at a time.

    On CUDA the substeps of a frame are captured once as a graph and replayed; elsewhere they run
    directly. Dense meshes are mapped on the device; the host reads them once per frame.
    """

    def __init__(self, model: Model, solver: Solver, substeps: int, dt: float) -> None:
        self.model, self.solver, self.substeps, self.dt = model, solver, substeps, dt
        self.states = [model.state(), model.state()]
        self.dense = wp.zeros(model.dense_count, dtype=wp.vec3, device=model.device)
        self._graph = None

    def frame_phases(self, overlap: bool = True) -> list[tuple[str, Callable[[], None]]]:
        """A frame's work in order: each substep's phases (see ``Solver.phases``), as (name, launcher) pairs.

        The states alternate between substeps; after an odd count the last one is copied back into
        ``states[0]`` as part of the last "solve". ``overlap``: see ``Solver.phases``.
        """
        a, b = self.states
        out = []
        for i in range(self.substeps):
            src, dst = (a, b) if i % 2 == 0 else (b, a)
            out += self.solver.phases(src, dst, self.dt, overlap)
        if self.substeps % 2 == 1:
            out.append(("solve", lambda: a.assign(b)))
        return out

    def _substeps(self, timer: PhaseTimer | None = None) -> None:
        if timer:
            timer.start()
        for name, phase in self.frame_phases(overlap=timer is None):
            phase()
            if timer:
                timer.lap(name)

    def advance(self, timer: PhaseTimer | None = None) -> None:
        """Advance one output frame (``substeps`` steps).

        With a ``timer`` the frame runs directly, timing each phase; without one on CUDA, the frame is a
        captured graph (captured on the first such call).
        """
        if timer is not None or not self.model.device.is_cuda:
            self._substeps(timer)
            return
        if self._graph is None:
            with wp.ScopedCapture(device=self.model.device) as capture:
                self._substeps()
            self._graph = capture.graph
        wp.capture_launch(self._graph)

    def dense_points(self) -> list[np.ndarray]:
        """Map the dense meshes from the current state; one (n_i, 3) array per body."""
        m = self.model
        map_dense(m.tets, self.states[0].x, m.dense_tet, m.dense_bary, self.dense)
        flat = self.dense.numpy()
        return [flat[b.dense_start : b.dense_start + b.dense_count] for b in m.bodies]

    def check_finite(self, frame: int) -> None:
        """Raise :class:`SimulationError` naming the frame and body if the state became NaN/Inf."""
        bad = self.solver.first_bad_vertex()
        if bad is not None:
            body = self.model.body_of_vertex(bad)
            raise SimulationError(
                f"frame {frame}: body '{body.name}' became NaN/Inf (tet vertex {bad - body.vertex_start}); "
                "try a smaller time step (more substeps), a lower Young's modulus or more CG iterations"
            )


def prepare_scene(
    scene: SceneConfig, cache_dir: Path | None, progress: Callable[[str], None] | None = None
) -> list[PreparedBody]:
    """Preprocess (or load from the cache) every body of ``scene``."""
    prepared = []
    for obj in scene.objects:
        if progress:
            progress(f"preparing '{obj.name}' ({obj.mesh}, {obj.faces} faces)")
        try:
            prepared.append(
                prepare(obj.mesh, faces=obj.faces, subdivide=obj.subdivide, maxh=obj.maxh, cache_dir=cache_dir)
            )
        except InputError as err:
            raise InputError(f"{scene.path}: object '{obj.name}': {err}") from None
    return prepared


def run_scene(
    scene: SceneConfig,
    output: Path,
    device: str | None = None,
    cache_dir: Path | None = None,
    progress: Callable[[str], None] | None = None,
    on_frame: Callable[[], None] | None = None,
    on_points: Callable[[int, list[np.ndarray]], None] | None = None,
    warn: Callable[[str], None] | None = None,
    overwrite: bool = True,
    save_every: float | None = 10.0,
) -> RunSummary:
    """Run ``scene`` and write its dense meshes to ``output`` (USD).

    Args:
        scene: A validated scene.
        output: Target .usdc/.usda file; written atomically. If the run is interrupted (Ctrl-C) or stops on
            NaN, the frames completed so far are kept in a valid file.
        device: Warp device; default: CUDA when present, else CPU.
        cache_dir: Preprocessing cache folder, or None for no cache.
        progress: Receives one-line status messages.
        on_frame: Called once per finished frame.
        on_points: Called as ``on_points(frame, points)`` with each frame's dense points (one (n_i, 3) array
            per body), frame 0 (the initial pose) included, after the frame is written; its time is not
            counted in the summary's phases.
        warn: Receives one-line warnings, each at most once per run (contact buffer overflow; a body moving
            more than half a tet per step, where thin parts may tunnel).
        overwrite: Whether an existing ``output`` may be replaced (else FileExistsError).
        save_every: Shortest time between USD snapshots (s), so a killed process keeps the frames up to the
            last one (see :mod:`warpfem.usd_out`); None: write only at the end.

    Returns:
        The run's summary.
    """
    from warpfem.usd_out import UsdWriter

    seconds: dict[str, float] = {"prepare": 0.0, "build": 0.0, "simulate": 0.0, "map": 0.0, "write": 0.0}
    t0 = time.perf_counter()
    prepared = prepare_scene(scene, cache_dir, progress)
    seconds["prepare"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    device = wp.get_device(device or ("cuda:0" if wp.is_cuda_available() else "cpu"))
    builder = ModelBuilder()
    for obj, prep in zip(scene.objects, prepared, strict=True):
        add_prepared_body(builder, obj, prep)
    model = builder.finalize(device)
    solver = solver_of(scene, model)
    sim = Simulation(model, solver, scene.substeps, scene.dt)
    seconds["build"] = time.perf_counter() - t0

    bodies = [(b.name, b.dense_faces) for b in model.bodies]
    timer = PhaseTimer(device)
    profiled = 0
    contacts = Contacts()
    spin = RotationWatch(model, solver.rotation)
    spin_warned = False
    with UsdWriter(
        output, bodies, fps=scene.fps, up_axis=scene.up_axis, overwrite=overwrite, save_every=save_every
    ) as writer:
        t0 = time.perf_counter()
        points = sim.dense_points()
        writer.add_frame(0, points)
        seconds["write"] += time.perf_counter() - t0
        if on_points:
            on_points(0, points)
        for frame in range(1, scene.frames + 1):
            profile = not device.is_cuda or frame == 1
            t0 = time.perf_counter()
            sim.advance(timer if profile else None)
            sim.check_finite(frame)
            profiled += profile
            t1 = time.perf_counter()
            points = sim.dense_points()
            t2 = time.perf_counter()
            writer.add_frame(frame, points)
            t3 = time.perf_counter()
            seconds["simulate"] += t1 - t0
            seconds["map"] += t2 - t1
            seconds["write"] += t3 - t2
            contacts.read(solver, frame, warn, scene.dt)
            per_step = spin.turned() / scene.substeps
            if warn and not spin_warned and frame > 1 and per_step.max() > FAST_TURN:
                body = model.bodies[int(np.argmax(per_step))]
                warn(
                    f"warning: frame {frame}: body '{body.name}' turns {per_step.max():.3g} rad per step (over "
                    f"{FAST_TURN}): one linear solve per step adds energy this fast; raise substeps"
                )
                spin_warned = True
            if on_points:
                on_points(frame, points)
            if on_frame:
                on_frame()
        stats = solver.read_cg_stats()
        t_close = time.perf_counter()  # the writer saves the file on leaving this block
    seconds["write"] += time.perf_counter() - t_close
    penetration = dense_penetration(sim, points)
    return RunSummary(
        output=output,
        device=device.alias,
        frames=scene.frames,
        simulated_seconds=scene.frames / scene.fps,
        bodies=len(model.bodies),
        tets=model.tet_count,
        tet_vertices=model.vertex_count,
        dense_vertices=model.dense_count,
        dense_triangles=sum(len(b.dense_faces) for b in model.bodies),
        cg_iterations_per_step=stats.iterations / max(stats.solves, 1),
        cg_residual_max=stats.residual_max,
        seconds=seconds,
        step_ms={k: 1000.0 * v / max(profiled, 1) for k, v in timer.seconds.items()},
        contacts_per_step=contacts.total / max(scene.frames * scene.substeps, 1),
        contacts_max=contacts.most,
        contact_depth_max=contacts.deepest,
        dense_penetration=penetration,
        dense_penetration_relative=penetration / min(b.size for b in model.bodies),
    )


class Contacts:
    """Body-body contact statistics gathered once per frame.

    Warns once if the contact buffer overflows, and once if a body moves more than half a tet (the median tet
    size) in one step: contacts are then tested too coarsely in time and thin parts may pass through each
    other (tunnelling); more substeps fix it.
    """

    def __init__(self) -> None:
        self.total, self.most, self.deepest, self.warned, self.warned_speed = 0, 0, 0.0, False, False

    def read(self, solver: Solver, frame: int, warn: Callable[[str], None] | None, dt: float = 0.0) -> None:
        """Add the contacts of the frame just simulated (one host synchronisation); ``dt`` is the step (s)."""
        if solver.collider is None:
            return
        speeds = solver.collider.read_speeds()
        cell = solver.model.tet_size
        fastest = int(np.argmax(speeds)) if len(speeds) else 0
        if dt > 0 and not self.warned_speed and warn and speeds[fastest] * dt > 0.5 * cell:
            body = solver.model.bodies[fastest]
            warn(
                f"warning: frame {frame}: body '{body.name}' moves {speeds[fastest]:.3g} m/s, "
                f"{1e3 * speeds[fastest] * dt:.3g} mm per step, more than half a tet ({1e3 * cell:.3g} mm): thin "
                "parts may pass through each other; raise substeps"
            )
            self.warned_speed = True
        total, most, deepest, overflow = solver.collider.read_stats()
        self.total += total
        self.most = max(self.most, most)
        self.deepest = max(self.deepest, deepest)
        if overflow and not self.warned and warn:
            warn(
                f"warning: frame {frame}: {most} contacts overflowed the buffer of {solver.collider.capacity}; "
                "the excess were ignored (raise contacts_per_point)"
            )
            self.warned = True


def dense_penetration(sim: Simulation, points: list[np.ndarray]) -> float:
    """Deepest dense vertex inside another body's tet mesh in the current state (m); 0 without collisions."""
    collider = sim.solver.collider
    if collider is None:
        return 0.0
    owner = np.concatenate([np.full(len(p), i) for i, p in enumerate(points)])
    return collider.deepest(sim.states[0].x, sim.solver.rotation, np.concatenate(points), owner)
