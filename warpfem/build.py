"""From a scene to a model and a solver: preprocess each body once, place it in the world, add it.

The glue between preprocessing (:mod:`warpfem.prep`) and the simulation (:mod:`warpfem.sim`), which never
import each other; every client (the API, the CLI, the benchmarks, the studies) builds through here.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from warpfem.errors import InputError
from warpfem.prep.geometry import BodyGeometry, body_geometry
from warpfem.prep.pipeline import PreparedBody, cached_surface_samples, prepare
from warpfem.prep.samples import SKIN_TOLERANCE, SurfaceSamples, spacings
from warpfem.prep.surface import read_triangles
from warpfem.scene import HandleConfig, ObjectConfig, ObstacleConfig, Scene
from warpfem.sim.collision import CollisionSettings
from warpfem.sim.drive import Handle, Motion, quat_of_matrix
from warpfem.sim.integrate import Box, Ground, MeshCollider, Sphere
from warpfem.sim.model import Model, ModelBuilder, on_edge_nodes, quadratic_nodes
from warpfem.sim.solver import Solver


def euler_rotation(degrees: tuple[float, float, float]) -> np.ndarray:
    """Rotation matrix of XYZ Euler angles in degrees: about x first, then y, then z (R = Rz Ry Rx)."""
    ax, ay, az = (math.radians(a) for a in degrees)
    rx = np.array([[1, 0, 0], [0, math.cos(ax), -math.sin(ax)], [0, math.sin(ax), math.cos(ax)]])
    ry = np.array([[math.cos(ay), 0, math.sin(ay)], [0, 1, 0], [-math.sin(ay), 0, math.cos(ay)]])
    rz = np.array([[math.cos(az), -math.sin(az), 0], [math.sin(az), math.cos(az), 0], [0, 0, 1]])
    return rz @ ry @ rx


def prepare_scene(
    scene: Scene, cache_dir: Path | None, progress: Callable[[str, str], None] | None = None
) -> list[PreparedBody]:
    """Preprocess (or load from the cache) each distinct mesh of ``scene`` once; one entry per object.

    Args:
        scene: A validated scene.
        cache_dir: The preprocessing cache, or None for none.
        progress: Receives ``(object name, message)`` as each stage starts.

    Raises:
        InputError: One line naming the scene file, the object and what is wrong with its mesh, or with the
            collision points its ``collision_spacing`` asks of it (before any kernel is compiled).
    """
    done: dict[tuple[Any, ...], PreparedBody] = {}
    checked: set[tuple[int, float]] = set()
    prepared = []
    for obj in scene.objects:
        key = (obj.mesh, obj.prim, obj.faces, obj.subdivide, obj.maxh, obj.tets_across, obj.max_tets)
        if key not in done:
            say = None if progress is None else (lambda message, name=obj.name: progress(name, message))
            try:
                done[key] = prepare(
                    obj.mesh,
                    faces=obj.faces,
                    subdivide=obj.subdivide,
                    maxh=obj.maxh,
                    cache_dir=cache_dir,
                    progress=say,
                    prim=obj.prim,
                    across=obj.tets_across,
                    max_tets=obj.max_tets,
                )
            except InputError as err:
                raise InputError(f"{scene.path}: object '{obj.name}': {err}") from None
        body = done[key]
        spacing = _spacings(obj, body)[0]
        if (id(body), spacing) not in checked:
            _check_spacing(scene, obj, body, spacing)
            checked.add((id(body), spacing))
        prepared.append(body)
    return prepared


def _spacings(obj: ObjectConfig, body: PreparedBody) -> tuple[float, float]:
    """The collision and skin points' spacings of ``obj`` in its mesh's units (``prep.samples.spacings``)."""
    return spacings(obj.collision_spacing / obj.scale, _size(body))


def _size(body: PreparedBody) -> float:
    """A prepared body's size in its mesh's units: the diagonal of its tets' bounding box."""
    return float(np.linalg.norm(np.ptp(body.tet_vertices, axis=0)))


