"""How far the visible (dense) surfaces sink into each other and into the ground, measured on the meshes alone.

An independent check of what a user sees in the output: it takes only the dense meshes' points and
triangles (as written to the USD file), never the simulator's contact buffers. A dense vertex of one body
is inside another when the other's dense surface winds around it (Warp's fast winding number,
``warpfem.kernels.penetration``), and its depth is its distance to that surface. Mesh obstacles are queried
the same way in Warp kernels of that module, on the CPU; the ground, spheres and boxes in NumPy.
"""

from __future__ import annotations

import functools
import weakref
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np


@dataclass(frozen=True)
class Penetration:
    """The deepest penetrations of one frame (or the worst over several: :meth:`worst`).

    Attributes:
        depth: Deepest dense vertex of a body inside another body's dense surface (m); 0 if none.
        relative: That depth over the size (bounding-box diagonal) of the body it is inside.
        inside: ``"a in b"``: which body's vertex is inside which ("" if none).
        below_ground: Deepest dense point below the ground plane or inside a static obstacle (m); 0 if none.
        below_relative: That depth over the size of its body.
        frame: The output frame of the body figures (-1: none given, or nothing inside another body).
        below_frame: The output frame of the ground figures (-1: none given, or nothing below).
    """

    depth: float = 0.0
    relative: float = 0.0
    inside: str = ""
    below_ground: float = 0.0
    below_relative: float = 0.0
    frame: int = -1
    below_frame: int = -1

    def worst(self, other: Penetration) -> Penetration:
        """The worse of the two for each measure (relative depths decide; ``self`` where they tie)."""
        body = self if self.relative >= other.relative else other
        ground = self if self.below_relative >= other.below_relative else other
        return Penetration(
            body.depth, body.relative, body.inside, ground.below_ground, ground.below_relative, body.frame,
            ground.below_frame,
        )  # fmt: skip


_BLOCKS = (1024, 64)


