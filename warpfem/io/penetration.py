"""How far the visible (dense) surfaces sink into each other and into the ground, measured on the meshes alone.

An independent check of what a user sees in the output: it takes only the dense meshes' points and
triangles (as written to the USD file), never the simulator's contact buffers. A dense vertex of one body
is inside another when the other's dense surface winds around it (libigl's fast winding number), and its
depth is its distance to that surface.
"""

from __future__ import annotations

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
    """

    depth: float = 0.0
    relative: float = 0.0
    inside: str = ""
    below_ground: float = 0.0
    below_relative: float = 0.0

    def worst(self, other: Penetration) -> Penetration:
        """The worse of the two for each measure (relative depths decide)."""
        body = self if self.relative >= other.relative else other
        ground = self if self.below_relative >= other.below_relative else other
        return Penetration(body.depth, body.relative, body.inside, ground.below_ground, ground.below_relative)


def _bounds(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The (3,) lower and upper corners of (n, 3) points, reduced column by column (~25x faster than axis=0)."""
    return np.array([p[:, k].min() for k in range(3)]), np.array([p[:, k].max() for k in range(3)])


def _sizes(points: Sequence[np.ndarray]) -> list[float]:
    return [float(np.linalg.norm(np.subtract(*_bounds(p)[::-1]))) if len(p) else 0.0 for p in points]


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
        if self.matrix is not None:
            m = np.asarray(self.matrix, np.float64)
            p = (p - m[:3, 3]) @ m[:3, :3]
        if self.mesh is not None:
            return _mesh_depth(p, *self.mesh)
        d = p - np.asarray(self.center)
        if self.half_extents is None:
            return self.radius - np.linalg.norm(d, axis=1)
        return np.min(np.asarray(self.half_extents) - np.abs(d), axis=1)


def _mesh_depth(p: np.ndarray, vertices: np.ndarray, faces: np.ndarray, closed: bool, reach: float) -> np.ndarray:
    """Depth of each point inside a closed mesh (winding number), or behind an open one's faces.

    Behind an open mesh: the nearest point is not on an edge no other face shares (nor at a corner of one),
    the point is on that face's back side and at most ``reach`` (m) from it; its depth is that distance.
    """
    import igl

    v, f = np.asarray(vertices, np.float64), np.asarray(faces, np.int64)
    q = np.ascontiguousarray(p, np.float64)
    if closed:
        return _depth_inside(q, v, f)
    squared, face, nearest = igl.point_mesh_squared_distance(q, v, f)
    a, b, c = (v[f[face, k]] for k in range(3))
    normal = np.cross(b - a, c - a)
    behind = np.einsum("ij,ij->i", q - nearest, normal) < 0
    edges = np.sort(np.stack([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]], axis=1), axis=2).reshape(-1, 2)
    _, inverse, counts = np.unique(edges, axis=0, return_inverse=True, return_counts=True)
    lone = (counts[inverse.reshape(-1)] == 1).reshape(-1, 3)
    rim = np.zeros(len(v), bool)
    for k, (i, j) in enumerate(((0, 1), (1, 2), (2, 0))):
        rim[f[lone[:, k]][:, [i, j]]] = True
    w = igl.barycentric_coordinates(nearest, a, b, c) < 1e-5  # weights of a, b, c near 0: edge a-b has c's
    lone, corner = lone[face], rim[f[face]]
    on_open = (lone & w[:, [2, 0, 1]]).any(axis=1) | (corner & (w[:, [1, 2, 0]] & w[:, [2, 0, 1]])).any(axis=1)
    depth = np.sqrt(squared)
    return np.where(behind & ~on_open & (depth <= reach), depth, 0.0)


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
) -> Penetration:
    """Measure one frame's dense meshes.

    Args:
        points: Each body's dense vertices (V_i, 3), metres, world frame.
        faces: Each body's closed, outward-wound triangles (F_i, 3).
        names: The bodies' names.
        ground: ``(height, up)`` of the ground plane, or None.
        obstacles: Spheres, boxes and meshes, where they are in this frame.
        bodies: Whether to measure bodies inside each other (the costly part); False: the ground and
            obstacles only.
    """
    sizes = _sizes(points)
    worst = Penetration()
    for p, size in zip(points, sizes, strict=True):
        below = _below(p, ground, obstacles) if len(p) else 0.0
        if below > 0 and below / max(size, 1e-30) > worst.below_relative:
            worst = Penetration(below_ground=below, below_relative=below / max(size, 1e-30))
    if not bodies:
        return worst
    boxes = [_bounds(p) if len(p) else None for p in points]
    for j, (v_j, f_j) in enumerate(zip(points, faces, strict=True)):
        if boxes[j] is None or len(f_j) == 0:
            continue
        lo, hi = boxes[j]
        owner, near = [], []
        for i, v_i in enumerate(points):
            if i == j or boxes[i] is None or (boxes[i][0] > hi).any() or (boxes[i][1] < lo).any():
                continue
            q = v_i[np.all((v_i >= lo) & (v_i <= hi), axis=1)]
            owner.append(np.full(len(q), i))
            near.append(q)
        if not near:
            continue
        owner, depth = np.concatenate(owner), _depth_inside(np.concatenate(near), v_j, f_j)
        k = int(np.argmax(depth)) if len(depth) else 0
        relative = depth[k] / max(sizes[j], 1e-30) if len(depth) else 0.0
        if len(depth) and depth[k] > 0 and relative > worst.relative:
            inside = f"{names[owner[k]]} in {names[j]}"
            worst = Penetration(float(depth[k]), float(relative), inside, worst.below_ground, worst.below_relative)
    return worst


