"""The solver: one implicit-Euler corotational FEM step, ``step(state_in, state_out, dt)``.

Everything is allocated in the constructor; a step launches kernels only (no allocation, no host
synchronisation on CUDA), so a frame of steps can be captured as a CUDA graph and replayed. Tunable
scalars (gravity, collider and contact parameters, CG limits) live in device arrays and can change between
replays.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
import warp as wp

from warpfem.sim import fem, integrate, skin
from warpfem.sim.cg import CGSolver, CGStats
from warpfem.sim.collision import DEFAULT_COLLISION, Collider, CollisionSettings
from warpfem.sim.deflation import RigidDeflation
from warpfem.sim.drive import Drive, Handle
from warpfem.sim.integrate import Box, Ground, MeshCollider, Sphere, StaticColliders
from warpfem.sim.model import Model, State
from warpfem.sim.rigid import RigidCorrection

DEFAULT_GROUND = Ground()

DEFAULT_CONTACT_PASSES = 2
"""Late-contact passes per step unless told (see :class:`Solver`); chosen by measurement (docs/decisions.md)."""

LATE_BODY_PASSES = 1
"""Of those, how many look for late contacts between bodies too (each a detection at the predicted positions,
the cost of the step's own); the others look at the static colliders only (docs/decisions.md)."""

DEFAULT_ROTATION_UPDATES = 2
"""Re-linearisations about the step's end rotations per step unless told (see :class:`Solver`)."""

DEFAULT_ROTATION_TOLERANCE = 0.01
"""A tet is re-linearised when its rotation at the step's end differs from the one solved with by more than
this (rad) unless told (see :class:`Solver`)."""

_NO_BAD_VERTEX = np.iinfo(np.int32).max


class Solver:
    """Corotational linear FEM with backward Euler, solved by block-Jacobi PCG.

    Args:
        model: The scene's model.
        gravity: Gravity (m/s^2).
        ground: The ground plane, or None for none.
        obstacles: Spheres, boxes and meshes, each still or moving rigidly (its ``motion``).
        cg_iterations: Fixed iteration count (``cg_tolerance == 0``) or cap.
        cg_tolerance: Relative residual at which CG stops; 0 runs exactly ``cg_iterations``.
        collision: Body-body and self collision settings, or None for none. A model whose bodies cannot
            touch (one body without self-collision) gets no collision stage at all.
        contact_passes: After a solve, how many times to look for contacts its new velocities cross that
            the step did not count (a point sped up within the step, or dragged by its body), add them and
            solve again from that answer (a solve only where some were found, of the bodies they touched and
            those touching another body: a body on its own that none touched keeps its answer, as it would
            alone); 0: none. The first :data:`LATE_BODY_PASSES` look between bodies too, the others at the
            static colliders. A pass runs only after the one before it solved (the first: always); each costs a
            look at every collision point and, where contacts were added, a warm-started solve.
        cg_path: How CG runs (:data:`warpfem.sim.cg.MODES`): "grid" (one persistent launch per solve) or
            "launches" (two launches per iteration), optionally "grid:B" for B blocks; None: the default
            (:data:`warpfem.sim.cg.DEFAULT_MODE`).
        rotation_updates: After the first solve, how many times at most to re-linearise the tets that turned
            more than ``rotation_tolerance`` (rad) within the step about their rotation at its end and solve
            again from that answer, in the bodies whose tets turned that much on average (the volume average of
            the turn to the fourth power) or one of whose tets turned twice that
            (:class:`~warpfem.sim.fem.TurnCheck`); a solve only where some body did; 0: never. One linear solve
            moves each vertex along the tangent of its rotation, which stretches a fast-turning body and adds
            energy; these updates converge to implicit Euler with the elastic force at the step's end, which
            does not.
            Once a solve stops short of its tolerance, the updates pause until CG's statistics are next read
            (:meth:`read_cg_stats`; a ``Simulation`` reads them after every frame): rotations read off an
            unconverged answer steer the next solve wrong. A loop that never reads them runs without updates
            after its first short solve. Either count may be lowered after construction, not raised.
        rotation_tolerance: See ``rotation_updates`` (rad, >= 0).
        handles: Pinned vertices that follow rigid motions (:class:`~warpfem.sim.drive.Handle`). With handles
            or moving obstacles, each step poses them from a device clock (``drive``: one launch to pose, one
            to advance the clock); without, ``drive`` is None and a step launches nothing for them.
        static_lift: Whether a step ends by moving the tet nodes so that no skin point (the visible surface's
            samples) lies below the surface of a still collider (the ground, obstacles without a motion),
            stopping them along that move (two launches a step, three with a still mesh collider;
            :func:`warpfem.sim.integrate.lift_points`);
            :meth:`lift_dense` does the same for every dense vertex. A penalty yields by what it needs to
            hold a load or stop a landing; the lift keeps that give out of sight. Off: the penalties alone.
            May be turned off after construction.
    """

    def __init__(
        self,
        model: Model,
        gravity: tuple[float, float, float] = (0.0, -9.81, 0.0),
        ground: Ground | None = DEFAULT_GROUND,
        obstacles: Sequence[Sphere | Box | MeshCollider] = (),
        cg_iterations: int = 400,
        cg_tolerance: float = 1.0e-4,
        collision: CollisionSettings | None = DEFAULT_COLLISION,
        cg_path: str | None = None,
        contact_passes: int = DEFAULT_CONTACT_PASSES,
        handles: Sequence[Handle] = (),
        rotation_updates: int = DEFAULT_ROTATION_UPDATES,
        rotation_tolerance: float = DEFAULT_ROTATION_TOLERANCE,
        static_lift: bool = True,
    ) -> None:
        _check_counts(contact_passes, rotation_updates, rotation_tolerance)
        self._rotation_updates, self.rotation_tolerance = rotation_updates, float(rotation_tolerance)
        self.model = model
        dev = model.device
        n = model.vertex_count
        self.force = wp.zeros(n, dtype=wp.vec3, device=dev)
        self.rhs = wp.zeros(n, dtype=wp.vec3, device=dev)
        self.direction = wp.zeros(n, dtype=wp.vec3, device=dev)
        self.diag_inv = wp.zeros(n, dtype=wp.mat33, device=dev)
        self.matrix = wp.zeros(model.nnz_blocks, dtype=wp.mat33, device=dev)
        self.rotation = wp.zeros(model.tet_count, dtype=wp.mat33, device=dev)
        self.gravity = wp.zeros(1, dtype=wp.vec3, device=dev)
        bodies = len(model.bodies)
        self._per_body = wp.zeros(bodies * (1 + rotation_updates), dtype=wp.vec3, device=dev)
        """What a step sums per body, in one array that the step's clear zeroes: momentum, then the turns."""
        self.momentum = self._per_body[:bodies]
        """Each body's momentum at the start of the step (the speculative static contacts' body speed)."""
        self._body_turn = [self._per_body[bodies * k : bodies * (k + 1)] for k in range(1, rotation_updates + 1)]
        """Per rotation update, how far each body's tets turned (:class:`~warpfem.sim.fem.TurnCheck`)."""
        self._turn_check = fem.TurnCheck(model, rotation_updates > 0)
        self.colliders = StaticColliders(
            [*([ground] if ground is not None else []), *obstacles], dev, model.body_size, self.gravity
        )
        still = static_lift and self.colliders.kind.shape[0] > len(self.colliders.moving)
        self.static_lift = still and model.skin_cell.shape[0] > 0
        """Whether a step ends with the skin lifted out of the still colliders (see ``static_lift`` above)."""
        self._lift = tuple(wp.zeros(n if self.static_lift else 0, dtype=wp.vec3, device=dev) for _ in range(2))
        """Per tet node, the moves the embedded points ask of it (``integrate.lift_points``)."""
        self.obstacles = list(obstacles)
        self.handles = list(handles)
        moving = self.colliders.moving
        self.drive = Drive(model, handles, moving, self.colliders.poses) if handles or moving else None
        self._no_vec3 = wp.zeros(0, dtype=wp.vec3, device=dev)  # an absent vector argument, allocated once
        self._no_mat33 = wp.zeros(0, dtype=wp.mat33, device=dev)
        self._no_int = wp.zeros(0, dtype=wp.int32, device=dev)
        self.held_v = self.drive.held_v if self.drive is not None else self._no_vec3
        self.bad_vertex = wp.array([_NO_BAD_VERTEX], dtype=wp.int32, device=dev)
        self.collider = Collider(model, collision) if collision is not None and model.has_collisions else None
        static = self.colliders.kind.shape[0] > 0
        self._contact_passes = contact_passes if static or self.collider is not None else 0
        self._allocate_apart(rotation_updates > 0)
        self._allocate_flags(rotation_updates, static)
        # the stream the collision stage's preparation runs on alongside the elastic launch (see phases)
        self._side = wp.Stream(dev) if dev.is_cuda and self.collider is not None else None
        # the rotated distance gradients the contacts read, summed by the elastic launch (none without contacts)
        self.grad = self.collider.grad if self.collider is not None else self._no_vec3
        self._list_cleared()
        self.cg = _cg_solver(model, cg_iterations, cg_tolerance, cg_path, self.collider)
        self.set_gravity(gravity)

    def _allocate_apart(self, apart: bool) -> None:
        """The system's elastic part apart from the rest, where rotation updates re-assemble it each update.

        A step re-linearised about new rotations is assembled afresh (differences of stiff blocks lose the mass
        term in float32); without updates the elastic launch adds straight into the system.
        """
        model, dev, n = self.model, self.model.device, self.model.vertex_count
        self.apart = apart
        self.elastic_force = wp.zeros(n, dtype=wp.vec3, device=dev) if apart else self.force
        self.elastic_matrix = wp.zeros(model.nnz_blocks, dtype=wp.mat33, device=dev) if apart else self.matrix
        self.matrix_base = wp.zeros(model.nnz_blocks, dtype=wp.mat33, device=dev) if apart else self.matrix
        self.rhs_base = wp.zeros(n, dtype=wp.vec3, device=dev) if apart else self._no_vec3
        self.rigid = RigidCorrection(model, self.rhs_base, self.matrix_base) if apart else None
        """Momentum of bodies no other body touches, kept exact where float32 loses it (with ``apart`` only)."""
        self.deflation = RigidDeflation(model, self.rigid) if apart else None
        """Bodies whose rigid motions CG leaves to the rigid correction (with ``apart`` only)."""

    def _allocate_flags(self, rotation_updates: int, static: bool) -> None:
        """The step's conditions (rotation updates, late-contact passes) and the late static contacts' marks."""
        dev, n = self.model.device, self.model.vertex_count
        updates, passes, bodies = rotation_updates, self._contact_passes, len(self.model.bodies)
        marks = (updates + (1 if passes else 0)) * bodies
        self.flags = wp.zeros(updates + passes + marks + 1 + passes, dtype=wp.int32, device=dev)
        """The step's conditions and per-body marks, each its own slots so one launch clears them all at the step's
        start."""
        self.turned = [self.flags[k : k + 1] for k in range(updates)]
        """Whether the k-th rotation update changed some tet (the condition of its solve)."""
        self.late_count = [self.flags[k : k + 1] for k in range(updates, updates + passes)]
        """Late contacts the k-th pass added (the condition of its solve)."""
        first = updates + passes
        self.turn_body = [self.flags[first + k * bodies : first + (k + 1) * bodies] for k in range(updates)]
        """Per rotation update and body, whether its solve moves the body (it turned, or it touches another)."""
        first += updates * bodies
        self.late_body = self.flags[first : first + bodies] if passes else self._no_int
        """Per body, whether a late solve moves it (a late contact touched it, or it touches another body)."""
        first += bodies if passes else 0
        points = self.model.skin_cell.shape[0] if static else 0
        listing = wp.zeros(points, dtype=wp.int32, device=dev)
        self.skin_list = [(self.flags[first + k : first + k + 1], listing) for k in range(1 + passes)]
        """How many skin points the step's static contacts read and which: at its start, then per late pass
        (:mod:`warpfem.sim.skin`; one list, filled afresh by each)."""
        self.late = (
            wp.zeros(n if static else 0, dtype=wp.int32, device=dev),
            wp.zeros(points, dtype=wp.int32, device=dev),
        )
        """Which tet vertices and skin points got a late static contact this step."""
        self.skin_clear = wp.zeros(points if passes else 0, dtype=float, device=dev)
        """Per skin point, how far its cell's nodes may move in the step without carrying it to a static collider
        (what lets a late pass leave it out: ``kernels.skin.skin_colliders``)."""
        self.body_speed = wp.zeros(bodies if points and passes else 0, dtype=float, device=dev)
        """Per body, its fastest vertex in the step's answers so far (the late passes' reach)."""

    def _list_cleared(self) -> None:
        """List what a step zeroes before it accumulates and counts, in one launch.

        In ``kernels.integrate.clear_step``'s order; the matrix itself is the base when nothing is apart. The
        elastic arrays kept apart are zeroed as the system reads them (``integrate.add_elastic``).
        """
        collider = self.collider
        self._cleared = [
            self.force,
            self.grad,
            self._per_body,
            self.matrix_base,
            collider.point_contact if collider is not None else self._no_int,
            *self.late,
            collider.counts if collider is not None else self._no_int,
            self.flags,
            self.body_speed,
        ]
        self._cleared_dim = max(a.shape[0] for a in self._cleared)

    def set_gravity(self, gravity: tuple[float, float, float]) -> None:
        """Set gravity (m/s^2); takes effect in captured graphs too."""
        self.gravity.assign(np.array([gravity], dtype=np.float32))

    def phases(
        self, state_in: State, state_out: State, dt: float, overlap: bool = True, carried: bool = False
    ) -> list[tuple[str, Callable[[], None]]]:
        """The step's phases in order, each a callable launching its kernels: elastic, [collision,] solve.

        ``carried``: the collision stage looks again only at the step before's contacts where the collider
        carries them (``Collider.respond``; the step's late look then finds the pairs it lacks), else at every
        point.

        With ``overlap`` on CUDA, the collision stage's preparation (``Collider.prepare``: collision points,
        tet inverses, trees, none of which the elastic launch touches) runs on a side stream alongside the
        elastic launch, forked in "elastic" and joined in "collision" (in a captured graph, two branches);
        without it, in order (what a timer that synchronises at each phase boundary needs).
        """
        model = self.model
        side = self._side if overlap else None  # None without collisions, or off CUDA

        def elastic() -> None:
            if side is not None:
                side.wait_stream(wp.get_stream(model.device))
                with wp.ScopedStream(side, sync_enter=False):
                    self.collider.prepare(state_in.x, state_in.v)
            if self.collider is not None:
                self.collider.release_placed()
            integrate.clear_step(self._cleared, self._cleared_dim, model.device)
            fem.elastic_forces_and_stiffness(
                model, state_in.x, dt, self.rotation, self.elastic_force, self.elastic_matrix, self.grad,
                v=state_in.v if self.apart else None,
                predict_least=self.rotation_tolerance,
            )  # fmt: skip

        def collision() -> None:
            if side is not None:
                wp.get_stream(model.device).wait_stream(side)
            else:
                self.collider.prepare(state_in.x, state_in.v)
            self.collider.respond(
                state_in.x, state_in.v, dt, self.force, self.matrix_base, cleared=True, carried=carried
            )

        def solve() -> None:
            if self.drive is not None:
                self.drive.pose(state_in.x, dt)
            self._assemble(state_in, state_out, dt)
            deflation = self._deflated(state_in, dt)
            self.cg.solve(self.matrix, self.diag_inv, self.rhs, state_out.v, self.direction, model.mass, deflation)
            self._finish(state_in, state_out, dt)
            if self.rotation_updates:
                self._update_rotations(state_in, state_out, dt, 1)
            self._late_passes(state_in, state_out, dt)
            if self.collider is not None:
                self.collider.keep()
            if self.static_lift:
                integrate.lift_points(model, state_out, self.colliders, model.skin_cell, model.skin_bary, *self._lift)
            if self.drive is not None:
                self.drive.tick(dt)

        if self.collider is None:
            return [("elastic", elastic), ("solve", solve)]
        return [("elastic", elastic), ("collision", collision), ("solve", solve)]

    def _assemble(self, state_in: State, state_out: State, dt: float) -> None:
        """Static contacts and the implicit Euler system on top of the elastic and contact terms."""
        model = self.model
        if self.colliders.kind.shape[0]:  # only the static contacts read the bodies' speed
            integrate.body_momentum(model, state_in, self.momentum)
        skin.skin_colliders(
            model,
            state_in,
            self.colliders,
            self.momentum,
            dt,
            self.force,
            self.matrix_base,
            self.skin_clear,
            self.skin_list[0],
        )
        apart = self.apart
        integrate.build_system(
            model,
            state_in,
            self.force,
            self.gravity,
            self.colliders,
            dt,
            self.matrix_base,
            self.rhs,
            self.diag_inv,
            state_out.v,
            self.direction,
            self.momentum,
            self.held_v,
            self.elastic_force if apart else self._no_vec3,
            self.rhs_base,
        )
        if apart:
            self._add_elastic(dt)

    def _add_elastic(self, dt: float, moving: wp.array | None = None) -> None:
        """The system from its bases; ``moving``: per body, the bodies the next solve moves (None: all)."""
        integrate.add_elastic(
            self.model, self.matrix_base, self.elastic_matrix, self.rhs_base, self.elastic_force, dt, self.matrix,
            self.rhs, self.diag_inv, self._no_int if moving is None else moving,
        )  # fmt: skip

    def _deflated(self, state_in: State, dt: float) -> RigidDeflation | None:
        """The deflation bound to this step where some body is stiffer than float32 resolves, else None."""
        if self.deflation is None or not self.deflation.needed(dt):
            return None
        self.deflation.bind(state_in.x, self.matrix_base, dt)
        return self.deflation

    def _finish(self, state_in: State, state_out: State, dt: float) -> None:
        """After a solve: the rigid correction where needed, then the positions.

        (:class:`~warpfem.sim.rigid.RigidCorrection`.)
        """
        if self.rigid is not None and self.rigid.needed(dt):
            coupling = self.collider.coupling if self.collider is not None else None
            self.rigid.apply(state_in.x, state_in.v, state_out.v, dt, coupling)
        self._advance(state_in, state_out, dt)

    def _advance(self, state_in: State, state_out: State, dt: float) -> None:
        integrate.advance_positions(
            self.model, state_in.x, state_in.v, state_out.v, dt, state_out.x, state_out.dv, self.bad_vertex
        )

    def _update_rotations(self, state_in: State, state_out: State, dt: float, k: int) -> None:
        """The k-th look at the tets' rotations; a solve, and the next look, only where some turned."""
        turned = self.turned[k - 1]
        self._turn_check.look(
            state_out.x, self.rotation_tolerance, self.cg, self.rotation, self._body_turn[k - 1], turned,
            self.turn_body[k - 1],
        )  # fmt: skip
        wp.capture_if(turned, on_true=lambda: self._relinearise(state_in, state_out, dt, k))

    def _relinearise(self, state_in: State, state_out: State, dt: float, k: int) -> None:
        """The system again about the rotations ``rotation`` holds, solved from the last answer.

        The solve moves the bodies that were re-linearised and those touching another body; a body on its own
        that did not turn enough keeps its answer, as it would alone.
        """
        fem.elastic_forces_and_stiffness(
            self.model, state_in.x, dt, self.rotation, self.elastic_force, self.elastic_matrix, self._no_vec3,
            given_rotation=True,
        )  # fmt: skip
        moving = self.turn_body[k - 1]
        integrate.moving_bodies(self.model, (self._no_int, self._no_int), self.cg.pairs, moving)
        self._add_elastic(dt, moving)
        self.cg.solve(self.matrix, self.diag_inv, self.rhs, state_out.v, deflation=self._deflated(state_in, dt))
        self._finish(state_in, state_out, dt)
        if k < self.rotation_updates:
            self._update_rotations(state_in, state_out, dt, k + 1)

    def _late_passes(self, state_in: State, state_out: State, dt: float, k: int = 0) -> None:
        """The k-th contact pass: contacts the answer makes that the step did not count, and a solve where any asks.

        Every static contact found asks; one between bodies where it ends the step deeper than half the contact
        offset (``Collider.solve_depth``). The next pass runs only after such a solve: an answer a pass found
        nothing in would show the next pass nothing either.
        """
        if k >= self.contact_passes:
            return
        base = self.rigid is not None and self.rigid.needed(dt)  # the rigid correction reads the late contacts
        count = self.late_count[k]
        if self.colliders.kind.shape[0]:
            static = [self.model, state_in, state_out.v, self.colliders, self.momentum, dt]
            system = [count, self.matrix, self.rhs, self.matrix_base if base else self._no_mat33,
                      self.rhs_base if base else self._no_vec3]  # fmt: skip
            integrate.late_contacts(*static, self.late[0], *system, self.body_speed)
            skin.late_contacts(*static, self.late[1], *system, self.skin_clear, self.body_speed, self.skin_list[1 + k])
        if self.collider is not None and k < LATE_BODY_PASSES:
            bases = (self.rhs_base, self.matrix_base) if base else None
            self.collider.respond_late(state_out.x, state_out.v, dt, self.rhs, self.matrix, count, bases)
        wp.capture_if(count, on_true=lambda: self._solve_again(state_in, state_out, dt, k))

    def _solve_again(self, state_in: State, state_out: State, dt: float, k: int) -> None:
        """Solve again for the bodies the k-th pass's contacts touched, then run the next pass.

        The other bodies keep their answer as it is. Without deflation: where it is needed, the rigid correction
        is too, so the late contacts enter the system without elasticity and mark their bodies as touching,
        which deflation leaves alone anyway.
        """
        integrate.moving_bodies(self.model, self.late, self.cg.pairs, self.late_body)
        integrate.refresh_preconditioner(self.model, self.matrix, self.diag_inv, self.late_body)
        self.cg.solve(self.matrix, self.diag_inv, self.rhs, state_out.v)
        self._finish(state_in, state_out, dt)
        self._late_passes(state_in, state_out, dt, k + 1)

    def lift_dense(self, state: State) -> None:
        """Lift every dense vertex of ``state`` out of the still colliders as a step lifts the skin points.

        Between skin points a deformed tet can carry a dense vertex a little lower than its neighbours; a
        frame's last state goes through this so that what is written never shows below the ground or inside
        a still obstacle by more than ``kernels.integrate.LIFT_GIVE`` of its body's size. Nothing without
        ``static_lift``.
        """
        if self.static_lift:
            m = self.model
            integrate.lift_points(m, state, self.colliders, m.dense_cell, m.dense_bary, *self._lift)

    @property
    def rotation_updates(self) -> int:
        """Rotation updates per step (see :class:`Solver`); may be lowered after construction."""
        return self._rotation_updates

    @rotation_updates.setter
    def rotation_updates(self, value: int) -> None:
        self._rotation_updates = _lowered("rotation_updates", value, len(self.turned))

    @property
    def contact_passes(self) -> int:
        """Late-contact passes per step (see :class:`Solver`); may be lowered after construction."""
        return self._contact_passes

    @contact_passes.setter
    def contact_passes(self, value: int) -> None:
        self._contact_passes = _lowered("contact_passes", value, len(self.late_count))

    @property
    def overlapped(self) -> bool:
        """Whether a step runs the collision stage's preparation beside the elastic launch (see ``phases``)."""
        return self._side is not None

    def step(self, state_in: State, state_out: State, dt: float) -> None:
        """Advance ``state_in`` by ``dt`` seconds into ``state_out`` (distinct states).

        (A timed run laps each phase through ``phases``: see ``warpfem.simulation.Simulation.frame_phases``.)
        """
        for _, phase in self.phases(state_in, state_out, dt):
            phase()

    def first_bad_vertex(self) -> int | None:
        """The lowest tet vertex that became NaN/Inf since the last call, or None (one host synchronisation)."""
        bad = int(self.bad_vertex.numpy()[0])
        if bad == _NO_BAD_VERTEX:
            return None
        self.bad_vertex.fill_(_NO_BAD_VERTEX)
        return bad

    def read_cg_stats(self) -> CGStats:
        """CG statistics since the last call (one host synchronisation)."""
        return self.cg.read_stats()


def _lowered(name: str, value: int, allocated: int) -> int:
    """``value`` if a count set after construction is within what the solver allocated for, else ValueError."""
    if not 0 <= value <= allocated:
        raise ValueError(f"{name} can be lowered after construction, to 0-{allocated}, not set to {value}")
    return value


def _check_counts(contact_passes: int, rotation_updates: int, rotation_tolerance: float) -> None:
    """Raise ValueError for a negative pass or update count or rotation tolerance."""
    if contact_passes < 0:
        raise ValueError(f"contact_passes must be >= 0, got {contact_passes}")
    if rotation_updates < 0:
        raise ValueError(f"rotation_updates must be >= 0, got {rotation_updates}")
    if not rotation_tolerance >= 0.0:
        raise ValueError(f"rotation_tolerance must be >= 0 rad, got {rotation_tolerance}")


def _cg_solver(
    model: Model, iterations: int, tolerance: float, cg_path: str | None, collider: Collider | None
) -> CGSolver:
    """The step's CG solver on ``model``'s pattern, run as ``cg_path`` says (see :class:`Solver`)."""
    mode, _, blocks = (cg_path or "").partition(":")
    if blocks and (mode != "grid" or not blocks.isdigit()):
        raise ValueError(f"cg_path must be 'grid', 'grid:B' (B blocks), 'launches' or None, got {cg_path!r}")
    cg = CGSolver(
        model.row_start,
        model.cols,
        model.free,
        iterations,
        model.device,
        coupling=collider.coupling if collider is not None else None,
        mode=mode or None,
        grid_blocks=int(blocks) if blocks else None,
    )
    cg.configure(iterations, tolerance)
    return cg