def bounds(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The (3,) lower and upper corners of (n >= 1, 3) points.

    Blocks of 1,024 points, then blocks of 64 of the rest, are reduced as rows of 3,072 and 192 values, whose
    columns NumPy reduces at full speed: it reduces axis 0 of an (n, 3) array far more slowly, and column by
    column it reads the array six times (docs/decisions.md).
    """
    lows, highs, start = [], [], 0
    for size in _BLOCKS:
        rows = (len(p) - start) // size * size
        if rows:
            block = p[start : start + rows].reshape(-1, 3 * size)
            row = 3 * _BLOCKS[-1]  # a block's corners reduced again to as many as the smallest block has
            lows.append(block.min(axis=0).reshape(-1, row).min(axis=0).reshape(-1, 3))
            highs.append(block.max(axis=0).reshape(-1, row).max(axis=0).reshape(-1, 3))
            start += rows
    lows.append(p[start:])
    highs.append(p[start:])
    return np.concatenate(lows).min(axis=0), np.concatenate(highs).max(axis=0)


class BodyBounds:
    """Each body's bounding box over a flat device array of all bodies' points, in one launch.

    The points are read in chunks of :attr:`CHUNK` of one body each, so a frame's boxes cost the device a
    pass over its points and the host nothing (``warpfem.kernels.penetration.body_bounds``).

    Args:
        ranges: ``(start, end)`` of each body's points in the flat array, one after the other.
        device: Warp device of the points.

    Raises:
        ValueError: The ranges do not follow each other from 0.
    """

    CHUNK = 64

    def __init__(self, ranges: Sequence[tuple[int, int]], device: Any) -> None:
        import warp as wp

        starts, owners, end = [], [], 0
        for body, (start, stop) in enumerate(ranges):
            if start != end or stop < start:
                raise ValueError(f"body {body}: points {start}..{stop} do not follow the previous body's (end {end})")
            chunks = list(range(start, stop, self.CHUNK))
            starts += chunks
            owners += [body] * len(chunks)
            end = stop
        self.device = wp.get_device(device)
        self._chunks = len(owners)
        self._start = wp.array(np.array(starts + [end], np.int32), dtype=wp.int32, device=self.device)
        self._owner = wp.array(np.array(owners, np.int32), dtype=wp.int32, device=self.device)
        empty = np.tile(np.array([[np.inf] * 3, [-np.inf] * 3], np.float32), (len(ranges), 1))
        self._empty = wp.array(empty, dtype=wp.vec3, device=self.device)
        self.bounds = wp.empty(2 * len(ranges), dtype=wp.vec3, device=self.device)
        """Body b's lower corner at ``2 b``, its upper at ``2 b + 1`` (m); infinite both ways for a non-finite point."""

    def compute(self, points: Any) -> Any:
        """Launch the boxes of ``points`` (the flat ``wp.vec3`` array) into :attr:`bounds` and return it."""
        import warp as wp

        from warpfem.kernels import penetration as K

        wp.copy(self.bounds, self._empty)
        if self._chunks:
            wp.launch(
                K.body_bounds,
                dim=self._chunks,
                inputs=[points, self._start, self._owner],
                outputs=[self.bounds],
                device=self.device,
            )
        return self.bounds


@dataclass(frozen=True, eq=False)
class Obstacle:
    """A sphere (``radius``), a box (``half_extents``) or a triangle mesh (``mesh``), placed by ``matrix``.

    Attributes:
        center: The sphere's or box's centre in its own frame (m).
        radius: The sphere's radius (m), where neither ``half_extents`` nor ``mesh`` is given.
        half_extents: The box's half sizes (m), axis-aligned in its own frame.
        mesh: ``(vertices, faces, closed, reach)`` of a mesh obstacle in its own frame (``reach``: how far behind
            an open mesh's faces it acts, m).
        matrix: 4x4 taking its own frame to the world (column vectors); None: the identity.
    """

    center: tuple[float, float, float] = (0.0, 0.0, 0.0)
    radius: float = 0.0
    half_extents: tuple[float, float, float] | None = None
    mesh: tuple[np.ndarray, np.ndarray, bool, float] | None = None
    matrix: np.ndarray | None = None

    def depth(self, p: np.ndarray) -> np.ndarray:
        """How deep each point is inside (m; <= 0 outside); behind an open mesh's faces counts as inside."""
        if self.mesh is not None:
            return _mesh_query(self.mesh).depths(p, self.matrix)
        if self.matrix is not None:
            m = np.asarray(self.matrix, np.float64)
            p = (p - m[:3, 3]) @ m[:3, :3]
        d = p - np.asarray(self.center)
        if self.half_extents is None:
            return self.radius - np.linalg.norm(d, axis=1)
        return np.min(np.asarray(self.half_extents) - np.abs(d), axis=1)


_ACCURACY = 2.0
"""The winding number's far-field accuracy around a closed mesh obstacle (Warp's dipole approximation; its default)."""


class _MeshQuery:
    """A mesh obstacle's ``wp.Mesh`` in its own frame, on Warp's CPU device, and the depth of points in it.

    A closed mesh holds a point its surface winds around (winding number > 0.5), as deep as the point's
    distance to the surface. An open mesh holds a point behind its faces: the nearest surface point is not on
    an edge no other face shares (nor at a corner of one), the point is on that face's back side and at most
    ``reach`` (m) from it; its depth is that distance. The queries run in Warp kernels
    (``warpfem.kernels.penetration.obstacle_depth``) on the CPU, where the points are: they hold no Python
    lock, so the threads beside the check run on, and they touch no GPU stream.
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, closed: bool, reach: float) -> None:
        import warp as wp

        v, f = np.asarray(vertices, np.float64).reshape(-1, 3), np.asarray(faces, np.int64).reshape(-1, 3)
        self.device = wp.get_device("cpu")
        self.closed = bool(closed)
        flags = np.zeros(len(f), np.int32)
        if not closed and len(f):
            lone, rim = _open_edges(f.tobytes(), len(v))
            flags = (lone @ np.array([1, 2, 4]) | rim[f] @ np.array([8, 16, 32])).astype(np.int32)
        self._flags = wp.array(flags, dtype=wp.int32, device=self.device)
        self.mesh = None
        if len(f):
            points = wp.array(v.astype(np.float32), dtype=wp.vec3, device=self.device)
            indices = wp.array(f.astype(np.int32).ravel(), dtype=wp.int32, device=self.device)
            self.mesh = wp.Mesh(points, indices, support_winding_number=self.closed)
        low, high = (v.min(axis=0), v.max(axis=0)) if len(v) else (np.zeros(3), np.zeros(3))
        diagonal = float(np.linalg.norm(high - low))
        pad = (0.0 if closed else float(reach)) + 1e-6 * max(diagonal, 1e-30)  # and float32's rounding of it
        self._box = (low - pad, high + pad)
        self.reach = 2.0 * diagonal if closed else float(reach)  # a closed mesh's inside is within its size

    def posed(self, matrix: np.ndarray | None) -> Any:
        """The kernels' view of this mesh placed by ``matrix`` (4x4 of its own frame in the world; None: identity)."""
        import warp as wp

        from warpfem.kernels import penetration as K

        m = np.eye(4) if matrix is None else np.asarray(matrix, np.float64)
        o = K.MeshObstacle()
        o.mesh = self.mesh.id
        o.inverse = wp.mat33(*m[:3, :3].T.ravel())  # the rotation's transpose: as its inverse
        o.translation = wp.vec3(*m[:3, 3])
        o.lower, o.upper = wp.vec3(*self._box[0]), wp.vec3(*self._box[1])
        o.closed = int(self.closed)
        o.reach = self.reach
        o.flags = self._flags
        return o

    def depths(self, p: np.ndarray, matrix: np.ndarray | None) -> np.ndarray:
        """Depth (m, float64; 0 outside) of each of the (n, 3) world points ``p`` in this mesh placed by ``matrix``."""
        import warp as wp

        from warpfem.kernels import penetration as K

        p = np.asarray(p, np.float32).reshape(-1, 3)
        if self.mesh is None or len(p) == 0:
            return np.zeros(len(p))
        out = wp.empty(len(p), dtype=float, device=self.device)
        points = wp.array(p, dtype=wp.vec3, device=self.device)
        wp.launch(
            K.obstacle_depths,
            dim=len(p),
            inputs=[points, self.posed(matrix), _ACCURACY],
            outputs=[out],
            device=self.device,
        )
        return out.numpy().astype(np.float64)

    def fold(self, points: Any, matrix: np.ndarray | None, slot: int, deepest: Any) -> None:
        """Fold the deepest of ``points`` (``wp.vec3`` on the CPU, m) in this mesh into ``deepest[slot]`` (m)."""
        import warp as wp

        from warpfem.kernels import penetration as K

        if self.mesh is None or len(points) == 0:
            return
        wp.launch(
            K.deepest_in_obstacle,
            dim=len(points),
            inputs=[points, self.posed(matrix), _ACCURACY, slot],
            outputs=[deepest],
            device=self.device,
        )


def _mesh_query(mesh: tuple[np.ndarray, np.ndarray, bool, float]) -> _MeshQuery:
    """The query of an :class:`Obstacle`'s ``mesh``, built on its first use (a mesh checked frame after frame)."""
    v = np.ascontiguousarray(mesh[0], np.float64)
    f = np.ascontiguousarray(mesh[1], np.int64)
    return _built_query(v.tobytes(), f.tobytes(), bool(mesh[2]), float(mesh[3]))


@functools.lru_cache(maxsize=8)
def _built_query(vertices: bytes, faces: bytes, closed: bool, reach: float) -> _MeshQuery:
    """The query of a mesh given as its float64 vertices' and int64 faces' bytes (the cache's key)."""
    v = np.frombuffer(vertices, np.float64).reshape(-1, 3)
    return _MeshQuery(v, np.frombuffer(faces, np.int64).reshape(-1, 3), closed, reach)


def _deepest_in_meshes(points: Sequence[np.ndarray], obstacles: Sequence[Obstacle]) -> list[float]:
    """Per body, the deepest of its points (m) inside a mesh obstacle: folded by the kernels, read once."""
    if not obstacles:
        return [0.0] * len(points)
    import warp as wp

    queries = [_mesh_query(o.mesh) for o in obstacles]
    deepest = wp.zeros(len(points), dtype=float, device=queries[0].device)
    for slot, p in enumerate(points):
        if len(p):
            flat = wp.array(np.asarray(p, np.float32).reshape(-1, 3), dtype=wp.vec3, device=deepest.device)
            for query, obstacle in zip(queries, obstacles, strict=True):
                query.fold(flat, obstacle.matrix, slot, deepest)
    return [float(d) for d in deepest.numpy()]


@functools.lru_cache(maxsize=8)
def _open_edges(faces: bytes, vertices: int) -> tuple[np.ndarray, np.ndarray]:
    """Which edges of each face (a-b, b-c, c-a) no other face shares, and which vertices lie on such an edge.

    ``faces``: an (m, 3) int64 array's bytes (the key, so a mesh checked frame after frame is sorted once).
    """
    f = np.frombuffer(faces, np.int64).reshape(-1, 3)
    edges = np.sort(np.stack([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]], axis=1), axis=2).reshape(-1, 2)
    _, inverse, counts = np.unique(edges, axis=0, return_inverse=True, return_counts=True)
    lone = (counts[inverse.reshape(-1)] == 1).reshape(-1, 3)
    rim = np.zeros(vertices, bool)
    for k, (i, j) in enumerate(((0, 1), (1, 2), (2, 0))):
        rim[f[lone[:, k]][:, [i, j]]] = True
    lone.flags.writeable = rim.flags.writeable = False  # shared by every later call
    return lone, rim