def frame_penetration(
    sim: Any, points: Sequence[np.ndarray] | None = None, bodies: bool | None = None, time: float | None = None
) -> Penetration:
    """:func:`measure` for a :class:`warpfem.Simulation`'s current frame: its dense meshes, its scene's colliders.

    Args:
        sim: The simulation (its bodies' dense triangles and names, its scene's ground and obstacles).
        points: The dense meshes as ``sim.dense_points()`` gives them (read here when not given).
        bodies: Whether to measure bodies inside each other; default: where there are two or more.
        time: The time of ``points`` (s), where moving obstacles are measured; default: the simulation's.
    """
    names = sim.body_names
    ground, obstacles = scene_colliders(sim, time)
    return measure(
        sim.dense_points() if points is None else points,
        [body.dense_faces for body in sim.model.bodies],
        names,
        ground,
        obstacles,
        bodies=len(names) > 1 if bodies is None else bodies,
    )


def _below(
    p: np.ndarray, ground: tuple[float, tuple[float, float, float]] | None, obstacles: Sequence[Obstacle]
) -> float:
    """Deepest of the points below the ground or inside an obstacle (m; 0 if none)."""
    deepest = 0.0
    if ground is not None:
        height, up = ground
        up = np.asarray(up, np.float64) / np.linalg.norm(up)
        axis = np.flatnonzero(up)
        if len(axis) == 1:  # an axis-aligned ground reads one column
            heights = p[:, axis[0]].astype(np.float64) * up[axis[0]]
        else:
            heights = np.asarray(p, np.float64) @ up
        deepest = float(height - heights.min())
    if obstacles:
        p = np.asarray(p, np.float64)
    for obstacle in obstacles:
        deepest = max(deepest, float(obstacle.depth(p).max()))
    return max(deepest, 0.0)


def _depth_inside(query: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Each query point's distance to the surface (vertices, faces) where the surface winds around it, else 0."""
    import igl

    depth = np.zeros(len(query))
    if len(query) == 0:
        return depth
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    q = np.asarray(query, dtype=np.float64)
    inside = igl.fast_winding_number(v, f, q) > 0.5
    if inside.any():
        distance, *_ = igl.signed_distance(q[inside], v, f, sign_type=igl.SIGNED_DISTANCE_TYPE_UNSIGNED)
        depth[inside] = np.abs(distance)
    return depth
