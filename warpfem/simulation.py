"""A scene built and stepped frame by frame: :class:`Simulation`, the centre of the public API.

Preprocessing runs once per distinct mesh (cached), the model and solver are built once, and each
:meth:`Simulation.step_frame` advances one output frame (``scene.substeps`` steps; on CUDA a captured
graph replayed), then reads that frame's statistics in one host synchronisation.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import warp as wp

from warpfem.build import (
    add_prepared_body,
    held_masks,
    obstacle_names,
    placed_geometry,
    prepare_scene,
    scene_samples,
    solver_of,
    with_edge_nodes,
)
from warpfem.errors import InputError, SimulationError
from warpfem.memory import check_fits, scene_estimate
from warpfem.prep.pipeline import default_cache_dir
from warpfem.scene import Scene
from warpfem.sim.approach import DEFAULT_APPROACH_LIMIT, ApproachWatch
from warpfem.sim.cg import CAP_SLACK
from warpfem.sim.embedding import map_dense
from warpfem.sim.fem import RotationWatch
from warpfem.sim.integrate import Box, MeshCollider, collider_pose, mesh_reach
from warpfem.sim.model import Body, Model, ModelBuilder, State
from warpfem.sim.modules import STEP_MODULES, load_modules
from warpfem.sim.solver import Solver

FAST_TURN = 0.03
"""Rotation per step (rad) past which a body gains visible energy (docs/tradeoff.md): warned about once."""

FLOAT32_FLOOR = 0.25 * 2.0**-24
"""The relative residual float32 CG resolves, per unit of the largest ratio of a free vertex's diagonal block
(2-norm) to its mass: a quarter of float32's unit roundoff, the middle of what float64 residuals of stiff
bodies' solves measured (docs/decisions.md, "CG's float32 floor, said")."""


@dataclass(frozen=True)
class FrameStats:
    """What the solver did over the frames of the last read (one for :meth:`Simulation.step_frame`; zero before).

    Attributes:
        cg_iterations: Mean CG iterations per step (over all its solves).
        cg_solves: Mean CG solves per step (one, plus one per rotation update or contact pass that changed it).
        cg_residual: Largest final relative CG residual of a step.
        contacts: Mean body-body contacts per step.
        contacts_max: Most contacts in one step.
        deepest_contact: Deepest contact the collision stage answered (m).
    """

    cg_iterations: float = 0.0
    cg_solves: float = 0.0
    cg_residual: float = 0.0
    contacts: float = 0.0
    contacts_max: int = 0
    deepest_contact: float = 0.0


@dataclass(frozen=True, eq=False)
class Posed:
    """A rigid shape of a scene (an obstacle or a handle's box) at one time: its rest mesh and where it is.

    Attributes:
        name: Its name (the scene's ``name`` key, else ``obstacle<i>`` / ``handle<i>``).
        kind: ``"sphere"``, ``"box"``, ``"mesh"`` (obstacles) or ``"handle"`` (a handle's box).
        vertices: (n, 3) float64 vertices in its own frame (m): a mesh's file vertices scaled, a sphere's or box's
            triangulated surface about its centre, a handle box's corners at rest in the world.
        faces: (m, 3) int32 triangles, wound outward.
        matrix: 4x4 float64 taking its own frame to the world at that time, for column vectors
            (``world = matrix @ [x, 1]``; USD's row-vector ``GfMatrix4d`` is its transpose).
        shape: A sphere's ``radius`` or a box's ``half_extents`` (m); a mesh's ``closed`` and ``reach`` (how far
            behind its faces it acts, m: its whole inside where closed); empty for handles.
    """

    name: str
    kind: str
    vertices: np.ndarray
    faces: np.ndarray
    matrix: np.ndarray
    shape: dict