def posed_obstacle(posed: Any) -> Obstacle:
    """An :class:`Obstacle` of one of ``Simulation.obstacles_at()``'s entries."""
    if posed.kind == "mesh":
        mesh = (posed.vertices, posed.faces, posed.shape["closed"], posed.shape["reach"])
        return Obstacle(mesh=mesh, matrix=posed.matrix)
    if posed.kind == "box":
        return Obstacle(half_extents=posed.shape["half_extents"], matrix=posed.matrix)
    return Obstacle(radius=posed.shape["radius"], matrix=posed.matrix)


def scene_colliders(
    sim: Any, time: float | None = None
) -> tuple[tuple[float, tuple[float, float, float]] | None, list[Obstacle]]:
    """The ground ``(height, up)`` (None without one) and the obstacles of a ``Simulation``.

    The obstacles are where they are at ``time`` (s; default: the simulation's current time).
    """
    scene = sim.scene
    up = (0.0, 1.0, 0.0) if scene.up_axis == "Y" else (0.0, 0.0, 1.0)
    ground = (scene.ground.height, up) if scene.ground.enabled else None
    return ground, [posed_obstacle(posed) for posed in sim.obstacles_at(time)]


def measure(
    points: Sequence[np.ndarray],
    faces: Sequence[np.ndarray],
    names: Sequence[str],
    ground: tuple[float, tuple[float, float, float]] | None = None,
    obstacles: Sequence[Obstacle] = (),
    bodies: bool = True,
    device: Any = None,
) -> Penetration:
    """Measure one frame's dense meshes (a :class:`PenetrationCheck` used once).

    Args:
        points: Each body's dense vertices (V_i, 3), metres, world frame.
        faces: Each body's closed, outward-wound triangles (F_i, 3).
        names: The bodies' names.
        ground: ``(height, up)`` of the ground plane, or None.
        obstacles: Spheres, boxes and meshes, where they are in this frame.
        bodies: Whether to measure bodies inside each other (the costly part); False: the ground and
            obstacles only.
        device: Warp device of the body check (default: Warp's default device).
    """
    return PenetrationCheck(faces, names, device).measure(points, ground, obstacles, bodies)


