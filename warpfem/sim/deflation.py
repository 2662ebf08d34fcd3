"""Rigid motions taken out of CG for bodies stiffer than float32 resolves at their step.

See :mod:`warpfem.kernels.deflation` for the method. :class:`RigidDeflation` holds the per-body arrays; the solver
binds a step's positions to it (:meth:`RigidDeflation.bind`), and :class:`~warpfem.sim.cg.CGSolver` runs a solve
given one with its launches.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from warpfem.kernels import deflation as K
from warpfem.sim.launch import WIDE_BLOCK
from warpfem.sim.model import Model
from warpfem.sim.rigid import FLOAT32_EPS, RigidCorrection

DEFLATION_GATE = 0.05
"""Where the float32 rounding of a body's stiffness blocks, as a share of its vertices' mass, exceeds this, CG
leaves the rigid motions of such a body in flight to the rigid correction: block-Jacobi CG stalls or diverges
along them there (docs/decisions.md, "Stiff bodies that touch")."""


class RigidDeflation:
    """Per body: whether CG leaves its rigid motions alone, the factors of its mass block, and a solve's sums.

    A body is deflated where its stiffness rounding at the step exceeds :data:`DEFLATION_GATE`, it holds no
    vertex (a pin or a handle already fixes its rigid motion) and it touches nothing this solve (contacts tie
    its rigid motion to its deformation, which a solve of the deformation alone would then get wrong).
    """

    def __init__(self, model: Model, rigid: RigidCorrection):
        """``rigid``: the rigid correction that supplies the deflated motions (its bodies and stiffness rates)."""
        dev, nb = model.device, len(model.bodies)
        self.model, self.rigid = model, rigid
        self.held = rigid.held
        self.movable = rigid.held.numpy() == 0
        self.body_first = rigid.body_first
        self.rate_device = wp.array(rigid.rate, dtype=float, device=dev)
        self._needed: dict[float, bool] = {}
        self.blocks = [wp.zeros(nb, dtype=wp.mat33, device=dev) for _ in range(3)]  # uu, uw, ww
        self.uu_inv = wp.zeros(nb, dtype=wp.mat33, device=dev)
        self.schur_inv = wp.zeros(nb, dtype=wp.mat33, device=dev)
        self.force = wp.zeros(4 * nb, dtype=wp.vec3, device=dev)  # r's and M q's sums, by the iteration's parity
        self.torque = wp.zeros(4 * nb, dtype=wp.vec3, device=dev)
        self.active = wp.zeros(nb, dtype=wp.int32, device=dev)
        self.touching = wp.zeros(nb, dtype=wp.int32, device=dev)
        self.x: wp.array | None = None
        self.matrix_base: wp.array | None = None
        self.dt = 0.0

    def needed(self, dt: float) -> bool:
        """Whether some body may be deflated at step ``dt`` (s): in flight, it is."""
        if dt not in self._needed:
            self._needed[dt] = bool(np.any((self.rigid.rounding(dt) > DEFLATION_GATE) & self.movable))
        return self._needed[dt]

    def bind(self, x: wp.array, matrix_base: wp.array, dt: float) -> None:
        """Binds the solves to come to a step.

        ``x``: the positions (m) the rigid motions are taken about; ``matrix_base``: the system without
        elasticity, whose diagonal blocks say which bodies touch something; ``dt``: the step (s).
        """
        self.x, self.matrix_base, self.dt = x, matrix_base, dt

    @property
    def key(self) -> tuple[int, int, float]:
        """What a recorded solve depends on beyond its own arguments."""
        return (self.x.ptr, self.matrix_base.ptr, self.dt)

    def arg(self) -> K.Deflation:
        """The kernels' view of the bound bodies."""
        d = K.Deflation()
        d.x, d.mass, d.vertex_body = self.x, self.model.mass, self.model.vertex_body
        d.body_first, d.active = self.body_first, self.active
        d.uu_inv, d.kuw, d.schur_inv = self.uu_inv, self.blocks[1], self.schur_inv
        d.force, d.torque = self.force, self.torque
        return d

    def factor_launches(self) -> list:
        """The recorded launches that mark the deflated bodies, zero the sums and factor their mass blocks."""
        model, dev = self.model, self.model.device
        nb, n = len(model.bodies), model.vertex_count
        options = dict(device=dev, block_dim=WIDE_BLOCK, record_cmd=True)
        rounding = FLOAT32_EPS * self.dt * self.dt
        return [
            wp.launch(
                K.deflation_contacts,
                dim=n,
                inputs=[self.matrix_base, model.diag_slot, model.mass, model.alpha, model.vertex_body, self.dt],
                outputs=[self.touching],
                **options,
            ),
            wp.launch(
                K.deflation_active,
                dim=nb,
                inputs=[self.held, self.touching, self.rate_device, rounding, DEFLATION_GATE],
                outputs=[self.active],
                **options,
            ),
            wp.launch(K.deflation_reset, dim=4 * nb, outputs=[self.force, self.torque, *self.blocks], **options),
            wp.launch(
                K.deflation_masses,
                dim=n,
                inputs=[self.x, model.mass, model.vertex_body, self.body_first, self.active],
                outputs=self.blocks,
                **options,
            ),
            wp.launch(
                K.deflation_factor,
                dim=nb,
                inputs=[self.active, *self.blocks],
                outputs=[self.uu_inv, self.schur_inv],
                **options,
            ),
        ]