def scene_samples(scene: Scene, prepared: list[PreparedBody], cache_dir: Path | None = None) -> list[SurfaceSamples]:
    """Which dense vertices of each object collide (:func:`~warpfem.prep.samples.surface_samples`).

    Chosen in the mesh's own coordinates, once per distinct mesh and spacing: a pile of one mesh pays once;
    read from the preprocessing cache ``cache_dir`` where it holds them (None: computed, not stored). With
    quadratic tets every dense vertex is a skin point: an unlocked body dents between skin points where it
    lands, and a refined skin lets those dents through the ground (docs/decisions.md).
    """
    done: dict[tuple[int, float], SurfaceSamples] = {}
    samples = []
    for obj, body in zip(scene.objects, prepared, strict=True):
        spacing, skin_spacing = _spacings(obj, body)
        key = (id(body), spacing)
        if key not in done:
            done[key] = cached_surface_samples(body, spacing, SKIN_TOLERANCE * _size(body), cache_dir, skin_spacing)
            if scene.solver.elements == "quadratic":
                done[key] = replace(done[key], skin=np.arange(len(body.dense_vertices)))
        samples.append(done[key])
    return samples


MAX_COLLISION_POINTS = 1_000_000
"""The most collision points a scene's ``collision_spacing`` may ask of one body (its surface's area over the
spacing squared): a spacing in metres far below a large body's size would otherwise fill the memory while the
points are chosen. The default spacing asks a few thousand."""


def _check_spacing(scene: Scene, obj: ObjectConfig, body: PreparedBody, spacing: float) -> None:
    """InputError where ``spacing`` (mesh units) asks more than :data:`MAX_COLLISION_POINTS` of ``body``."""
    corners = body.dense_vertices[body.dense_faces]
    area = 0.5 * float(
        np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1).sum()
    )
    wanted = area / spacing**2
    if wanted > MAX_COLLISION_POINTS:
        least = obj.scale * np.sqrt(area / MAX_COLLISION_POINTS)
        raise InputError(
            f"{scene.path}: object '{obj.name}': collision_spacing = {obj.collision_spacing:g} m asks for about "
            f"{wanted:,.0f} collision points on its surface (at most {MAX_COLLISION_POINTS:,}): use {least:.2g} m "
            "or more, or 0 for the default"
        )


def placed_geometry(
    obj: ObjectConfig, prepared: PreparedBody, samples: SurfaceSamples
) -> tuple[np.ndarray, BodyGeometry]:
    """The tet vertices of a prepared body placed in the world (scale, rotate, translate), and its geometry."""
    rot = euler_rotation(obj.rotate)
    move = np.asarray(obj.translate, dtype=np.float64)
    tet_x = obj.scale * prepared.tet_vertices @ rot.T + move
    geometry = body_geometry(
        tet_x,
        prepared.tets,
        obj.collision_spacing,
        surface_faces=prepared.boundary_faces,
        vertex_depth=obj.scale * prepared.vertex_depth,
        vertex_grad=prepared.vertex_grad @ rot.T,
        dense=(obj.scale * prepared.dense_vertices @ rot.T + move, prepared.embed_tet, prepared.embed_bary),
        face_depth=obj.scale * prepared.face_depth,
        samples=samples,
        dense_faces=prepared.dense_faces,
    )
    return tet_x, geometry


def in_box(x: np.ndarray, lo: tuple[float, float, float], hi: tuple[float, float, float]) -> np.ndarray:
    """Which points of ``x`` (n, 3) lie in the box ``[lo, hi]`` (m), faces included."""
    return np.all((x >= np.asarray(lo)) & (x <= np.asarray(hi)), axis=1)


