"""Frames in which bodies close fast on each other run more substeps.

A body–body contact is found at the start of a step and, through the late pass, at the positions the solve
predicts; a thin part (a leg, an ear) that a step carries deeper than it is thick passes through before either
sees it. :class:`ApproachWatch` looks at the state at each frame's start (a few launches, no host
synchronisation) and raises a device flag where two bodies near each other, or the points of the last step's
contacts, close by more than a share of the smaller body's size in one step; the frame then runs the fewest of
1.25, 1.5 or 2 times its substeps that brings that closing within the share (``warpfem.Simulation`` branches on
the flags inside its captured graph). Only frames of fast impacts pay for it.
"""

from __future__ import annotations

import warp as wp

from warpfem.kernels import approach as K
from warpfem.presets import APPROACH_LIMIT as DEFAULT_APPROACH_LIMIT
from warpfem.sim.collision import Collider
from warpfem.sim.model import Model, State

__all__ = ["DEFAULT_APPROACH_LIMIT", "ApproachWatch", "refined_substeps"]


REFINED_RATIOS = ((5, 4), (3, 2), (2, 1))
"""The refined levels' substeps as fractions of the frame's own: 1.25, 1.5 and 2 times (each where it is a
whole number of steps; ``warpfem.sim.drive.TICKS_PER_STEP`` counts the steps of each in whole ticks)."""


def refined_substeps(substeps: int) -> tuple[int, ...]:
    """The substeps a refined frame may run, fewest first.

    Each of :data:`REFINED_RATIOS` times ``substeps`` that is a whole number: 1.25 times a multiple of 4,
    1.5 times an even count, and twice any.
    """
    return tuple(substeps * a // b for a, b in REFINED_RATIOS if substeps * a % b == 0)


class ApproachWatch:
    """The flag that a frame's bodies close on each other too fast for its steps.

    Args:
        model: A model of two or more bodies.
        collider: Its collision stage, whose last step's contacts are watched too.
        limit: The share of the smaller body's size two bodies may close by in one step (> 0).
        substeps: The frame's substeps (>= 1); a refined frame runs one of :func:`refined_substeps`.
    """

    def __init__(self, model: Model, collider: Collider, limit: float, substeps: int) -> None:
        if not limit > 0.0:
            raise ValueError(f"limit must be > 0, got {limit}")
        self.model, self.collider, self.limit = model, collider, float(limit)
        self.substeps = int(substeps)
        self.levels = refined_substeps(self.substeps)
        """The substeps a refined frame runs: the first whose steps close by at most ``limit``, else the last."""
        dev, n = model.device, len(model.bodies)
        self._momentum = wp.zeros(n, dtype=wp.vec3, device=dev)
        self._lower = wp.zeros(n, dtype=wp.vec3, device=dev)
        self._upper = wp.zeros(n, dtype=wp.vec3, device=dev)
        self.flags = wp.zeros(len(self.levels), dtype=wp.int32, device=dev)
        """Per refined level (:attr:`levels`), 1 where the frame about to run needs at least that many substeps
        (the conditions :meth:`decide` sets); ``flag`` is the first: the frame needs refining at all."""
        self.flag = self.flags[0:1]
        below = (self.substeps, *self.levels[:-1])
        shares = [self.limit * fewer / self.substeps for fewer in below]
        self._limits = wp.array(shares, dtype=float, device=dev)
        """Per level, the closing in one of the frame's own steps (a share of the smaller size) past which the
        substeps below that level would each close by more than ``limit``."""
        self._count = wp.zeros(len(self.levels), dtype=wp.int32, device=dev)

    def decide(self, state: State, frame_dt: float, step_dt: float) -> None:
        """Set :attr:`flags` from ``state`` for a frame of ``frame_dt`` seconds in steps of ``step_dt``.

        Level k's flag rises where the closing in one step exceeds ``limit`` times the ratio of the substeps
        below that level to the frame's own: its steps would close by more than ``limit``.
        """
        m, n, dev, c = self.model, len(self.model.bodies), self.model.device, self.collider
        boxes = [self._lower, self._upper]
        wp.launch(K.clear_bodies, dim=n, outputs=[self._momentum, *boxes, self.flags], device=dev)
        extent_in = [state.x, state.v, m.mass, m.vertex_body]
        wp.launch(K.body_extent, dim=m.vertex_count, inputs=extent_in, outputs=[self._momentum, *boxes], device=dev)
        approach_in = [self._momentum, m.body_mass, *boxes, m.body_size, frame_dt, step_dt, self._limits]
        wp.launch(K.approach, dim=n, inputs=approach_in, outputs=[self.flags], device=dev)
        contacts = [c.count, c.contact_point, c.contact_cell, c.contact_bary, c.contact_normal]
        closing_in = [*contacts, state.v, m.cells, m.point_cell, c.point_bary, m.vertex_body, m.body_size, step_dt]
        closing_in.append(self._limits)
        wp.launch(K.contacts_closing, dim=c.capacity, inputs=closing_in, outputs=[self.flags], device=dev)

    def count(self, level: int) -> None:
        """Count one frame run at refined level ``level`` (launched inside that branch)."""
        wp.launch(K.count_frame, dim=1, outputs=[self._count[level : level + 1]], device=self.model.device)

    def read_count(self) -> list[int]:
        """Frames run at each refined level since the last call (one host synchronisation)."""
        counts = [int(k) for k in self._count.numpy()]
        self._count.zero_()
        return counts
