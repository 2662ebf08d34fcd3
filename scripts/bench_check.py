"""The benchmark's dense check: penetration of the dense meshes, measured on the meshes alone, over the run it
times (``scripts/bench.py``)."""

from __future__ import annotations

import dataclasses

import numpy as np
import warp as wp

import warpfem

CHECKS_OVER_RUN = 12
"""Frames of the run (the timed frames and the ones before them) on which the dense meshes are checked for
penetration by default, besides the last (``--check-every`` sets the frames between checks instead: 1 checks
every frame)."""

CHECK_MAX_BODIES = 256
"""Scenes of more bodies are checked at the end only by default (the check of a frame grows with the bodies in
contact): ``--check-bodies``. The pile of 256's landing is where the overlap over a run peaks, so it is checked
over its run; the pile of 1,024 at the end only (docs/decisions.md, "Friction from the load, not the
overlap")."""


def checked_frames(run_frames: int, every: int) -> list[int]:
    """The frames of a run of ``run_frames`` (numbered from 1) the dense check reads: every ``every``-th and the
    last (0: :data:`CHECKS_OVER_RUN` spread over it)."""
    every = every or max(1, run_frames // CHECKS_OVER_RUN)
    return sorted({*range(every, run_frames + 1, every), run_frames})


class FrameChecks:
    """The figures of a run's checked frames: the worst (and its frame), the last frame's, each frame's."""

    def __init__(self, last: int) -> None:
        self.last, self.worst, self.end = last, warpfem.Penetration(), warpfem.Penetration()
        # inside another body, below the ground (relative), which body in which ("" for none)
        self.by_frame: dict[int, tuple[float, float, str]] = {}

    def add(self, frame: int, now: warpfem.Penetration) -> None:
        """Frame ``frame``'s figures."""
        self.worst = self.worst.worst(now)
        self.by_frame[frame] = (now.relative, now.below_relative, now.inside)
        if frame == self.last:
            self.end = now

    def result(self) -> dict:
        """The JSON of the checks: ``end``, ``worst`` (with its frames), the frames checked and their figures (the
        depth inside another body and below the ground, and the pair of bodies of the first)."""
        frames = sorted(self.by_frame)

        def first_deepest(k: int) -> int:  # the first frame of the worst figure k (0: none above zero)
            deepest = max(frames, key=lambda f: self.by_frame[f][k], default=0)
            return deepest if deepest and self.by_frame[deepest][k] > 0 else 0

        end, worst = dataclasses.asdict(self.end), dataclasses.asdict(self.worst)
        worst |= {"frame": first_deepest(0), "below_frame": first_deepest(1)}
        by_frame = {key: [self.by_frame[f][k] for f in frames] for k, key in enumerate(("inside", "below", "pair"))}
        return {"end": end, "worst": worst, "frames_checked": len(frames), "frames": frames, "by_frame": by_frame}


class DenseCheck:
    """Penetration of the dense meshes measured on the meshes alone (``warpfem.io.penetration``), over the run.

    The frames to check (:func:`checked_frames`) are checked as they come before the timed frames; during them
    each is copied on the device into a buffer allocated beforehand (no host synchronisation), and checked once
    they are timed. So the run checked is the run timed, its solver state included. Scenes of more than
    ``most_bodies`` bodies are checked at their last frame only.
    """

    def __init__(self, sim: warpfem.Simulation, run_frames: int, timed_from: int, most_bodies: int, every: int):
        frames = checked_frames(run_frames, every) if len(sim.body_names) <= most_bodies else [run_frames]
        self.sim, self.checks = sim, FrameChecks(run_frames)
        self.buffers = {f: wp.empty_like(sim.dense) for f in frames if f >= timed_from}
        self.direct = set(frames) - set(self.buffers)

    def after(self, frame: int) -> None:
        """Frame ``frame`` of the run has been stepped and mapped: check it now (before the timed frames), or
        copy it for later."""
        if frame in self.direct:
            self._check(frame, None)
        elif frame in self.buffers:
            wp.copy(self.buffers[frame], self.sim.dense)

    def result(self) -> dict:
        """Check the copied frames; the worst over the checked frames and the last frame's figures."""
        for frame, buffer in sorted(self.buffers.items()):
            self._check(frame, buffer.numpy())
        self.buffers.clear()
        return self.checks.result()

    def _check(self, frame: int, flat: np.ndarray | None) -> None:
        from warpfem.io.penetration import frame_penetration

        bodies = self.sim.model.bodies
        points = None if flat is None else [flat[b.dense_start : b.dense_start + b.dense_count] for b in bodies]
        self.checks.add(frame, frame_penetration(self.sim, points, bodies=True, time=frame / self.sim.fps))
