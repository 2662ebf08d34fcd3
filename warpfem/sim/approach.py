"""Frames in which bodies close fast on each other run twice the substeps.

A body–body contact is found at the start of a step and, through the late pass, at the positions the solve
predicts; a thin part (a leg, an ear) that a step carries deeper than it is thick passes through before either
sees it. :class:`ApproachWatch` looks at the state at each frame's start (four launches, no host
synchronisation) and raises a device flag where two bodies near each other, or the points of the last step's
contacts, close by more than a share of the smaller body's size in one step; the frame is then run with its
steps halved (``warpfem.Simulation`` branches on the flag inside its captured graph). Only frames of fast
impacts pay for it.
"""

from __future__ import annotations

import warp as wp

from warpfem.kernels import approach as K
from warpfem.presets import APPROACH_LIMIT as DEFAULT_APPROACH_LIMIT
from warpfem.sim.collision import Collider
from warpfem.sim.model import Model, State

__all__ = ["DEFAULT_APPROACH_LIMIT", "ApproachWatch"]


class ApproachWatch:
    """The flag that a frame's bodies close on each other too fast for its steps.

    Args:
        model: A model of two or more bodies.
        collider: Its collision stage, whose last step's contacts are watched too.
        limit: The share of the smaller body's size two bodies may close by in one step (> 0).
    """

    def __init__(self, model: Model, collider: Collider, limit: float) -> None:
        if not limit > 0.0:
            raise ValueError(f"limit must be > 0, got {limit}")
        self.model, self.collider, self.limit = model, collider, float(limit)
        dev, n = model.device, len(model.bodies)
        self._momentum = wp.zeros(n, dtype=wp.vec3, device=dev)
        self._lower = wp.zeros(n, dtype=wp.vec3, device=dev)
        self._upper = wp.zeros(n, dtype=wp.vec3, device=dev)
        self.flag = wp.zeros(1, dtype=wp.int32, device=dev)
        """1 where the frame about to run needs twice the substeps (the condition :meth:`decide` sets)."""
        self._count = wp.zeros(1, dtype=wp.int32, device=dev)

    def decide(self, state: State, frame_dt: float, step_dt: float) -> None:
        """Set :attr:`flag` from ``state`` for a frame of ``frame_dt`` seconds in steps of ``step_dt``."""
        m, n, dev, c = self.model, len(self.model.bodies), self.model.device, self.collider
        boxes = [self._lower, self._upper]
        wp.launch(K.clear_bodies, dim=n, outputs=[self._momentum, *boxes, self.flag], device=dev)
        extent_in = [state.x, state.v, m.mass, m.vertex_body]
        wp.launch(K.body_extent, dim=m.vertex_count, inputs=extent_in, outputs=[self._momentum, *boxes], device=dev)
        approach_in = [self._momentum, m.body_mass, *boxes, m.body_size, frame_dt, step_dt, self.limit]
        wp.launch(K.approach, dim=n, inputs=approach_in, outputs=[self.flag], device=dev)
        contacts = [c.count, c.contact_point, c.contact_cell, c.contact_bary, c.contact_normal]
        closing_in = [*contacts, state.v, m.cells, m.point_cell, m.point_bary, m.vertex_body, m.body_size, step_dt]
        wp.launch(K.contacts_closing, dim=c.capacity, inputs=[*closing_in, self.limit], outputs=[self.flag], device=dev)

    def count(self) -> None:
        """Count one frame run at twice the substeps (launched inside that branch)."""
        wp.launch(K.count_frame, dim=1, outputs=[self._count], device=self.model.device)

    def read_count(self) -> int:
        """Frames run at twice the substeps since the last call (one host synchronisation)."""
        count = int(self._count.numpy()[0])
        self._count.zero_()
        return count
