"""Driven motion: rigid keyframed motions, handles holding vertices to them, and the device side posing both.

:class:`Motion` is a keyframed rigid motion, :class:`Handle` a set of vertices held to one, :class:`Drive` what
poses the handles and moving colliders on the device each step.

A held vertex is kinematic: it leaves the solve as a pin does, with the velocity that takes it to its
handle's pose at the step's end (docs/decisions.md: kinematic handles). A moving collider's pose at the
step's start and end is written into the solver's collider arrays, so its contacts see its surface's speed.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import warp as wp

from warpfem.kernels import drive as K
from warpfem.sim.approach import REFINED_RATIOS


def quat_of_matrix(r: np.ndarray) -> np.ndarray:
    """The unit quaternion (x, y, z, w) of a rotation matrix (Shepperd's method)."""
    r = np.asarray(r, np.float64)
    trace = np.trace(r)
    if trace > 0:
        s = 2.0 * np.sqrt(1.0 + trace)
        q = [(r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s, 0.25 * s]
    else:
        a = int(np.argmax(np.diag(r)))
        b, c = (a + 1) % 3, (a + 2) % 3
        s = 2.0 * np.sqrt(1.0 + r[a, a] - r[b, b] - r[c, c])
        q = [0.0, 0.0, 0.0, (r[c, b] - r[b, c]) / s]
        q[a], q[b], q[c] = 0.25 * s, (r[a, b] + r[b, a]) / s, (r[a, c] + r[c, a]) / s
    q = np.asarray(q)
    return q / np.linalg.norm(q)


def matrix_of_quat(q: np.ndarray) -> np.ndarray:
    """The rotation matrix of a unit quaternion (x, y, z, w)."""
    x, y, z, w = np.asarray(q, np.float64) / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def _slerp(q0: np.ndarray, q1: np.ndarray, u: float) -> np.ndarray:
    angle = np.arccos(np.clip(np.dot(q0, q1), -1.0, 1.0))
    if angle < 1e-9:
        return q0
    return (np.sin((1 - u) * angle) * q0 + np.sin(u * angle) * q1) / np.sin(angle)


@dataclass(frozen=True)
class Motion:
    """A rigid motion over time, ``x(t) = pivot + T(t) + R(t) (x - pivot)``, from keys.

    Between keys the translation is interpolated linearly and the rotation by slerp (the shorter way);
    before the first key and after the last the motion holds.

    Attributes:
        times: (k,) key times (s), strictly increasing.
        rotations: (k, 4) unit quaternions (x, y, z, w) of R at the keys.
        translations: (k, 3) T at the keys (m).
        pivot: The point R turns about (m).
    """

    times: np.ndarray
    rotations: np.ndarray
    translations: np.ndarray
    pivot: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        times = np.asarray(self.times, np.float64).reshape(-1)
        q = np.asarray(self.rotations, np.float64).reshape(-1, 4)
        t = np.asarray(self.translations, np.float64).reshape(-1, 3)
        if not len(times) or len(q) != len(times) or len(t) != len(times):
            raise ValueError("a motion needs at least one key, with one rotation and one translation per time")
        if (np.diff(times) <= 0).any():
            raise ValueError("a motion's key times must be strictly increasing")
        q = q / np.linalg.norm(q, axis=1, keepdims=True)
        for k in range(1, len(q)):  # the shorter way: each key on the side of the one before it
            if np.dot(q[k], q[k - 1]) < 0:
                q[k] = -q[k]
        object.__setattr__(self, "times", times)
        object.__setattr__(self, "rotations", q)
        object.__setattr__(self, "translations", t)

    @classmethod
    def still(cls) -> Motion:
        """The motion that never moves."""
        return cls(np.zeros(1), np.array([[0.0, 0.0, 0.0, 1.0]]), np.zeros((1, 3)))

    def at(self, time: float) -> tuple[np.ndarray, np.ndarray]:
        """R (3x3) and the translation of ``x -> R x + t`` at ``time`` (s), in float64."""
        times = self.times
        k = int(np.searchsorted(times, time, side="right")) - 1
        if k < 0:
            q, move = self.rotations[0], self.translations[0]
        elif k >= len(times) - 1:
            q, move = self.rotations[-1], self.translations[-1]
        else:
            u = (time - times[k]) / (times[k + 1] - times[k])
            q = _slerp(self.rotations[k], self.rotations[k + 1], u)
            move = (1 - u) * self.translations[k] + u * self.translations[k + 1]
        r = matrix_of_quat(q)
        pivot = np.asarray(self.pivot, np.float64)
        return r, pivot + move - r @ pivot

    def matrix(self, time: float) -> np.ndarray:
        """:meth:`at` as one 4x4 matrix (column vectors)."""
        pose = np.eye(4)
        pose[:3, :3], pose[:3, 3] = self.at(time)
        return pose


@dataclass(frozen=True)
class Handle:
    """Tet vertices held to a rigid motion of their rest positions.

    Attributes:
        vertices: Global indices of the held tet vertices; each must be pinned in the model (``free`` 0).
        motion: Their motion: vertex i is at ``R(t) x0_i + t(t)``.
        name: A name for output.
    """

    vertices: np.ndarray
    motion: Motion = field(default_factory=Motion.still)
    name: str = "handle"


TICKS_PER_STEP = math.lcm(*(more for more, _ in REFINED_RATIOS))
"""The clock counts ticks of the first step's dt over this many (30), so that a step of a refined frame
(``warpfem.sim.approach.REFINED_RATIOS``: four fifths, two thirds or half as long) advances it by a whole number
of ticks (24, 20 or 15) and the motions keep their time."""


class Drive:
    """The device side of the handles and moving colliders: their keys, the clock, one launch per step.

    Args:
        model: The model (its rest positions and pins).
        handles: The handles.
        colliders: ``(collider index, motion, rest rotation 3x3, rest translation)`` of each moving collider.
        center, rotation, center_next, rotation_next: The solver's collider pose arrays, written each step.

    Raises:
        ValueError: A handle vertex the model does not pin, or one held by two handles.
    """

    def __init__(self, model, handles: Sequence[Handle], colliders: Sequence[tuple], poses: Sequence[wp.array]):
        dev = model.device
        free = model.free.numpy()
        vertices = [np.asarray(h.vertices, np.int64).reshape(-1) for h in handles]
        held = np.concatenate(vertices) if vertices else np.zeros(0, np.int64)
        if len(held) and (free[held] != 0).any():
            raise ValueError("a handle holds a vertex the model does not pin (pass it in pinned)")
        if len(np.unique(held)) != len(held):
            raise ValueError("a vertex is held by two handles")
        motions = [c[1] for c in colliders] + [h.motion for h in handles]
        rests = [(c[2], c[3]) for c in colliders] + [(np.eye(3), np.zeros(3))] * len(handles)
        tracks = K.Tracks()
        tracks.start = _arr(np.cumsum([0] + [len(m.times) for m in motions]), wp.int32, dev)
        tracks.time = _arr(np.concatenate([m.times for m in motions]), float, dev)
        tracks.rotation = _arr(np.concatenate([m.rotations for m in motions]), wp.quat, dev)
        tracks.translation = _arr(np.concatenate([m.translations for m in motions]), wp.vec3, dev)
        tracks.pivot = _arr([m.pivot for m in motions], wp.vec3, dev)
        tracks.rest_rotation = _arr([quat_of_matrix(r) for r, _ in rests], wp.quat, dev)
        tracks.rest_translation = _arr([t for _, t in rests], wp.vec3, dev)
        self.tracks = tracks
        self.collider_index = _arr([c[0] for c in colliders], wp.int32, dev)
        self.collider_track = _arr(np.arange(len(colliders)), wp.int32, dev)
        self.held_vertex = _arr(held, wp.int32, dev)
        self.held_track = _arr(np.repeat(np.arange(len(handles)) + len(colliders), [len(v) for v in vertices]),
                               wp.int32, dev)  # fmt: skip
        self.held_v = wp.zeros(model.vertex_count if len(held) else 0, dtype=wp.vec3, device=dev)
        """Each held vertex's velocity this step (m/s); what a pinned vertex without a handle keeps: zero."""
        self.clock = wp.zeros(1, dtype=wp.int32, device=dev)
        """Ticks taken: the motions' time is ``clock * tick_dt``."""
        self.tick_dt: float | None = None
        """A tick (s): the first step's dt over :data:`TICKS_PER_STEP`; every step is a whole number of ticks."""
        self.poses = poses
        self.model = model
        self.handles = list(handles)
        self.dim = len(colliders) + len(held)

    def pose(self, x: wp.array, dt: float) -> None:
        """Pose the moving colliders over the step about to be taken and the held vertices' velocities."""
        if self.dim == 0:
            return
        self._ticks(dt)
        wp.launch(
            K.drive,
            dim=self.dim,
            inputs=[self.clock, self.tick_dt, dt, self.tracks, self.collider_index, self.collider_track,
                    self.held_vertex, self.held_track, self.model.rest_x, x],
            outputs=[*self.poses, self.held_v],
            device=self.model.device,
        )  # fmt: skip

    def set_step(self, dt: float) -> None:
        """Set the clock's tick from a run's step of ``dt`` s, before the first step.

        A refined frame's shorter steps are then whole numbers of ticks whichever frame comes first.
        """
        if self.tick_dt is None:
            self.tick_dt = dt / TICKS_PER_STEP

    def tick(self, dt: float) -> None:
        """One step of ``dt`` s taken (after every launch of the step that reads the clock)."""
        wp.launch(K.tick, dim=1, inputs=[self.clock, self._ticks(dt)], device=self.model.device)

    def _ticks(self, dt: float) -> int:
        """How many ticks a step of ``dt`` s is; ValueError if not a whole number.

        The first step sets the tick where :meth:`set_step` did not.
        """
        self.set_step(dt)
        ticks = round(dt / self.tick_dt)
        if ticks < 1 or abs(ticks * self.tick_dt - dt) > 1e-9 * dt:
            raise ValueError(f"a driven step of {dt} s is not a whole number of the clock's {self.tick_dt} s ticks")
        return ticks


def _arr(data, dtype, device) -> wp.array:
    np_type = np.int32 if dtype == wp.int32 else np.float32
    values = np.asarray(data, dtype=np_type)
    if dtype in (wp.vec3, wp.quat):
        values = values.reshape(-1, 3 if dtype == wp.vec3 else 4)
    return wp.array(np.ascontiguousarray(values), dtype=dtype, device=device)
