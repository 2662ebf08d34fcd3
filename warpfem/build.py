"""From a scene to a model and a solver: preprocess each body once, place it in the world, add it.

The glue between preprocessing (:mod:`warpfem.prep`) and the simulation (:mod:`warpfem.sim`), which never
import each other; every client (the API, the CLI, the benchmarks, the studies) builds through here.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from warpfem.errors import InputError
from warpfem.prep.geometry import (
    DEFAULT_SPACING,
    SKIN_TOLERANCE,
    BodyGeometry,
    SurfaceSamples,
    body_geometry,
    surface_samples,
)
from warpfem.prep.pipeline import PreparedBody, prepare
from warpfem.scene import ObjectConfig, Scene
from warpfem.sim.collision import CollisionSettings
from warpfem.sim.integrate import Box, Ground, Sphere
from warpfem.sim.model import Model, ModelBuilder
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
        InputError: One line naming the scene file, the object and what is wrong with its mesh.
    """
    done: dict[tuple[Any, ...], PreparedBody] = {}
    prepared = []
    for obj in scene.objects:
        key = (obj.mesh, obj.prim, obj.faces, obj.subdivide, obj.maxh)
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
                )
            except InputError as err:
                raise InputError(f"{scene.path}: object '{obj.name}': {err}") from None
        prepared.append(done[key])
    return prepared


def scene_samples(scene: Scene, prepared: list[PreparedBody]) -> list[SurfaceSamples]:
    """Which dense vertices of each object collide (:func:`~warpfem.prep.geometry.surface_samples`).

    Chosen in the mesh's own coordinates, once per distinct mesh and spacing: a pile of one mesh pays once.
    """
    done: dict[tuple[int, float], SurfaceSamples] = {}
    samples = []
    for obj, body in zip(scene.objects, prepared, strict=True):
        size = float(np.linalg.norm(np.ptp(body.tet_vertices, axis=0)))
        spacing = obj.collision_spacing / obj.scale if obj.collision_spacing else DEFAULT_SPACING * size
        key = (id(body), spacing)
        if key not in done:
            done[key] = surface_samples(body.dense_vertices, body.dense_faces, spacing, SKIN_TOLERANCE * size)
        samples.append(done[key])
    return samples


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
    )
    return tet_x, geometry


def add_prepared_body(
    builder: ModelBuilder, obj: ObjectConfig, prepared: PreparedBody, placed: tuple[np.ndarray, BodyGeometry]
) -> None:
    """Add a preprocessed body, placed by :func:`placed_geometry`, with the materials of its scene object."""
    tet_x, geometry = placed
    pinned = None
    if obj.pin_min is not None:
        pinned = np.all((tet_x >= np.asarray(obj.pin_min)) & (tet_x <= np.asarray(obj.pin_max)), axis=1)
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
    )


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
        **options: :meth:`ModelBuilder.add_body`'s other keywords (damping, ``velocity``, ``pinned``, the
            dense embedding, ``self_collision``).

    Returns:
        The body's index.
    """
    geometry = body_geometry(vertices, tets, collision_spacing, surface_faces, vertex_depth, vertex_grad)
    return builder.add_body(name, vertices, tets, geometry, young, poisson, density, **options)


def ground_of(scene: Scene) -> Ground | None:
    """The scene's ground plane in solver terms, or None."""
    if not scene.ground.enabled:
        return None
    up = (0.0, 1.0, 0.0) if scene.up_axis == "Y" else (0.0, 0.0, 1.0)
    g = scene.ground
    return Ground(height=g.height, stiffness=g.stiffness, friction=g.friction, up=up)


def obstacles_of(scene: Scene) -> list[Sphere | Box]:
    """The scene's static spheres and boxes in solver terms."""
    return [
        Sphere(o.center, o.radius, o.stiffness, o.friction)
        if o.kind == "sphere"
        else Box(o.center, o.half_extents, o.stiffness, o.friction)
        for o in scene.obstacles
    ]


def solver_of(scene: Scene, model: Model, cg_path: str | None = None) -> Solver:
    """The solver a scene asks for (``cg_path``: see :class:`~warpfem.sim.solver.Solver`)."""
    c = scene.collision
    return Solver(
        model,
        gravity=scene.gravity,
        ground=ground_of(scene),
        obstacles=obstacles_of(scene),
        cg_iterations=scene.solver.cg_iterations,
        cg_tolerance=scene.solver.stop_tolerance,
        collision=CollisionSettings(stiffness=c.stiffness, friction=c.friction) if c.enabled else None,
        cg_path=cg_path,
    )