def add_prepared_body(
    builder: ModelBuilder,
    obj: ObjectConfig,
    prepared: PreparedBody,
    placed: tuple[np.ndarray, BodyGeometry],
    held: np.ndarray | None = None,
    tet_edges: np.ndarray | None = None,
) -> None:
    """Add a preprocessed body, placed by :func:`placed_geometry`, with the materials of its scene object.

    ``held``: a mask of tet vertices its handles hold (pinned, as those of its pin box). ``tet_edges``: for
    quadratic tets, each tet's edge nodes, placed after the corners (:func:`with_edge_nodes`).
    """
    tet_x, geometry = placed
    pinned = held
    if obj.pin_min is not None:
        pinned = in_box(tet_x, obj.pin_min, obj.pin_max) | (False if held is None else held)
    builder.add_body(
        obj.name,
        tet_x,
        prepared.tets,
        geometry,
        young=obj.young,
        poisson=obj.poisson,
        # the tets fill the cage, a little more than the visible surface holds: the body keeps its mass
        density=obj.density / float(prepared.stats.get("cage_volume_ratio", 1.0)),
        damping_mass=obj.damping_mass,
        damping_stiffness=obj.damping_stiffness,
        velocity=initial_velocity(tet_x, prepared.tets, obj.velocity, obj.angular_velocity),
        pinned=pinned,
        dense_faces=prepared.dense_faces,
        embed_tet=prepared.embed_tet,
        embed_bary=prepared.embed_bary,
        self_collision=obj.self_collision,
        tet_edges=tet_edges,
    )


def with_edge_nodes(
    prepared: PreparedBody, placed: tuple[np.ndarray, BodyGeometry]
) -> tuple[tuple[np.ndarray, BodyGeometry], np.ndarray]:
    """A placed body's nodes as quadratic tets (its tet vertices, then its edges' midpoints), each tet's edge nodes."""
    nodes, tet_edges = quadratic_nodes(placed[0], prepared.tets)
    return (nodes, placed[1]), tet_edges


def initial_velocity(
    x: np.ndarray, tets: np.ndarray, velocity: tuple[float, float, float], spin: tuple[float, float, float]
) -> np.ndarray:
    """Each vertex's velocity (m/s) for a body moving at ``velocity`` and spinning at ``spin`` (rad/s).

    The spin is about the centre of mass of the tets (uniform density: their centroids weighted by volume).
    """
    d = x[tets[:, 1:]] - x[tets[:, :1]]
    volume = np.linalg.det(d) / 6.0
    centre = (volume[:, None] * x[tets].mean(axis=1)).sum(axis=0) / volume.sum()
    return np.asarray(velocity, np.float64) + np.cross(np.asarray(spin, np.float64), x - centre)


def add_body(
    builder: ModelBuilder,
    name: str,
    vertices: np.ndarray,
    tets: np.ndarray,
    young: float,
    poisson: float,
    density: float,
    *,
    collision_spacing: float = 0.0,
    surface_faces: np.ndarray | None = None,
    vertex_depth: np.ndarray | None = None,
    vertex_grad: np.ndarray | None = None,
    quadratic: bool = False,
    **options: Any,
) -> int:
    """Add a tet mesh given in world coordinates (m), computing its geometry (:func:`body_geometry`).

    Args:
        builder: The model builder.
        name: Body name.
        vertices: (p, 3) tet vertex rest positions (m).
        tets: (q, 4) positively oriented tets.
        young: Young's modulus (Pa).
        poisson: Poisson's ratio.
        density: Density (kg/m^3).
        collision_spacing: Spacing of extra collision samples on the surface (m); 0: vertices only.
        surface_faces: Outward boundary triangles (default: the tet mesh's boundary).
        vertex_depth: Distance to the surface at each vertex (m); computed when not given.
        vertex_grad: Outward unit gradient of that distance; computed when not given.
        quadratic: Quadratic (10-node) tets: a node is added at each edge's midpoint, after ``vertices``; a
            ``pinned`` mask or per-vertex ``velocity`` given for ``vertices`` extends to it (pinned where both
            ends are, the mean velocity).
        **options: :meth:`ModelBuilder.add_body`'s other keywords (damping, ``velocity``, ``pinned``, the
            dense embedding, ``self_collision``).

    Returns:
        The body's index.
    """
    geometry = body_geometry(vertices, tets, collision_spacing, surface_faces, vertex_depth, vertex_grad)
    if quadratic:
        corners = len(vertices)
        vertices, edges = quadratic_nodes(vertices, tets)
        options["tet_edges"] = edges
        for key, merge in (("pinned", np.logical_and), ("velocity", None)):
            value = options.get(key)
            if value is not None and np.ndim(value) >= 1 and len(value) == corners:
                options[key] = on_edge_nodes(value, tets, edges, len(vertices), merge)
    return builder.add_body(name, vertices, tets, geometry, young, poisson, density, **options)


