"""Bodies out of the still colliders' reach, so that their skin points skip the static contact and lift tests.

In a pile most bodies are far from the ground; the per-point tests of the static colliders (the step's skin
contacts and the lift out of the still colliders) would read every one of their points to find nothing. A
bound per body (``kernels.reach``: its nodes' box, grown by how far its embedded points can stand out of
their cells, against the colliders' distances) tells those kernels which bodies to leave out; what the tests
find is the same.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from warpfem.kernels import reach as K
from warpfem.sim.integrate import StaticColliders
from warpfem.sim.model import Model

REACH_BODIES = 64
"""Scenes of more than this many bodies bound each body's reach of the still colliders (a few launches a step);
smaller scenes, a layer or two deep, rarely have a body the bound leaves out."""


def point_spread(model: Model) -> np.ndarray:
    """Per body, the largest ``sum |w|`` of the weights its skin points and dense vertices have in their cells."""
    body_of_cell = model.cell_body.numpy()
    spread = np.ones(len(model.bodies))
    for cell, bary in ((model.skin_cell, model.skin_bary), (model.dense_cell, model.dense_bary)):
        if cell.shape[0]:
            np.maximum.at(spread, body_of_cell[cell.numpy()], np.abs(bary.numpy()).sum(axis=1))
    return spread


class StaticReach:
    """Per body, whether its points can reach a still collider: the bounds the skin's static tests skip by.

    Args:
        model: The scene's model.
        colliders: Its static colliders (a moving one, or a mesh, leaves no body out).
    """

    def __init__(self, model: Model, colliders: StaticColliders) -> None:
        self.model, self.colliders = model, colliders
        dev, n = model.device, len(model.bodies)
        self.spread = wp.array(point_spread(model), dtype=float, device=dev)
        self._lower = wp.zeros(n, dtype=wp.vec3, device=dev)
        self._upper = wp.zeros(n, dtype=wp.vec3, device=dev)
        self._speed = wp.zeros(n, dtype=float, device=dev)
        self._no_speed = wp.zeros(0, dtype=float, device=dev)
        self._no_v = wp.zeros(0, dtype=wp.vec3, device=dev)
        self.clear = wp.zeros(n, dtype=float, device=dev)
        """Per body, a lower bound (m) of its skin points' clearance where none can touch a collider in the step,
        else -1 (:meth:`bound_step`)."""
        self.free = wp.zeros(n, dtype=wp.int32, device=dev)
        """Per body, 1 where none of its points can lie below a still collider past the lift's give
        (:meth:`bound_lift`)."""

    def _bounds(self, x: wp.array, v: wp.array | None) -> None:
        m, n = self.model, len(self.model.bodies)
        speed = self._speed if v is not None else self._no_speed
        boxes = [self._lower, self._upper, speed]
        wp.launch(K.clear_bounds, dim=n, outputs=boxes, device=m.device)
        inputs = [x, v if v is not None else self._no_v, m.vertex_body]
        wp.launch(K.body_bounds, dim=m.vertex_count, inputs=inputs, outputs=boxes, device=m.device)

    def bound_step(self, x: wp.array, v: wp.array, dt: float) -> wp.array:
        """:attr:`clear` for a step of ``dt`` s from positions ``x`` and velocities ``v``; returns it."""
        self._bounds(x, v)
        inputs = [self._lower, self._upper, self._speed, self.spread, self.colliders.arrays, dt]
        wp.launch(K.static_clearance, dim=len(self.model.bodies), inputs=inputs, outputs=[self.clear],
                  device=self.model.device)  # fmt: skip
        return self.clear

    def bound_lift(self, x: wp.array) -> wp.array:
        """:attr:`free` at positions ``x``; returns it."""
        self._bounds(x, None)
        inputs = [self._lower, self._upper, self.spread, self.colliders.arrays]
        wp.launch(K.lift_clearance, dim=len(self.model.bodies), inputs=inputs, outputs=[self.free],
                  device=self.model.device)  # fmt: skip
        return self.free
