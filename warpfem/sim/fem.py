"""Host side of the corotational FEM stage: launches the per-tet force and stiffness kernel."""

from __future__ import annotations

import numpy as np
import warp as wp

from warpfem.kernels import fem as K
from warpfem.sim.cg import CAP_SLACK, CGSolver
from warpfem.sim.launch import spread_block_dim
from warpfem.sim.model import Model


def elastic_forces_and_stiffness(
    model: Model,
    x: wp.array,
    dt: float,
    rotation_out: wp.array,
    force_out: wp.array,
    matrix_out: wp.array,
    grad_out: wp.array | None = None,
    given_rotation: bool = False,
    v: wp.array | None = None,
    predict_least: float = 0.0,
) -> None:
    """Add every tet's corotational elastic force (N) and (dt^2 + dt beta) R K R^T to the outputs.

    Linear or quadratic tets, as the model has.
    ``force_out`` and ``matrix_out`` are accumulated into (zero them first); ``rotation_out`` receives each
    tet's rotation at ``x``, or with ``given_rotation`` holds the rotations to linearise about; with
    velocities ``v`` (m/s) each rotation is predicted on by the tet's spin for ``dt`` where that turns more
    than ``predict_least`` (rad; see
    :func:`warpfem.kernels.fem.elastic_forces_and_stiffness`). ``grad_out``
    (zeroed first; None or empty where nothing collides) accumulates the distance
    gradients turned by the tets' rotations, for contact detection. One launch for all bodies.
    """
    if grad_out is None:
        grad_out = wp.zeros(0, dtype=wp.vec3, device=model.device)

    quadratic = model.quadratic
    topology = [model.tets, model.tet_edges] if quadratic else [model.tets]
    wp.launch(
        K.quadratic_forces_and_stiffness if quadratic else K.elastic_forces_and_stiffness,
        dim=model.tet_count,
        inputs=[
            x,
            x if v is None else v,
            *topology,
            model.dm_inv,
            model.rest_volume,
            model.tet_mu,
            model.tet_lambda,
            model.tet_beta,
            model.node_slots if quadratic else model.tet_slots,
            model.vertex_grad,
            dt,
            int(given_rotation),
            int(v is not None),
            predict_least,
        ],
        outputs=[rotation_out, force_out, matrix_out, grad_out],
        device=model.device,
        block_dim=spread_block_dim(model.tet_count, model.device),
    )


class TurnCheck:
    """The rotation updates' look at the tets: which turned within the step enough to re-linearise.

    A single linear solve misreads a tet that turned by ``theta`` past the rotation it was solved with by a
    strain of about ``theta^2 / 2``, whose energy goes as ``theta^4``. A body is re-linearised where the volume
    average of its tets' ``theta^4`` exceeds ``tolerance^4`` (it misreads more energy than the whole body turned
    by ``tolerance`` would), or where one of its tets turned more than twice ``tolerance`` (a crushed part: an
    impact's first contact). A spin turns every tet alike and updates past ``tolerance`` as a per-tet test
    would; a landing that turns a few tets a little does not. In a body that updates, the tets that turned more
    than ``tolerance`` take their rotation at the step's end.

    Args:
        model: The scene's model.
        updates: Whether the solver makes rotation updates at all (else nothing is allocated).
    """

    def __init__(self, model: Model, updates: bool) -> None:
        self.model = model
        dev, n = model.device, model.tet_count if updates else 0
        self.turned = wp.zeros(n, dtype=wp.mat33, device=dev)
        """Each tet's rotation at the positions last looked at."""
        self.turn = wp.zeros(n, dtype=float, device=dev)
        """Each tet's turn (rad) from the rotation it was solved with."""

    def look(
        self,
        x: wp.array,
        tolerance: float,
        cg: CGSolver,
        rotation: wp.array,
        body_turn: wp.array,
        changed_out: wp.array,
        body_changed_out: wp.array,
    ) -> None:
        """Replace ``rotation`` by the tets' rotations at ``x`` where they turned enough (see the class; rad).

        ``body_turn`` (one vec3 per body, zeroed first) receives each body's sum of volume x turn^4 and count of
        tets past twice ``tolerance``;
        ``changed_out[0]`` becomes 1 where a rotation was replaced, and ``body_changed_out`` (one per body) of
        each body where one was (zero them first). Nothing is replaced once one
        of ``cg``'s solves since its statistics were last read stopped short of its tolerance. Two launches for
        all bodies.
        """
        m = self.model
        block = spread_block_dim(m.tet_count, m.device)
        wp.launch(
            K.turn_rotations,
            dim=m.tet_count,
            inputs=[
                x,
                m.tets,
                m.dm_inv,
                m.rest_volume,
                m.tet_body,
                rotation,
                cg.tolerance,
                cg.residual_max,
                CAP_SLACK,
                tolerance,
            ],  # fmt: skip
            outputs=[self.turned, self.turn, body_turn],
            device=m.device,
            block_dim=block,
        )
        wp.launch(
            K.replace_turned,
            dim=m.tet_count,
            inputs=[self.turned, self.turn, m.tet_body, body_turn, m.body_volume, tolerance],
            outputs=[rotation, changed_out, body_changed_out],
            device=m.device,
            block_dim=block,
        )


class RotationWatch:
    """Tracks how far each body's tets turn between checks, to warn about fast rotation.

    One linear solve per step moves vertices along the tangent of their rotation, which stretches a body by
    sqrt(1 + (omega dt)^2) per step and adds energy; implicit Euler with the force at the step's end (rotation
    updates) keeps it from gaining but takes about (omega dt)^2 of its spin's energy per step.
    """

    def __init__(self, model: Model, rotation: wp.array) -> None:
        self.model, self.rotation = model, rotation
        self.before = wp.clone(rotation)
        self.angle = wp.zeros(len(model.bodies), dtype=float, device=model.device)
        self.tet_counts = np.array([b.tet_count for b in model.bodies], dtype=np.float64)

    def turned(self) -> np.ndarray:
        """Mean tet rotation per body (rad) since the last call (one host synchronisation).

        The mean, not the largest: a rigid spin turns every tet, an impact only the few near the contact.
        """
        self.angle.zero_()
        wp.launch(
            K.rotation_change,
            dim=self.model.tet_count,
            inputs=[self.rotation, self.before, self.model.tet_body],
            outputs=[self.angle],
            device=self.model.device,
        )
        wp.copy(self.before, self.rotation)
        return self.angle.numpy() / self.tet_counts