def ground_of(scene: Scene) -> Ground | None:
    """The scene's ground plane in solver terms, or None."""
    if not scene.ground.enabled:
        return None
    up = (0.0, 1.0, 0.0) if scene.up_axis == "Y" else (0.0, 0.0, 1.0)
    g = scene.ground
    return Ground(height=g.height, stiffness=g.stiffness, friction=g.friction, up=up, offset=g.offset)


def keyed_motion(keys: list, pivot: np.ndarray) -> Motion:
    """The :class:`Motion` of a scene's ``keys`` rows ``[t, tx, ty, tz, rx, ry, rz]`` about ``pivot`` (m)."""
    rows = np.asarray(keys, np.float64).reshape(-1, 7)
    rotations = [quat_of_matrix(euler_rotation(tuple(row[4:]))) for row in rows]
    return Motion(rows[:, 0], rotations, rows[:, 1:4], tuple(float(c) for c in pivot))


def obstacle_of(scene: Scene, index: int) -> Sphere | Box | MeshCollider:
    """Obstacle ``index`` of ``scene`` in solver terms (a mesh obstacle's file read and placed).

    Raises:
        InputError: An unreadable or empty mesh file (naming the scene file and the obstacle's key).
    """
    o: ObstacleConfig = scene.obstacles[index]
    if o.kind != "mesh":
        motion = None if o.keys is None else keyed_motion(o.keys, np.asarray(o.center))
        if o.kind == "sphere":
            return Sphere(o.center, o.radius, o.stiffness, o.friction, motion, o.offset)
        return Box(o.center, o.half_extents, o.stiffness, o.friction, motion, o.offset)
    try:
        vertices, faces, closed = read_triangles(o.mesh, o.prim)
    except InputError as err:
        raise InputError(f"{scene.path}: obstacle[{index}]: mesh {err}") from None
    vertices = vertices * (1.0 if o.scale is None else o.scale)
    rotation = euler_rotation(o.rotate or (0.0, 0.0, 0.0))
    translation = np.asarray(o.translate or (0.0, 0.0, 0.0), np.float64)
    placed = vertices @ rotation.T + translation
    pivot = 0.5 * (placed.min(axis=0) + placed.max(axis=0))
    motion = None if o.keys is None else keyed_motion(o.keys, pivot)
    return MeshCollider(
        vertices, faces, rotation, tuple(translation), o.stiffness, o.friction, motion, closed, o.offset
    )


def obstacles_of(scene: Scene) -> list[Sphere | Box | MeshCollider]:
    """The scene's obstacles in solver terms."""
    return [obstacle_of(scene, index) for index in range(len(scene.obstacles))]


def obstacle_names(scene: Scene) -> list[str]:
    """Each obstacle's name: its ``name``, else ``obstacle<index>``."""
    return [o.name or f"obstacle{i}" for i, o in enumerate(scene.obstacles)]


def handle_names(scene: Scene) -> list[str]:
    """Each handle's name: its ``name``, else ``handle<index>``."""
    return [h.name or f"handle{i}" for i, h in enumerate(scene.handles)]