class PenetrationCheck:
    """Measures frames of one set of bodies, keeping their dense surfaces' ``wp.Mesh`` trees between frames.

    Every dense vertex of a body is tested against each other body whose bounding box holds it: inside where
    that body's dense surface winds around it (Warp's fast winding number), as deep as its distance to that
    surface; one kernel launch a frame (``warpfem.kernels.penetration``), the trees refitted to the new points.

    Args:
        faces: Each body's closed, outward-wound triangles (F_i, 3).
        names: The bodies' names.
        device: Warp device of the body check (default: Warp's default device).
    """

    ACCURACY = 2.0
    """The winding number's far-field accuracy (Warp's dipole approximation; its default)."""

    PAD = 1e-6
    """Padding of each body's bounding box and reach, relative to its size."""

    def __init__(self, faces: Sequence[np.ndarray], names: Sequence[str], device: Any = None) -> None:
        import warp as wp

        self.faces = [np.asarray(f, np.int32).reshape(-1, 3) for f in faces]
        self.names = list(names)
        self.device = wp.get_device(device)
        self._meshes: list[Any] | None = None  # built from the first frame checked for bodies
        self._bvh: Any = None  # the tree of the bodies' boxes, built from the first boxes
        self._started = False  # a body check launched and not collected
        self.device_seconds = 0.0
        """The device time of the last body check collected (s; 0 on the CPU)."""

    def measure(
        self,
        points: Sequence[np.ndarray],
        ground: tuple[float, tuple[float, float, float]] | None = None,
        obstacles: Sequence[Obstacle] = (),
        bodies: bool = True,
        boxes: np.ndarray | None = None,
    ) -> Penetration:
        """Measure one frame: ``points`` as in :func:`measure`, one (V_i, 3) array per body (m).

        ``boxes``: each body's (2, 3) lower and upper corners where known (:class:`BodyBounds`), so the
        points are not read for them.
        """
        if boxes is None:
            boxes = [bounds(p) if len(p) else None for p in points]
        else:
            if np.shape(boxes) != (len(points), 2, 3):
                raise ValueError(f"boxes must be a ({len(points)}, 2, 3) array, got shape {np.shape(boxes)}")
            boxes = [(box[0], box[1]) if len(p) else None for p, box in zip(points, boxes, strict=True)]
        sizes = [float(np.linalg.norm(b[1] - b[0])) if b is not None else 0.0 for b in boxes]
        shapes = [o for o in obstacles if o.mesh is None]  # spheres and boxes: NumPy costs less than a launch
        in_meshes = _deepest_in_meshes(points, [o for o in obstacles if o.mesh is not None])
        worst = Penetration()
        for p, box, size, in_mesh in zip(points, boxes, sizes, in_meshes, strict=True):
            below = max(_below(p, ground, shapes, box), in_mesh) if len(p) else 0.0
            if below > 0 and below / max(size, 1e-30) > worst.below_relative:
                worst = Penetration(below_ground=below, below_relative=below / max(size, 1e-30))
        if not bodies or sum(len(f) > 0 for f in self.faces) < 2:
            return worst
        return self._worst_inside(self._deepest(points, boxes, sizes), sizes, worst)

    def start_bodies(self, points: Any, counts: Sequence[int], bounds: Any) -> None:
        """Launch the check of bodies inside each other on a flat device array; :meth:`collect_bodies` reads it.

        Args:
            points: ``wp.vec3`` array on this check's device, the bodies' points one after the other (m).
            counts: Each body's number of points in ``points``.
            bounds: ``wp.vec3`` array of each body's lower and upper corners (:attr:`BodyBounds.bounds`).

        It queues on the device's current stream after what is there and returns without waiting (the first
        call waits once: the trees are built from its points); the points never pass through the host.

        Raises:
            RuntimeError: The previous check was not collected.
        """
        import warp as wp

        from warpfem.kernels import penetration as K

        if self._started:
            raise RuntimeError("collect the previous body check first")
        dev, first = self.device, self._meshes is None
        if first:
            self._allocate(list(counts))
        if points.shape[0] != self._points.shape[0]:
            raise ValueError(f"{points.shape[0]} points given, {self._points.shape[0]} expected")
        if dev.is_cuda and not first:
            dev.stream.record_event(self._begin)
        wp.copy(self._points, points)
        if first:
            self._build(list(counts))
            if dev.is_cuda:
                dev.stream.record_event(self._begin)
        wp.launch(
            K.check_boxes,
            dim=len(counts),
            inputs=[bounds, self._body_box, self.PAD],
            outputs=[self._lowers, self._uppers, self._reach],
            device=dev,
        )
        self._query()
        wp.copy(self._deep_host, self._deep)
        wp.copy(self._reach_host, self._reach)
        if dev.is_cuda:
            dev.stream.record_event(self._end)
        self._started = True

    def collect_bodies(self) -> Penetration:
        """Wait for the check :meth:`start_bodies` launched and return the deepest vertex inside another body.

        :attr:`device_seconds` is then the time the check took on the device (0 on the CPU).
        """
        import warp as wp

        if not self._started:
            raise RuntimeError("no body check was started")
        self._started = False
        if self.device.is_cuda:
            wp.synchronize_event(self._end)
            self.device_seconds = wp.get_event_elapsed_time(self._begin, self._end) / 1e3
        reach = self._reach_host.numpy().astype(np.float64)
        sizes = list(reach / (1 + 2 * self.PAD))
        deepest = self._decode(self._deep_host.numpy(), reach)
        return self._worst_inside(deepest, sizes, Penetration())

    def _worst_inside(self, deepest: list[tuple[float, int]], sizes: list[float], worst: Penetration) -> Penetration:
        """``worst`` updated with the deepest vertex inside another body (``deepest``: per body, depth and owner)."""
        for j, (depth, owner) in enumerate(deepest):
            relative = depth / max(sizes[j], 1e-30)
            if depth > 0 and relative > worst.relative:
                inside = f"{self.names[owner]} in {self.names[j]}"
                worst = Penetration(depth, relative, inside, worst.below_ground, worst.below_relative)
        return worst

    def _deepest(
        self,
        points: Sequence[np.ndarray],
        boxes: list[tuple[np.ndarray, np.ndarray] | None],
        sizes: list[float],
    ) -> list[tuple[float, int]]:
        """Per body: the deepest depth (m) of another body's vertex inside it, and that body's index."""
        first = self._meshes is None
        counts = [len(p) for p in points]
        if first:
            self._allocate(counts)
        self._upload(points)
        if first:
            self._build(counts)
        pad = [self.PAD * max(s, 1e-30) for s in sizes]
        reach = np.array([s + 2 * d for s, d in zip(sizes, pad, strict=True)], np.float32)
        box = [(boxes[j][0] - pad[j], boxes[j][1] + pad[j]) for j in self._box_body_np]
        self._lowers.assign(np.array([b[0] for b in box], np.float32))
        self._uppers.assign(np.array([b[1] for b in box], np.float32))
        self._reach.assign(reach)
        self._query()
        return self._decode(self._deep.numpy(), reach)

    def _query(self) -> None:
        """Refit the trees to the points and boxes in place and launch the query (the box tree built at first)."""
        import warp as wp

        from warpfem.kernels import penetration as K

        if self._bvh is None:  # built on the first boxes, so that its splits follow the bodies
            wp.synchronize_device(self.device)
            self._bvh = wp.Bvh(self._lowers, self._uppers)
        else:
            self._bvh.refit()
        for mesh in self._meshes:
            if mesh is not None:
                mesh.refit()
        self._deep.zero_()
        wp.launch(
            K.deepest_inside,
            dim=len(self._points),
            inputs=[self._points, self._owner, self._bvh.id, self._box_body, self._mesh_ids, self._reach],
            outputs=[self.ACCURACY, self._deep],
            device=self.device,
        )

    @staticmethod
    def _decode(packed: np.ndarray, reach: np.ndarray) -> list[tuple[float, int]]:
        """Per body, the depth (m) and owner packed by ``deepest_inside`` against its reach."""
        from warpfem.kernels import penetration as K

        owner = (packed & ((1 << K.OWNER_BITS) - 1)).astype(int)
        fraction = (packed >> K.OWNER_BITS).astype(np.float64) / 2.0**K.DEPTH_BITS
        return [(float(f * r), int(o)) for f, r, o in zip(fraction, reach, owner, strict=True)]

    def _allocate(self, counts: list[int]) -> None:
        """Allocate the flat point array of the bodies' points (``counts`` each)."""
        import warp as wp

        if len(counts) != len(self.faces) or len(counts) >= 1 << 20:
            raise ValueError(f"{len(counts)} point arrays for {len(self.faces)} bodies (at most 2^20)")
        self._host = None  # the host side of an upload, allocated by the first one
        self._points = wp.zeros(sum(counts), dtype=wp.vec3, device=self.device)

    def _build(self, counts: list[int]) -> None:
        """Build each body's ``wp.Mesh`` on the flat array's first points, and what the query keeps between frames."""
        import warp as wp

        dev = self.device
        wp.synchronize_device(dev)  # the trees are built from the points just copied
        self._offsets = np.concatenate([[0], np.cumsum(counts)]).astype(int)
        owner = np.repeat(np.arange(len(counts), dtype=np.int32), counts)
        self._owner = wp.array(owner, dtype=wp.int32, device=dev)
        self._meshes = [
            wp.Mesh(
                self._points[a:b],
                wp.array(f.ravel(), dtype=wp.int32, device=dev),
                support_winding_number=True,
            )
            if len(f)
            else None
            for f, a, b in zip(self.faces, self._offsets[:-1], self._offsets[1:], strict=True)
        ]
        self._mesh_ids = wp.array([m.id if m else 0 for m in self._meshes], dtype=wp.uint64, device=dev)
        self._box_body_np = [j for j, m in enumerate(self._meshes) if m is not None]
        self._box_body = wp.array(self._box_body_np, dtype=wp.int32, device=dev)
        body_box = np.full(len(counts), -1, np.int32)
        body_box[self._box_body_np] = np.arange(len(self._box_body_np), dtype=np.int32)
        self._body_box = wp.array(body_box, dtype=wp.int32, device=dev)
        self._lowers = wp.zeros(len(self._box_body_np), dtype=wp.vec3, device=dev)
        self._uppers = wp.zeros(len(self._box_body_np), dtype=wp.vec3, device=dev)
        self._reach = wp.zeros(len(counts), dtype=float, device=dev)
        self._deep = wp.zeros(len(counts), dtype=wp.int64, device=dev)
        self._reach_host = wp.zeros(len(counts), dtype=float, device="cpu", pinned=dev.is_cuda)
        self._deep_host = wp.zeros(len(counts), dtype=wp.int64, device="cpu", pinned=dev.is_cuda)
        self._begin = wp.Event(dev, enable_timing=True) if dev.is_cuda else None
        self._end = wp.Event(dev, enable_timing=True) if dev.is_cuda else None

    def _upload(self, points: Sequence[np.ndarray]) -> None:
        """Copy the bodies' points into the flat host array, then to the device (one copy)."""
        import warp as wp

        dev = self.device
        if self._host is None:
            cpu = dev.is_cpu
            self._host = self._points if cpu else wp.empty(len(self._points), dtype=wp.vec3, device="cpu", pinned=True)
        flat = self._host.numpy()
        start = 0
        for p in points:
            if len(p) != 0:
                flat[start : start + len(p)] = p
            start += len(p)
        if start != len(flat):
            raise ValueError(f"{start} points given, {len(flat)} expected")
        if self._points is not self._host:
            wp.copy(self._points, self._host)


