"""The solver: one implicit-Euler corotational FEM step, ``step(state_in, state_out, dt)``.

Everything is allocated in the constructor; a step launches kernels only (no allocation, no host
synchronisation on CUDA), so a frame of steps can be captured as a CUDA graph and replayed. Tunable
scalars (gravity, ground, CG limits) live in device arrays and can change between replays.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from warpfem import fem, integrate
from warpfem.cg import CGSolver, CGStats
from warpfem.kernels import integrate as IK
from warpfem.model import Model, State

_NO_BAD_VERTEX = np.iinfo(np.int32).max


@dataclass(frozen=True)
class Ground:
    """A ground plane answered with an implicit penalty and implicit Coulomb-like friction.

    Attributes:
        height: Plane offset along ``up`` (m).
        stiffness: Penalty stiffness per unit vertex mass (1/s^2); resting penetration is about g / stiffness.
        friction: Coulomb friction coefficient.
        up: Unit normal of the plane, pointing into the free half-space.
    """

    height: float = 0.0
    stiffness: float = 1.0e6
    friction: float = 0.5
    up: tuple[float, float, float] = (0.0, 1.0, 0.0)


class Solver:
    """Corotational linear FEM with backward Euler, solved by block-Jacobi PCG.

    Args:
        model: The scene's model.
        gravity: Gravity (m/s^2).
        ground: The ground plane, or None for none.
        cg_iterations: Fixed iteration count (``cg_tolerance == 0``) or cap.
        cg_tolerance: Relative residual at which CG stops; 0 runs exactly ``cg_iterations``.
    """

    def __init__(
        self,
        model: Model,
        gravity: tuple[float, float, float] = (0.0, -9.81, 0.0),
        ground: Ground | None = Ground(),
        cg_iterations: int = 100,
        cg_tolerance: float = 1.0e-4,
    ) -> None:
        self.model = model
        dev = model.device
        n = model.vertex_count
        self.force = wp.zeros(n, dtype=wp.vec3, device=dev)
        self.rhs = wp.zeros(n, dtype=wp.vec3, device=dev)
        self.diag_inv = wp.zeros(n, dtype=wp.mat33, device=dev)
        self.matrix = wp.zeros(model.nnz_blocks, dtype=wp.mat33, device=dev)
        self.rotation = wp.zeros(model.tet_count, dtype=wp.mat33, device=dev)
        self.gravity = wp.zeros(1, dtype=wp.vec3, device=dev)
        self.up = wp.zeros(1, dtype=wp.vec3, device=dev)
        self.ground = wp.zeros(4, dtype=float, device=dev)
        self.bad_vertex = wp.array([_NO_BAD_VERTEX], dtype=wp.int32, device=dev)
        self.cg = CGSolver(model.row_start, model.cols, model.free, cg_iterations, dev)
        self.cg.configure(cg_iterations, cg_tolerance)
        self.set_gravity(gravity)
        self.set_ground(ground)

    def set_gravity(self, gravity: tuple[float, float, float]) -> None:
        """Set gravity (m/s^2); takes effect in captured graphs too."""
        self.gravity.assign(np.array([gravity], dtype=np.float32))

    def set_ground(self, ground: Ground | None) -> None:
        """Set or remove (None) the ground plane; takes effect in captured graphs too."""
        g = ground or Ground()
        params = np.zeros(4, dtype=np.float32)
        params[IK.GROUND_ENABLED] = 1.0 if ground is not None else 0.0
        params[IK.GROUND_HEIGHT] = g.height
        params[IK.GROUND_STIFFNESS] = g.stiffness
        params[IK.GROUND_FRICTION] = g.friction
        up = np.asarray(g.up, dtype=np.float64)
        self.up.assign((up / np.linalg.norm(up)).astype(np.float32)[None])
        self.ground.assign(params)

    def step(self, state_in: State, state_out: State, dt: float) -> None:
        """Advance ``state_in`` by ``dt`` seconds into ``state_out`` (distinct states)."""
        model = self.model
        self.force.zero_()
        self.matrix.zero_()
        fem.elastic_forces_and_stiffness(model, state_in.x, dt, self.rotation, self.force, self.matrix)
        integrate.build_system(
            model,
            state_in,
            self.force,
            self.gravity,
            self.up,
            self.ground,
            dt,
            self.matrix,
            self.rhs,
            self.diag_inv,
            state_out.v,
        )
        self.cg.solve(self.matrix, self.diag_inv, self.rhs, state_out.v)
        integrate.advance_positions(model, state_in.x, state_out.v, dt, state_out.x, self.bad_vertex)

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