def held_masks(scene: Scene, tet_x: list[np.ndarray]) -> list[np.ndarray]:
    """Each handle's mask of its object's placed tet vertices (``tet_x``, one array per object).

    Raises:
        InputError: A box that holds no vertex, or one that holds vertices pinned or held by another handle.
    """
    names = [obj.name for obj in scene.objects]
    taken = [np.zeros(len(x), bool) for x in tet_x]
    for k, obj in enumerate(scene.objects):
        if obj.pin_min is not None:
            taken[k] = in_box(tet_x[k], obj.pin_min, obj.pin_max)
    masks = []
    for index, h in enumerate(scene.handles):
        k = names.index(h.object)
        mask = in_box(tet_x[k], h.min, h.max)
        where = f"{scene.path}: handle[{index}]: min"
        if not mask.any():
            lo, hi = tet_x[k].min(axis=0).round(4).tolist(), tet_x[k].max(axis=0).round(4).tolist()
            raise InputError(f"{where}, max: the box holds no tet vertex of '{h.object}' (they span {lo} to {hi} m)")
        if (mask & taken[k]).any():
            raise InputError(f"{where}, max: the box holds tet vertices of '{h.object}' that its pin box or an "
                             "earlier handle already holds")  # fmt: skip
        taken[k] |= mask
        masks.append(mask)
    return masks


def handle_motion(scene: Scene, index: int) -> Motion:
    """Handle ``index``'s motion: its keys about its box's centre, or its USD prim's or joint's relative transform.

    Raises:
        InputError: The USD file or prim cannot give a rigid motion (naming the scene file and the key).
    """
    from warpfem.io.usd_motion import read_joint_motion, read_motion

    h: HandleConfig = scene.handles[index]
    if h.keys is not None:
        return keyed_motion(h.keys, 0.5 * (np.asarray(h.min) + np.asarray(h.max)))
    try:
        if h.joint is not None:
            times, rotations, translations, origin = read_joint_motion(h.usd, h.joint)
        else:
            times, rotations, translations, origin = read_motion(h.usd, h.prim)
    except InputError as err:
        raise InputError(f"{scene.path}: handle[{index}]: usd {err}") from None
    # about the prim's origin, so that between samples its path is interpolated, not a world point's
    about_origin = translations + rotations @ origin - origin
    return Motion(times, [quat_of_matrix(r) for r in rotations], about_origin, pivot=tuple(origin))


def solver_of(scene: Scene, model: Model, cg_path: str | None = None, held: list[np.ndarray] | None = None) -> Solver:
    """The solver a scene asks for (``cg_path``: see :class:`~warpfem.sim.solver.Solver`).

    ``held``: each handle's mask of its object's tet vertices (:func:`held_masks`; the model must pin them).
    """
    c = scene.collision
    held = [] if held is None else held
    if len(held) != len(scene.handles):
        raise ValueError(f"the scene has {len(scene.handles)} handles; pass held=held_masks(...) with one mask each")
    starts = {b.name: b.vertex_start for b in model.bodies}
    handles = [
        Handle(starts[h.object] + np.flatnonzero(mask), handle_motion(scene, index), name)
        for index, (h, mask, name) in enumerate(zip(scene.handles, held, handle_names(scene), strict=True))
    ]
    return Solver(
        model,
        gravity=scene.gravity,
        ground=ground_of(scene),
        obstacles=obstacles_of(scene),
        cg_iterations=scene.solver.cg_iterations,
        cg_tolerance=scene.solver.stop_tolerance,
        collision=CollisionSettings(c.stiffness, c.friction, c.offset, damping=c.damping) if c.enabled else None,
        cg_path=cg_path,
        handles=handles,
        contact_passes=scene.solver.contact_passes,
        rotation_updates=scene.solver.rotation_updates,
        rotation_tolerance=scene.solver.rotation_tolerance,
        static_lift=scene.solver.static_lift,
    )