def frame_penetration(
    sim: Any, points: Sequence[np.ndarray] | None = None, bodies: bool | None = None, time: float | None = None
) -> Penetration:
    """:func:`measure` for a :class:`warpfem.Simulation`'s current frame: its dense meshes, its scene's colliders.

    The body check runs on the simulation's device and keeps its meshes with the simulation between calls.

    Args:
        sim: The simulation (its bodies' dense triangles and names, its scene's ground and obstacles).
        points: The dense meshes as ``sim.dense_points()`` gives them (read here when not given).
        bodies: Whether to measure bodies inside each other; default: where there are two or more.
        time: The time of ``points`` (s), where moving obstacles are measured; default: the simulation's.
    """
    names = sim.body_names
    ground, obstacles = scene_colliders(sim, time)
    check = _CHECKS.get(sim)
    if check is None:
        check = _CHECKS[sim] = PenetrationCheck([b.dense_faces for b in sim.model.bodies], names, sim.device)
    return check.measure(
        sim.dense_points() if points is None else points,
        ground,
        obstacles,
        bodies=len(names) > 1 if bodies is None else bodies,
    )


_CHECKS: weakref.WeakKeyDictionary[Any, PenetrationCheck] = weakref.WeakKeyDictionary()
"""Each simulation's check, kept while the simulation lives."""


def _below(
    p: np.ndarray,
    ground: tuple[float, tuple[float, float, float]] | None,
    obstacles: Sequence[Obstacle],
    box: tuple[np.ndarray, np.ndarray] | None = None,
) -> float:
    """Deepest of the points below the ground or inside an obstacle (m; 0 if none).

    ``box``: the points' bounds (:func:`bounds`), where known: an axis-aligned ground reads its lowest point
    off them instead of reading the points again.
    """
    deepest = 0.0
    if ground is not None:
        height, up = ground
        up = np.asarray(up, np.float64) / np.linalg.norm(up)
        axis = np.flatnonzero(up)
        if len(axis) == 1:  # an axis-aligned ground reads the bounds
            a, u = int(axis[0]), float(up[axis[0]])
            low, high = bounds(p) if box is None else box
            lowest = u * float(low[a]) if u > 0 else u * float(high[a])
        else:
            lowest = float((np.asarray(p, np.float64) @ up).min())
        deepest = height - lowest
    if obstacles:
        p = np.asarray(p, np.float64)
    for obstacle in obstacles:
        deepest = max(deepest, float(obstacle.depth(p).max()))
    return max(deepest, 0.0)