@dataclass
class RunTotals:
    """Statistics over every frame stepped so far.

    Attributes:
        steps: Steps taken.
        refined_frames: Frames run at more substeps (1.25, 1.5 or 2 times), their bodies closing fast on each other.
        cg_solves: CG solves (one per step).
        cg_iterations: CG iterations over all solves.
        cg_residual_max: Largest final relative CG residual.
        cg_capped_frames: Frames in which CG stopped at its iteration cap above its tolerance.
        cg_short_solves: Solves that stopped at the cap above the tolerance.
        cg_float32_floor: The relative residual float32 resolves in these systems, estimated once from the
            first frame's diagonal blocks (:data:`FLOAT32_FLOOR`); a smaller residual CG reports is its own
            recurrence's, not the system's.
        contacts: Contacts summed over steps.
        contacts_max: Most contacts in one step.
        deepest_contact: Deepest contact (m).
    """

    steps: int = 0
    refined_frames: int = 0
    cg_solves: int = 0
    cg_iterations: int = 0
    cg_residual_max: float = 0.0
    cg_capped_frames: int = 0
    cg_short_solves: int = 0
    cg_float32_floor: float = 0.0
    contacts: int = 0
    contacts_max: int = 0
    deepest_contact: float = 0.0


class PhaseTimer:
    """Wall time per phase (s), measured by synchronising the device at each phase boundary."""

    def __init__(self, device: wp.context.Device) -> None:
        self.device = device
        self.seconds: dict[str, float] = {}
        self.frames = 0
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
    """A scene's model, solver and states, advanced one output frame at a time.

    Args:
        scene: A validated scene (:func:`warpfem.load_scene` or :meth:`warpfem.Scene.from_dict`).
        device: ``"cpu"`` or ``"cuda:N"``; default: ``cuda:0`` when there is a GPU, else the CPU.
        cache_dir: The preprocessing cache; default: ``$WARPFEM_CACHE``, else ``~/.cache/warpfem``.
        cache: False preprocesses again and stores nothing (the CLI's ``--no-cache``).
        progress: Receives ``(object name, message)`` as each preprocessing stage starts.
        warn: Receives one-line warnings, each kind at most once (contact buffer overflow; a body moving more
            than half a tet per step; a body turning fast enough to gain energy; CG stopping at its cap or below
            what float32 resolves).
        cg_path: How CG runs (see :class:`~warpfem.sim.solver.Solver`); None: the default.
        notify: Receives one-line notices of work before the first step that takes long only once: compiling
            the kernels on a first run (before it starts, then its time).

    Raises:
        InputError: A bad mesh (naming the scene file and object), or a scene that would not fit in the
            device's memory (before anything is allocated).

    Attributes:
        scene: The scene (None for :meth:`from_model`).
        substeps: Steps per output frame; ``dt`` the step (s), ``fps`` output frames per second.
        model: The :class:`~warpfem.sim.model.Model` (what never changes).
        solver: The :class:`~warpfem.sim.solver.Solver`.
        states: Two :class:`~warpfem.sim.model.State` buffers; ``states[0]`` is the current one between frames.
        frame: Output frames stepped so far (0: the initial pose).
        stats: The last frame's :class:`FrameStats`.
        totals: :class:`RunTotals` over all frames stepped.
        seconds: Wall time (s) of ``prepare`` (preprocessing, or reading the cache), ``compile`` (loading
            every kernel module the step can use, compiled where Warp's kernel cache lacks it: a first run)
            and ``build``.
        phase_timer: Per-phase wall time of the frames stepped with ``profile=True``.
        approach: The :class:`~warpfem.sim.approach.ApproachWatch` by which a frame whose bodies close on each
            other by more than ``approach_limit`` (the scene's ``[collision]``) times the smaller one's size in a
            step runs 1.25, 1.5 or 2 times the substeps; None where bodies cannot collide or the limit is 0.
    """

    def __init__(
        self,
        scene: Scene,
        device: str | None = None,
        cache_dir: str | Path | None = None,
        cache: bool = True,
        progress: Callable[[str, str], None] | None = None,
        warn: Callable[[str], None] | None = None,
        cg_path: str | None = None,
        notify: Callable[[str], None] | None = None,
    ) -> None:
        self.scene = scene
        self.warn = warn
        check_device(device)
        dev = wp.get_device(device or ("cuda:0" if wp.is_cuda_available() else "cpu"))
        clock = time.perf_counter()
        folder = (Path(cache_dir) if cache_dir is not None else default_cache_dir()) if cache else None
        prepared = prepare_scene(scene, folder, progress)
        self.seconds = {"prepare": time.perf_counter() - clock}
        clock = time.perf_counter()
        load_modules([(dev, STEP_MODULES)], notify)  # before anything launches: the step's timing holds no compile
        self.seconds["compile"] = time.perf_counter() - clock
        clock = time.perf_counter()
        samples = scene_samples(scene, prepared, folder)
        placed = [placed_geometry(*where) for where in zip(scene.objects, prepared, samples, strict=True)]
        check_fits(scene_estimate(scene, prepared, [geometry for _, geometry in placed]), dev.alias)
        edges = [None] * len(placed)
        if scene.solver.elements == "quadratic":
            placed, edges = map(list, zip(*map(with_edge_nodes, prepared, placed), strict=True))
        held = held_masks(scene, [tet_x for tet_x, _ in placed])
        builder = ModelBuilder()
        for obj, body, where, tet_edges in zip(scene.objects, prepared, placed, edges, strict=True):
            masks = [m for h, m in zip(scene.handles, held, strict=True) if h.object == obj.name]
            add_prepared_body(builder, obj, body, where, np.any(masks, axis=0) if masks else None, tet_edges)
        model = builder.finalize(dev)
        solver = solver_of(scene, model, cg_path, held)
        self._attach(model, solver, scene.substeps, scene.fps, scene.collision.approach_limit)
        self.seconds["build"] = time.perf_counter() - clock

    @classmethod
    def from_model(
        cls,
        model: Model,
        solver: Solver,
        substeps: int = 1,
        fps: float = 60.0,
        warn: Callable[[str], None] | None = None,
        approach_limit: float = DEFAULT_APPROACH_LIMIT,
    ) -> Simulation:
        """A simulation of a model built by hand (:class:`~warpfem.sim.model.ModelBuilder`, :func:`warpfem.add_body`).

        Args:
            model: The model.
            solver: Its solver.
            substeps: Steps per output frame.
            fps: Output frames per second.
            warn: As for the constructor.
            approach_limit: See :attr:`approach` (>= 0 and < 1; 0: never).

        The step's kernel modules are loaded here (those the model's and solver's construction did not load
        already); ``seconds["compile"]`` says how long that took.

        Raises:
            ValueError: ``approach_limit`` outside [0, 1) or not a number.
        """
        if not 0.0 <= approach_limit < 1.0:
            raise ValueError(f"approach_limit must be >= 0 and < 1 (a share of a body's size), got {approach_limit}")
        sim = cls.__new__(cls)
        clock = time.perf_counter()
        load_modules([(model.device, STEP_MODULES)])
        sim.scene, sim.warn, sim.seconds = None, warn, {"compile": time.perf_counter() - clock}
        sim._attach(model, solver, substeps, fps, approach_limit)
        return sim

    def _attach(self, model: Model, solver: Solver, substeps: int, fps: float, approach_limit: float) -> None:
        """Allocate the states and buffers of ``model`` stepped by ``solver``."""
        self.model, self.solver = model, solver
        watched = approach_limit > 0 and solver.collider is not None and len(model.bodies) > 1
        self.substeps, self.fps = int(substeps), float(fps)
        self.approach = ApproachWatch(model, solver.collider, approach_limit, self.substeps) if watched else None
        self.dt = 1.0 / (self.fps * self.substeps)
        if solver.drive is not None:
            solver.drive.set_step(self.dt)
        self.states = [model.state(), model.state()]
        self.dense = wp.zeros(model.dense_count, dtype=wp.vec3, device=model.device)
        self.frame = 0
        self.stats = FrameStats()
        self.totals = RunTotals()
        self.phase_timer = PhaseTimer(model.device)
        self._graph = None
        self._rest_x: np.ndarray | None = None
        self._rotation = RotationWatch(model, solver.rotation)
        self._warned: set[str] = set()
        if solver.collider is not None:
            self._say_placed(solver.collider.mark_placed(self.states[0].x, self.states[0].v, self.dt))

    @property
    def device(self) -> wp.context.Device:
        """The Warp device the simulation runs on."""
        return self.model.device

    @property
    def time(self) -> float:
        """Simulated time (s) at the current frame."""
        return self.frame / self.fps

    @property
    def body_names(self) -> list[str]:
        """The bodies' names, in scene order."""
        return [b.name for b in self.model.bodies]

    def body(self, name: str) -> Body:
        """Where body ``name`` lives in the model's flat arrays.

        Raises:
            InputError: No body has that name (the message lists them).
        """
        for b in self.model.bodies:
            if b.name == name:
                return b
        raise InputError(f"no body named '{name}' (bodies: {', '.join(self.body_names)})")

    def obstacles_at(self, time: float | None = None) -> list[Posed]:
        """Every obstacle at ``time`` (s; default: the current :attr:`time`), in scene order (for output).

        Evaluated on the host from the obstacles' keys; a still obstacle's ``matrix`` is its rest placement.
        """
        time = self.time if time is None else float(time)
        names = obstacle_names(self.scene) if self.scene is not None else None
        return [
            Posed(names[i] if names else f"obstacle{i}", *collider_shape(c), collider_pose(c, time), collider_info(c))
            for i, c in enumerate(self.solver.obstacles)
        ]

    def handles_at(self, time: float | None = None) -> list[Posed]:
        """Every handle's box at ``time`` (s; default: the current :attr:`time`): where its held vertices are."""
        time = self.time if time is None else float(time)
        if self.solver.handles and self._rest_x is None:  # read once: later calls touch no device array
            self._rest_x = self.model.rest_x.numpy().astype(np.float64)
        out = []
        for handle in self.solver.handles:
            rest = self._rest_x[handle.vertices]
            vertices, faces = box_surface(rest.min(axis=0), rest.max(axis=0))
            out.append(Posed(handle.name, "handle", vertices, faces, handle.motion.matrix(time), {}))
        return out

    def step_frame(self, profile: bool = False) -> FrameStats:
        """Advance one output frame and read its statistics (one host synchronisation).

        Args:
            profile: Run the frame's phases directly, synchronising at each boundary, and add their wall
                times to :attr:`phase_timer` (slower; on CUDA the frame is otherwise a graph replay).

        Raises:
            SimulationError: The state became NaN/Inf (naming the frame and body).
        """
        self.advance(self.phase_timer if profile else None)
        self.frame += 1
        self.phase_timer.frames += profile
        self.check_finite()
        return self.read_stats()

    def frame_phases(self, overlap: bool = True, substeps: int | None = None) -> list[tuple[str, Callable[[], None]]]:
        """A frame's work in order: each substep's phases (see ``Solver.phases``), as (name, launcher) pairs.

        The states alternate between substeps; after an odd count the last one is copied back into
        ``states[0]`` as part of the last "solve", which ends with the dense vertices lifted out of the still
        colliders (``Solver.lift_dense``). ``overlap``: see ``Solver.phases``. ``substeps``: the frame's steps
        (None: the scene's; more where :attr:`approach` asks for them), each the frame's time over that many.
        """
        a, b = self.states
        out = []
        substeps = substeps or self.substeps
        dt = self.dt * self.substeps / substeps
        for i in range(substeps):
            src, dst = (a, b) if i % 2 == 0 else (b, a)
            out += self.solver.phases(src, dst, dt, overlap, carried=True)
        if substeps % 2 == 1:
            out.append(("solve", lambda: a.assign(b)))
        if self.solver.static_lift:
            out.append(("solve", lambda: self.solver.lift_dense(a)))
        return out

    def advance(self, timer: PhaseTimer | None = None) -> None:
        """Advance one output frame on the device, reading nothing back (``frame`` and ``stats`` unchanged).

        With a ``timer`` the frame runs directly, timing each phase; without one on CUDA, the frame is a
        captured graph (captured on the first such call).
        """
        if timer is not None or not self.device.is_cuda:
            if timer:
                timer.start()

            def run(substeps: int) -> None:
                for name, phase in self.frame_phases(overlap=timer is None, substeps=substeps):
                    phase()
                    if timer:
                        timer.lap(name)

            self._branch(run)
            return
        self.capture()
        wp.capture_launch(self._graph)

    def _branch(self, run: Callable[[int], None]) -> None:
        """``run(substeps)`` for the frame about to run: more substeps where :attr:`approach` raises its flags.

        The flags are set on the device and branched on there (conditional nodes in a captured graph): the
        first refined level where only its flag is up, the next where its flag is up too.
        """
        watch = self.approach
        if watch is None:
            run(self.substeps)
            return
        watch.decide(self.states[0], 1.0 / self.fps, self.dt)

        def level(k: int) -> Callable[[], None]:
            def refined() -> None:
                watch.count(k)
                run(watch.levels[k])

            if k + 1 == len(watch.levels):
                return refined
            return lambda: wp.capture_if(watch.flags[k + 1 : k + 2], on_true=level(k + 1), on_false=refined)

        wp.capture_if(watch.flag, on_true=level(0), on_false=lambda: run(self.substeps))

    def capture(self) -> None:
        """Capture the frame's CUDA graph now if it is not yet (nothing runs; nothing on the CPU).

        A capture forbids host synchronisation on the device from any thread, so a caller with another
        thread waiting on the device (the file writer) captures before starting it.
        """
        if self.device.is_cuda and self._graph is None:
            # every module the step uses is loaded (see STEP_MODULES): the capture need not load all of Warp's
            with wp.ScopedCapture(device=self.device, force_module_load=False) as capture:
                self._branch(lambda substeps: [phase() for _, phase in self.frame_phases(substeps=substeps)])
            self._graph = capture.graph

    def map_dense(self) -> wp.array:
        """Map every dense mesh from the current state on the device; returns the flat (V, 3) device array."""
        m = self.model
        map_dense(m.cells, self.states[0].x, m.dense_cell, m.dense_bary, self.dense)
        return self.dense

    def dense_points(self, name: str | None = None) -> np.ndarray | list[np.ndarray]:
        """The dense mesh of body ``name`` as a NumPy (V, 3) array (m, world frame); None: one per body.

        A body's copies its own points only (a loop over a large pile's bodies copies the pile once, not once
        a body); every body's at once (``None``) takes one copy of them all.
        """
        if name is None:
            flat = self.map_dense().numpy()
            return [flat[b.dense_start : b.dense_start + b.dense_count].copy() for b in self.model.bodies]
        b = self.body(name)
        return self.map_dense()[b.dense_start : b.dense_start + b.dense_count].numpy().copy()

    def tet_points(self, name: str) -> np.ndarray:
        """The tet vertices of body ``name`` as a NumPy (P, 3) array (m, world frame)."""
        b = self.body(name)
        return self.states[0].x[b.vertex_start : b.vertex_start + b.vertex_count].numpy().copy()

    def state(self) -> State:
        """The current state (positions, velocities) on the device."""
        return self.states[0]

    def check_finite(self) -> None:
        """Raise :class:`SimulationError` naming the frame and body if the state became NaN/Inf (one sync)."""
        bad = self.solver.first_bad_vertex()
        if bad is not None:
            body = self.model.body_of_vertex(bad)
            raise SimulationError(
                f"frame {self.frame}: body '{body.name}' became NaN/Inf (tet vertex {bad - body.vertex_start}); "
                "try a smaller time step (more substeps), a lower Young's modulus or more CG iterations"
            )

    def read_stats(self, frames: int = 1) -> FrameStats:
        """Read what the solver did since the last read, ``frames`` frames of :meth:`advance` (one sync).

        :meth:`step_frame` reads after every frame; a caller that advances several frames without it reads
        once after them. Updates :attr:`stats` and :attr:`totals` and gives the warnings due.
        """
        refined = self.approach.read_count() if self.approach is not None else []
        levels = self.approach.levels if self.approach is not None else ()
        substeps = self.substeps * frames + sum(
            count * (more - self.substeps) for count, more in zip(refined, levels, strict=True)
        )
        cg = self.solver.read_cg_stats()
        t = self.totals
        t.steps += substeps
        t.refined_frames += sum(refined)
        t.cg_solves += cg.solves
        t.cg_iterations += cg.iterations
        t.cg_residual_max = max(t.cg_residual_max, cg.residual_max)
        t.cg_short_solves += cg.short
        cap, tolerance = self.solver.cg.limits
        if t.steps == substeps:  # the first read: the systems' diagonal blocks are in place
            self._check_float32_floor(tolerance)
        if tolerance > 0 and cg.residual_max > tolerance * CAP_SLACK:
            t.cg_capped_frames += frames
            self._warn_once(
                "cg-cap",
                f"warning: frame {self.frame}: CG stopped at its cap of {cap} iterations with a relative residual "
                f"of {cg.residual_max:.2g}, above its tolerance {tolerance:g}: raise [solver] cg_iterations or "
                "substeps (the run's summary counts such frames)",
            )
        total, most, deepest = 0, 0, 0.0
        collider = self.solver.collider
        if collider is not None:
            self._check_speed(collider.read_speeds())
            total, most, deepest, overflow = collider.read_stats()
            if overflow:
                self._warn_once(
                    "overflow",
                    f"warning: frame {self.frame}: {most} contacts overflowed the buffer of {collider.capacity}; "
                    "the excess were ignored (raise contacts_per_point)",
                )
            t.contacts += total
            t.contacts_max = max(t.contacts_max, most)
            t.deepest_contact = max(t.deepest_contact, deepest)
        per_step = self._rotation.turned() / substeps
        if self.frame > 1 and per_step.max() > FAST_TURN:
            body = self.model.bodies[int(np.argmax(per_step))]
            self._warn_once(
                "spin",
                f"warning: frame {self.frame}: body '{body.name}' turns {per_step.max():.3g} rad per step (over "
                f"{FAST_TURN}): {self._turn_effect(per_step.max())}; raise substeps",
            )
        self.stats = FrameStats(
            cg_iterations=cg.iterations / substeps,
            cg_solves=cg.solves / substeps,
            cg_residual=cg.residual_max,
            contacts=total / substeps,
            contacts_max=most,
            deepest_contact=deepest,
        )
        return self.stats

    def _check_float32_floor(self, tolerance: float) -> None:
        """Estimate the residual float32 resolves from the last solve's diagonal blocks; warn once above the tolerance.

        A body stiff for its step (its diagonal blocks many times its masses) leaves CG's recurrence below the
        tolerance while the system's residual stays above it: the residual CG reports then understates.
        """
        model = self.model
        blocks = self.solver.matrix.numpy()[model.diag_slot.numpy()]
        ratio = diagonal_to_mass(blocks, model.mass.numpy(), model.free.numpy() != 0)
        vertex = int(np.argmax(ratio))
        floor = FLOAT32_FLOOR * float(ratio[vertex])
        self.totals.cg_float32_floor = floor
        if 0.0 < tolerance < floor:
            self._warn_once(
                "float32",
                f"warning: body '{model.body_of_vertex(vertex).name}': float32 resolves CG's relative residual only "
                f"to about {floor:.1g} here, above its tolerance {tolerance:g} (the body is stiff for this step: "
                f"its stiffest vertex's diagonal is {ratio[vertex]:.2g} times its mass), so the residual CG reports "
                "understates the system's: raise substeps or lower young for the tolerance to hold",
            )

    def _check_speed(self, speeds: np.ndarray) -> None:
        """Warn once if a body moves more than half a tet in one step: thin parts may then tunnel."""
        if not len(speeds):
            return
        fastest = int(np.argmax(speeds))
        cell, dt = self.model.tet_size, self.dt
        if speeds[fastest] * dt > 0.5 * cell:
            body = self.model.bodies[fastest]
            self._warn_once(
                "speed",
                f"warning: frame {self.frame}: body '{body.name}' moves {speeds[fastest]:.3g} m/s, "
                f"{1e3 * speeds[fastest] * dt:.3g} mm per step, more than half a tet ({1e3 * cell:.3g} mm): thin "
                "parts may pass through each other; raise substeps",
            )

    def _turn_effect(self, per_step: float) -> str:
        """What turning ``per_step`` rad per step does to a body's energy, in words."""
        if self.solver.rotation_updates == 0:
            return "one linear solve per step adds energy this fast"
        # implicit Euler keeps about 1 / (1 + (omega dt)^2) of a spin's energy per step
        lost = 1.0 - (1.0 + per_step**2) ** -(self.fps * self.substeps)
        return f"implicit Euler takes about {100 * lost:.0f} % of a spin's energy per second this fast"

    def _say_placed(self, marked: np.ndarray) -> None:
        """Warn where bodies start inside one another.

        ``marked``: per collision point, as :meth:`~warpfem.sim.collision.Collider.mark_placed` returns it.
        """
        if marked.any():
            bodies = np.unique(self.model.point_body.numpy()[marked])
            names = ", ".join(f"'{self.model.bodies[b].name}'" for b in bodies)
            self._warn_once(
                "placed",
                f"warning: {names} start inside other bodies: their contacts push them apart, without friction "
                "until they are out",
            )

    def _warn_once(self, kind: str, message: str) -> None:
        if self.warn is not None and kind not in self._warned:
            self._warned.add(kind)
            self.warn(message)


