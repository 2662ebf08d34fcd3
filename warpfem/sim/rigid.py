"""The rigid correction: each stiff body's momentum solved exactly where float32 loses it in CG.

See :mod:`warpfem.kernels.rigid` for the method and :class:`RigidCorrection` for when it runs.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from warpfem.kernels import rigid as K
from warpfem.sim.contacts import Coupling
from warpfem.sim.launch import spread_block_dim
from warpfem.sim.model import Model

FLOAT32_EPS = 6.0e-8
"""Float32's unit roundoff."""

RIGID_TURN_LIMIT = 0.05
"""A body turning faster than this a step (rad) keeps the torque its solve left (see ``rigid_correct``)."""

RIGID_GATE = 1.0e-3
"""Where the float32 rounding of a body's stiffness blocks, as a share of its vertices' mass, exceeds this
(:meth:`RigidCorrection.needed`), each step corrects its momentum: below it the rounding is out of reach."""

COUPLED_ITERATIONS = 24
"""Iterations of the coupled solve of touching bodies' rigid motions (six unknowns a body, block-Jacobi
preconditioned): two bodies' twelve are solved in twelve; a larger stack gets as far as these go."""


class RigidCorrection:
    """Keeps the momentum of stiff bodies exactly what gravity, damping and the contacts make it.

    At E dt^2 / (rho h^2) around 1e7 (a 1 GPa body at 24 steps a second), float32 rounding of the stiffness
    blocks exceeds the mass terms, so the system's rigid motions are lost in it: CG stalls, and the motion it
    returns along them is noise that can feed energy in. Elastic forces are internal and change no momentum,
    so after a solve each body without pins or handles takes the rigid motion that zeroes the force and torque
    of its residual without the elastic terms (``rhs_base`` and ``matrix_base``: masses, damping and the
    contacts' own blocks, nothing large). A body touching others solves for it together with them, through
    the contacts between them (the coupling pairs).
    """

    def __init__(self, model: Model, rhs_base: wp.array, matrix_base: wp.array):
        """Allocates the per-body sums; takes each body's stiffness rate from ``model``.

        ``rhs_base`` and ``matrix_base``: the step's system without elasticity, late contacts included.
        """
        self.model, self.rhs_base, self.matrix_base = model, rhs_base, matrix_base
        dev, nb = model.device, len(model.bodies)
        self.body_first = wp.array([b.vertex_start for b in model.bodies], dtype=wp.int32, device=dev)
        held = np.zeros(nb, dtype=np.int32)
        held[model.vertex_body.numpy()[model.free.numpy() == 0]] = 1
        self.held = wp.array(held, dtype=wp.int32, device=dev)
        self.paired = wp.zeros(nb, dtype=wp.int32, device=dev)
        self.weight = wp.zeros(nb, dtype=float, device=dev)
        self.moment = wp.zeros(nb, dtype=wp.vec3, device=dev)
        self.force = wp.zeros(nb, dtype=wp.vec3, device=dev)
        self.torque = wp.zeros(nb, dtype=wp.vec3, device=dev)
        self.second = wp.zeros(nb, dtype=wp.mat33, device=dev)
        self.momentum = wp.zeros(nb, dtype=wp.vec3, device=dev)
        self.spin = wp.zeros(nb, dtype=wp.vec3, device=dev)
        self.contact = [wp.zeros(nb, dtype=wp.mat33, device=dev) for _ in range(3)]  # blocks uu, uw, ww
        self.sums = K.RigidSums()
        self.sums.weight, self.sums.moment, self.sums.second = self.weight, self.moment, self.second
        self.sums.kuu, self.sums.kuw, self.sums.kww = self.contact
        self.sums.held, self.sums.paired = self.held, self.paired
        self.krylov = K.Krylov()
        for name in ("zu", "zw", "ru", "rw", "pu", "pw", "qu", "qw", "su", "sw"):
            setattr(self.krylov, name, wp.zeros(nb, dtype=wp.vec3, device=dev))
        self.krylov.rs = wp.zeros(COUPLED_ITERATIONS + 1, dtype=float, device=dev)
        self.krylov.pq = wp.zeros(COUPLED_ITERATIONS, dtype=float, device=dev)
        self.rate = _stiffness_rate(model)
        self._needed: dict[float, bool] = {}

    def rounding(self, dt: float) -> np.ndarray:
        """Per body, float32's rounding of its stiffness blocks at step ``dt`` (s), as a share of its mass."""
        return FLOAT32_EPS * dt * dt * self.rate

    def needed(self, dt: float) -> bool:
        """Whether some body's stiffness rounding at step ``dt`` (s) exceeds :data:`RIGID_GATE` of its mass."""
        if dt not in self._needed:
            self._needed[dt] = bool(np.any(self.rounding(dt) > RIGID_GATE))
        return self._needed[dt]

    def apply(self, x: wp.array, v_start: wp.array, v: wp.array, dt: float, coupling: Coupling | None) -> None:
        """Corrects ``v`` (the solve's answer, m/s) of each body without held vertices.

        ``x``, ``v_start``: the step's start.
        """
        model, dev = self.model, self.model.device
        n = model.vertex_count
        block = spread_block_dim(n, dev)
        sums = [self.weight, self.moment, self.force, self.torque, self.second, self.momentum, self.spin]
        for a in (self.paired, *sums, *self.contact, self.krylov.rs, self.krylov.pq):
            a.zero_()
        pairs = coupling is not None and coupling.matrix.shape[0] > 0
        if pairs:
            wp.launch(
                K.mark_touched_pairs,
                dim=coupling.matrix.shape[0],
                inputs=[coupling.count, coupling.verts_a, coupling.verts_b, model.vertex_body],
                outputs=[self.paired],
                device=dev,
                block_dim=spread_block_dim(coupling.matrix.shape[0], dev),
            )
        per_vertex = [model.mass, model.alpha, model.vertex_body, self.body_first, self.held]
        wp.launch(
            K.rigid_sums,
            dim=n,
            inputs=[x, v_start, v, self.rhs_base, *per_vertex, dt],
            outputs=sums,
            device=dev,
            block_dim=block,
        )
        wp.launch(
            K.rigid_contact_sums,
            dim=n,
            inputs=[x, v, model.row_start, model.cols, model.diag_slot, self.matrix_base, *per_vertex, dt],
            outputs=[self.force, self.torque, *self.contact],
            device=dev,
            block_dim=block,
        )
        bodies = [x, model.vertex_body, self.body_first, self.held, self.paired]
        wp.launch(
            K.rigid_correct,
            dim=n,
            inputs=[*bodies, *sums, *self.contact, dt, RIGID_TURN_LIMIT],
            outputs=[v],
            device=dev,
            block_dim=block,
        )
        if pairs:
            self._coupled(x, v, coupling)

    def _coupled(self, x: wp.array, v: wp.array, coupling: Coupling) -> None:
        """The touching bodies' rigid motions, solved together through their pairs, added to ``v``."""
        model, dev = self.model, self.model.device
        nb, capacity = len(model.bodies), coupling.matrix.shape[0]
        k, m = self.krylov, self.sums
        pair_args = [
            coupling.count, coupling.verts_a, coupling.weights_a, coupling.verts_b, coupling.weights_b,
            coupling.matrix,
        ]  # fmt: skip
        bodies = [x, model.vertex_body, self.body_first, self.held, self.paired]
        pair_block = spread_block_dim(capacity, dev)
        wp.launch(
            K.coupled_pairs,
            dim=capacity,
            inputs=[*pair_args, v, *bodies, 0, k.pu, k.pw, -1.0],
            outputs=[self.force, self.torque],
            device=dev,
            block_dim=pair_block,
        )
        wp.launch(K.coupled_start, dim=nb, inputs=[m, self.force, self.torque, k], device=dev)
        for it in range(COUPLED_ITERATIONS):
            wp.launch(K.coupled_blocks, dim=nb, inputs=[m, k], device=dev)
            wp.launch(
                K.coupled_pairs,
                dim=capacity,
                inputs=[*pair_args, v, *bodies, 1, k.pu, k.pw, 1.0],
                outputs=[k.qu, k.qw],
                device=dev,
                block_dim=pair_block,
            )
            wp.launch(K.coupled_curvature, dim=nb, inputs=[m, k, it], device=dev)
            wp.launch(K.coupled_step, dim=nb, inputs=[m, k, it], device=dev)
            wp.launch(K.coupled_direction, dim=nb, inputs=[m, k, it], device=dev)
        wp.launch(
            K.coupled_apply,
            dim=model.vertex_count,
            inputs=[x, model.vertex_body, self.body_first, m, k],
            outputs=[v],
            device=dev,
            block_dim=spread_block_dim(model.vertex_count, dev),
        )


def _stiffness_rate(model: Model) -> np.ndarray:
    """Per body, the largest (lambda + 2 mu) V |grad N|^2 / m over its tets and corners (1/s^2).

    That is a tet's stiffness block over its corner's mass; times dt^2, their ratio in the system.
    """
    tets = model.tets.numpy()
    g = model.dm_inv.numpy()  # rows: the gradients of barycentric coordinates 1-3
    grads = np.concatenate([-g.sum(axis=1, keepdims=True), g], axis=1)  # (q, 4, 3)
    modulus = model.tet_lambda.numpy() + 2.0 * model.tet_mu.numpy()
    block = modulus[:, None] * model.rest_volume.numpy()[:, None] * np.sum(grads * grads, axis=2)
    mass = np.maximum(model.mass.numpy()[tets], 1e-30)
    per_tet = np.max(block / mass, axis=1)
    rate = np.zeros(len(model.bodies))
    np.maximum.at(rate, model.tet_body.numpy(), per_tet)
    return rate