def diagonal_to_mass(blocks: np.ndarray, mass: np.ndarray, free: np.ndarray) -> np.ndarray:
    """Each vertex's diagonal block (2-norm, blocks (n, 3, 3)) over its mass (kg); 0 where held or massless.

    Its largest value sets float32's floor of a solve (:data:`FLOAT32_FLOOR`).
    """
    mass = np.asarray(mass, np.float64)
    ratio = np.zeros(len(mass))
    live = np.asarray(free, bool) & (mass > 0.0)
    ratio[live] = np.linalg.norm(np.asarray(blocks, np.float64)[live], ord=2, axis=(1, 2)) / mass[live]
    return ratio


def box_surface(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The 8 corners and 12 outward triangles of the box ``[lo, hi]``."""
    corners = np.array([[(lo, hi)[(k >> a) & 1][a] for a in range(3)] for k in range(8)], np.float64)
    faces = [(0, 2, 3), (0, 3, 1), (4, 5, 7), (4, 7, 6), (0, 1, 5), (0, 5, 4)]
    faces += [(2, 6, 7), (2, 7, 3), (0, 4, 6), (0, 6, 2), (1, 3, 7), (1, 7, 5)]
    return corners, np.asarray(faces, np.int32)


def collider_shape(c) -> tuple[str, np.ndarray, np.ndarray]:
    """An obstacle's kind and its surface in its own frame (a sphere's as an icosphere of 320 triangles)."""
    if isinstance(c, MeshCollider):
        return "mesh", np.asarray(c.vertices, np.float64), np.asarray(c.faces, np.int32)
    if isinstance(c, Box):
        return ("box", *box_surface(-np.asarray(c.half_extents), np.asarray(c.half_extents)))
    import trimesh

    ball = trimesh.creation.icosphere(subdivisions=2, radius=c.radius)
    return "sphere", np.asarray(ball.vertices, np.float64), np.asarray(ball.faces, np.int32)


def collider_info(c) -> dict:
    """A sphere's radius, a box's half extents, or whether a mesh is closed."""
    if isinstance(c, MeshCollider):
        return {"closed": c.closed, "reach": mesh_reach(c)}
    if isinstance(c, Box):
        return {"half_extents": tuple(c.half_extents)}
    return {"radius": c.radius}


def check_device(name: str | None, option: str = "device") -> None:
    """Raise :class:`InputError` naming ``option`` if ``name`` is not a Warp device here (None: the default)."""
    if name is None:
        return
    try:
        wp.get_device(name)
    except (ValueError, RuntimeError):
        available = ", ".join(d.alias for d in wp.get_devices())
        raise InputError(f"{option} {name}: no such device (available: {available})") from None
