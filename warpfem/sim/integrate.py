"""Host side of the implicit Euler stage: static colliders, system assembly per vertex, position update."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import warp as wp

from warpfem.kernels import integrate as K
from warpfem.kernels.product import Pairs
from warpfem.presets import STATIC_OFFSET, STATIC_OFFSET_LIMIT
from warpfem.sim.drive import Motion, quat_of_matrix
from warpfem.sim.launch import spread_block_dim
from warpfem.sim.model import Model, State


def check_response(owner: str, stiffness: float, friction: float, offset: float) -> None:
    """Raise ValueError naming ``owner``'s field where a collider's penalty, friction or offset is out of range."""
    if not stiffness > 0.0:
        raise ValueError(f"{owner}.stiffness must be > 0 1/s^2, got {stiffness}")
    if not friction >= 0.0:
        raise ValueError(f"{owner}.friction must be >= 0, got {friction}")
    if not 0.0 <= offset <= STATIC_OFFSET_LIMIT:
        raise ValueError(f"{owner}.offset must be in [0, {STATIC_OFFSET_LIMIT}] of the size, got {offset}")


def check_vector(owner: str, name: str, value, positive: bool = False) -> None:
    """Raise ValueError unless ``value`` is three finite numbers (each > 0 where ``positive``)."""
    v = np.asarray(value, dtype=np.float64) if np.ndim(value) == 1 and len(value) == 3 else None
    if v is None or not np.isfinite(v).all() or (positive and not (v > 0.0).all()):
        kind = "three finite numbers > 0" if positive else "three finite numbers"
        raise ValueError(f"{owner}.{name} must be {kind}, got {value!r}")


@dataclass(frozen=True)
class Ground:
    """A ground plane (a plane collider).

    Attributes:
        height: Plane offset along ``up`` (m).
        stiffness: Penalty stiffness per unit vertex mass (1/s^2); resting penetration is about g / stiffness.
        friction: Coulomb friction coefficient.
        up: Unit normal of the plane, pointing into the free half-space.
        offset: How far above the plane its penalty starts, as a share of the touching body's size (>= 0).
    """

    height: float = 0.0
    stiffness: float = 1.0e7
    friction: float = 0.5
    up: tuple[float, float, float] = (0.0, 1.0, 0.0)
    offset: float = STATIC_OFFSET

    def __post_init__(self) -> None:
        if not np.isfinite(self.height):
            raise ValueError(f"Ground.height must be a finite number of m, got {self.height}")
        check_vector("Ground", "up", self.up)
        if abs(np.linalg.norm(self.up) - 1.0) > 1.0e-6:
            raise ValueError(f"Ground.up must be a unit vector, got {self.up!r}")
        check_response("Ground", self.stiffness, self.friction, self.offset)


@dataclass(frozen=True)
class Sphere:
    """A sphere collider: ``center`` (m), ``radius`` (m), penalty ``stiffness`` (1/s^2), ``friction``.

    ``motion``: a rigid motion of it (about its centre, as the motion's pivot says), or None: it stays.
    ``offset``: as :class:`Ground`'s.
    """

    center: tuple[float, float, float]
    radius: float
    stiffness: float = 1.0e7
    friction: float = 0.5
    motion: Motion | None = None
    offset: float = STATIC_OFFSET

    def __post_init__(self) -> None:
        check_vector("Sphere", "center", self.center)
        if not (np.isfinite(self.radius) and self.radius > 0.0):
            raise ValueError(f"Sphere.radius must be > 0 m, got {self.radius}")
        check_response("Sphere", self.stiffness, self.friction, self.offset)


@dataclass(frozen=True)
class Box:
    """A box collider, axis-aligned at rest: ``center`` and ``half_extents`` (m), ``stiffness`` (1/s^2), ``friction``.

    ``motion``: a rigid motion of it (which may turn it), or None: it stays. ``offset``: as :class:`Ground`'s.
    """

    center: tuple[float, float, float]
    half_extents: tuple[float, float, float]
    stiffness: float = 1.0e7
    friction: float = 0.5
    motion: Motion | None = None
    offset: float = STATIC_OFFSET

    def __post_init__(self) -> None:
        check_vector("Box", "center", self.center)
        check_vector("Box", "half_extents", self.half_extents, positive=True)
        check_response("Box", self.stiffness, self.friction, self.offset)


@dataclass(frozen=True, eq=False)
class MeshCollider:
    """A triangle mesh collider, placed at rest by ``x -> rotation x + translation`` (m).

    A closed mesh pushes points out of its inside, an open one (a terrain) out from behind its faces, along
    their normals (faces wound counter-clockwise seen from the side points are kept on), up to
    :data:`OPEN_REACH` of its size behind them and not past its open edges. ``motion``: a rigid motion of the
    placed mesh, or None: it stays.

    Attributes:
        vertices: (n, 3) vertex positions in the mesh's own frame (m).
        faces: (m, 3) triangles.
        rotation: (3, 3) its rest rotation.
        translation: Its rest translation (m).
        stiffness: Penalty per unit mass (1/s^2).
        friction: Coulomb friction coefficient.
        motion: Its rigid motion, or None.
        closed: Whether it is closed (every edge shared by two faces).
        offset: As :class:`Ground`'s.
    """

    vertices: np.ndarray
    faces: np.ndarray
    rotation: np.ndarray = field(default_factory=lambda: np.eye(3))
    translation: tuple[float, float, float] = (0.0, 0.0, 0.0)
    stiffness: float = 1.0e7
    friction: float = 0.5
    motion: Motion | None = None
    closed: bool = True
    offset: float = STATIC_OFFSET

    def __post_init__(self) -> None:
        v, f = np.asarray(self.vertices), np.asarray(self.faces)
        if v.ndim != 2 or v.shape[1] != 3 or len(v) < 3 or not np.isfinite(v.astype(np.float64)).all():
            raise ValueError(f"MeshCollider.vertices must be (n >= 3, 3) finite positions, got shape {v.shape}")
        if f.ndim != 2 or f.shape[1] != 3 or len(f) == 0 or not np.issubdtype(f.dtype, np.integer):
            raise ValueError(f"MeshCollider.faces must be (m >= 1, 3) integer triangles, got {f.dtype} {f.shape}")
        if f.min() < 0 or f.max() >= len(v):
            raise ValueError(f"MeshCollider.faces index vertices 0..{len(v) - 1}, got {f.min()}..{f.max()}")
        r = np.asarray(self.rotation, np.float64)
        if r.shape != (3, 3) or not np.allclose(r @ r.T, np.eye(3), atol=1.0e-5) or np.linalg.det(r) <= 0.0:
            raise ValueError("MeshCollider.rotation must be a 3 x 3 rotation matrix")
        check_vector("MeshCollider", "translation", self.translation)
        check_response("MeshCollider", self.stiffness, self.friction, self.offset)


Collider = Ground | Sphere | Box | MeshCollider


def rest_pose(c: Collider) -> tuple[np.ndarray, np.ndarray]:
    """A collider's rest rotation (3x3) and translation: its own frame in the world at rest."""
    if isinstance(c, MeshCollider):
        return np.asarray(c.rotation, np.float64), np.asarray(c.translation, np.float64)
    if isinstance(c, Ground):
        return np.eye(3), np.zeros(3)
    return np.eye(3), np.asarray(c.center, np.float64)


def collider_pose(c: Collider, time: float) -> np.ndarray:
    """A collider's own frame in the world at ``time`` (s): the 4x4 matrix taking its points there (column vectors)."""
    r, t = rest_pose(c)
    motion = getattr(c, "motion", None)
    if motion is not None:
        mr, mt = motion.at(time)
        r, t = mr @ r, mr @ t + mt
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = r, t
    return pose


OPEN_REACH = 0.05
"""How far behind its faces an open mesh (a terrain) acts, as a fraction of its bounding-box diagonal: its
thickness. A closed mesh acts on its whole inside."""


def mesh_reach(c: MeshCollider) -> float:
    """How far behind its surface a mesh collider acts (m): a closed one's size, an open one's thickness."""
    diagonal = float(np.linalg.norm(np.ptp(np.asarray(c.vertices, np.float64), axis=0)))
    return diagonal if c.closed else OPEN_REACH * diagonal


def open_edge_flags(faces: np.ndarray) -> np.ndarray:
    """Per face: which of its edges no other face shares, and which of its corners lie on such an edge.

    Bits 0-2 flag the edges of corners 0-1, 1-2, 2-0; bits 3-5 corners 0-2.
    """
    faces = np.asarray(faces, np.int64)
    edges = np.sort(np.stack([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]], axis=1), axis=2).reshape(-1, 2)
    _, inverse, counts = np.unique(edges, axis=0, return_inverse=True, return_counts=True)
    lone = (counts[inverse.reshape(-1)] == 1).reshape(-1, 3)
    on_edge = np.zeros(faces.max() + 1, bool)
    for k, (a, b) in enumerate(((0, 1), (1, 2), (2, 0))):
        on_edge[faces[lone[:, k]][:, [a, b]]] = True
    flags = (lone * np.array([1, 2, 4])).sum(axis=1) + (on_edge[faces] * np.array([8, 16, 32])).sum(axis=1)
    return flags.astype(np.int32)


class StaticColliders:
    """Device arrays of the colliders (ground, spheres, boxes, meshes); one loop over them per point.

    ``arrays`` is the :class:`warpfem.kernels.integrate.Colliders` the kernels take; ``moving`` lists the
    moving colliders as ``(index, motion, rest rotation, rest translation)`` for :class:`~warpfem.sim.drive.Drive`.
    ``body_size``: each body's size (m; :attr:`Model.body_size <warpfem.sim.model.Model>`), which the colliders'
    offsets are shares of, read where it is. ``gravity``: the solver's
    one-element gravity array (m/s^2), read by the speculative contact test (None: no gravity).
    """

    def __init__(
        self, colliders: Sequence[Collider], device, body_size: wp.array, gravity: wp.array | None = None
    ) -> None:
        self.colliders = list(colliders)
        kind, center, rotation, size, response, meshes, self.moving = [], [], [], [], [], [], []
        face_start, open_edges = [], [np.zeros(0, np.int32)]
        self.meshes: list[wp.Mesh] = []
        for index, c in enumerate(colliders):
            face_start.append(sum(len(e) for e in open_edges))
            r, t = rest_pose(c)
            if isinstance(c, Ground):
                up = np.asarray(c.up, dtype=np.float64)
                up /= np.linalg.norm(up)
                kind.append(int(K.PLANE))
                t = c.height * up
                size.append(up)
            elif isinstance(c, Sphere):
                kind.append(int(K.SPHERE))
                size.append((c.radius, 0.0, 0.0))
            elif isinstance(c, Box):
                kind.append(int(K.BOX))
                size.append(c.half_extents)
            else:
                kind.append(int(K.MESH))
                v = np.asarray(c.vertices, np.float64)
                points = wp.array(v.astype(np.float32), dtype=wp.vec3, device=device)
                indices = wp.array(np.asarray(c.faces, np.int32).reshape(-1), dtype=wp.int32, device=device)
                mesh = wp.Mesh(points, indices)
                self.meshes.append(mesh)
                open_edges.append(open_edge_flags(c.faces))
                size.append((mesh_reach(c), 0.0, 0.0))
            meshes.append(self.meshes[-1].id if kind[-1] == int(K.MESH) else 0)
            center.append(t)
            rotation.append(quat_of_matrix(r))
            response.append((c.stiffness, c.friction, c.offset))
            if getattr(c, "motion", None) is not None:
                self.moving.append((index, c.motion, r, t))

        def arr(data, dtype, width):
            np_type = {wp.int32: np.int32, wp.uint64: np.uint64}.get(dtype, np.float32)
            shape = (len(kind), width) if width else (len(kind),)
            return wp.array(np.asarray(data, dtype=np_type).reshape(shape), dtype=dtype, device=device)

        a = K.Colliders()
        a.kind = arr(kind, wp.int32, 0)
        a.center, a.center_next = arr(center, wp.vec3, 3), arr(center, wp.vec3, 3)
        a.rotation, a.rotation_next = arr(rotation, wp.quat, 4), arr(rotation, wp.quat, 4)
        a.moving = arr([int(getattr(c, "motion", None) is not None) for c in colliders], wp.int32, 0)
        a.size = arr(size, wp.vec3, 3)
        a.response = arr(response, wp.vec3, 3)
        a.body_size = body_size
        a.mesh = arr(meshes, wp.uint64, 0)
        a.face_start = arr(face_start, wp.int32, 0)
        a.open_edges = wp.array(np.concatenate(open_edges).astype(np.int32), dtype=wp.int32, device=device)
        a.gravity = gravity if gravity is not None else wp.zeros(1, dtype=wp.vec3, device=device)
        self.arrays = a
        self.kind = a.kind
        moving = {index for index, *_ in self.moving}
        self.still_meshes = any(k == int(K.MESH) and o not in moving for o, k in enumerate(kind))
        """Whether some mesh collider does not move (what :func:`lift_points` has a launch of its own for)."""

    @property
    def poses(self) -> list[wp.array]:
        """The pose arrays a :class:`~warpfem.sim.drive.Drive` writes: centre, rotation, then at the step's end."""
        a = self.arrays
        return [a.center, a.rotation, a.center_next, a.rotation_next]


def clear_step(zeroed: list[wp.array], dim: int, device: wp.context.Device) -> None:
    """Zero a step's accumulators and counters in one launch, in ``kernels.integrate.clear_step``'s order.

    ``dim``: the longest of the arrays (worked out once by the caller, not on every step).
    """
    wp.launch(K.clear_step, dim=dim, inputs=zeroed, device=device)


def body_momentum(model: Model, state: State, momentum_out: wp.array) -> None:
    """Each body's momentum (kg m/s) added into ``momentum_out`` (zero it first): the static contacts' body speed."""
    wp.launch(
        K.body_momentum,
        dim=model.vertex_count,
        inputs=[state.v, model.mass, model.vertex_body],
        outputs=[momentum_out],
        device=model.device,
        block_dim=spread_block_dim(model.vertex_count, model.device),
    )


def build_system(
    model: Model,
    state: State,
    force: wp.array,
    gravity: wp.array,
    colliders: StaticColliders,
    dt: float,
    matrix_out: wp.array,
    rhs_out: wp.array,
    diag_inv_out: wp.array,
    v_guess_out: wp.array,
    direction_out: wp.array,
    momentum: wp.array,
    held_v: wp.array,
    elastic_force: wp.array,
    rhs_base_out: wp.array,
) -> None:
    """Complete the backward-Euler system for the new velocity (see :mod:`warpfem.kernels.integrate`).

    ``matrix_out`` must already hold the elastic blocks; mass, damping and static-collider terms are added to
    its diagonal. ``v_guess_out`` receives the CG start (the current velocity) and ``direction_out`` the direction
    CG moves it along first: ``state.dv``, the velocity change of the step that produced the state (zero on
    pinned vertices and where not finite). A held vertex starts, and stays, at its ``held_v`` (m/s; a handle's
    velocity this step), or at rest where ``held_v`` is empty. With ``elastic_force`` not empty (N), the elastic
    force kept apart from ``force``: the right-hand side without it goes to ``rhs_base_out`` (see
    :func:`add_elastic`); both empty where the elastic force is in ``force``.
    """
    wp.launch(
        K.build_system,
        dim=model.vertex_count,
        inputs=[
            state.x,
            state.v,
            model.mass,
            model.alpha,
            model.free,
            model.diag_slot,
            model.vertex_depth,
            force,
            elastic_force,
            gravity,
            colliders.arrays,
            held_v,
            state.dv,
            model.vertex_body,
            momentum,
            model.body_mass,
            dt,
        ],
        outputs=[matrix_out, rhs_out, diag_inv_out, v_guess_out, direction_out, rhs_base_out],
        device=model.device,
        block_dim=spread_block_dim(model.vertex_count, model.device),
    )


def late_contacts(
    model: Model,
    state: State,
    v_new: wp.array,
    colliders: StaticColliders,
    momentum: wp.array,
    dt: float,
    late: wp.array,
    count_out: wp.array,
    matrix_out: wp.array,
    rhs_out: wp.array,
    matrix_base_out: wp.array,
    rhs_base_out: wp.array,
    body_speed: wp.array,
) -> None:
    """Add to the system the static contacts on tet vertices that a solve's ``v_new`` crosses unseen.

    (See ``kernels.integrate.late_contact``; the skin's: :func:`warpfem.sim.skin.late_contacts`.) Also to the
    system without elasticity ``matrix_base_out`` and ``rhs_base_out`` where those are not empty. ``late``
    marks the tet vertices already given one this step (zero it at its start); ``count_out[0]`` counts those
    added. Each body's fastest vertex in ``v_new`` raises its entry of ``body_speed`` (where not empty).
    """
    wp.launch(
        K.late_vertex_contacts,
        dim=model.vertex_count,
        inputs=[state.x, state.v, v_new, model.mass, model.free, model.diag_slot, model.vertex_depth,
                colliders.arrays, model.vertex_body, momentum, model.body_mass, dt],
        outputs=[late, count_out, matrix_out, rhs_out, matrix_base_out, rhs_base_out, body_speed],
        device=model.device,
        block_dim=spread_block_dim(model.vertex_count, model.device),
    )  # fmt: skip


def lift_points(
    model: Model,
    state: State,
    colliders: StaticColliders,
    cell: wp.array,
    bary: wp.array,
    up: wp.array,
    down: wp.array,
) -> None:
    """Move the tet nodes so that no point embedded at ``bary`` in ``cell`` lies below a still collider's surface.

    Below it by more than ``kernels.integrate.LIFT_GIVE`` of its body's size, that is: the give a resting
    penalty needs. Two launches (the moves the points ask, then the nodes moved; a third for the still mesh
    colliders, where there are any); ``up`` and ``down`` are the per-node requests, zero between calls. A node
    moved against its velocity stops along the move (``kernels.integrate.apply_lift``), so a body pressed into
    the ground rests on it rather than bouncing.
    """
    dev = model.device
    for kernel in (K.lift_points, K.lift_points_meshes) if colliders.still_meshes else (K.lift_points,):
        wp.launch(
            kernel,
            dim=cell.shape[0],
            inputs=[state.x, model.cells, model.cell_body, model.free, cell, bary, colliders.arrays],
            outputs=[up, down],
            device=dev,
        )
    n = model.vertex_count
    wp.launch(
        K.apply_lift,
        dim=n,
        inputs=[up, down],
        outputs=[state.x, state.v, state.dv],
        device=dev,
        block_dim=spread_block_dim(n, dev),
    )


def add_elastic(
    model: Model,
    matrix_base: wp.array,
    elastic_matrix: wp.array,
    rhs_base: wp.array,
    elastic_force: wp.array,
    dt: float,
    matrix_out: wp.array,
    rhs_out: wp.array,
    diag_inv_out: wp.array,
    solving: wp.array,
) -> None:
    """The system with an elastic part kept apart: matrix, right-hand side and preconditioner from their bases.

    The elastic arrays are zeroed as they are read (the next assembly, of this step or the next, adds into
    them). ``solving``: as :func:`refresh_preconditioner`'s.
    """
    count = max(matrix_out.shape[0], model.vertex_count)
    wp.launch(
        K.add_elastic,
        dim=count,
        inputs=[model.free, matrix_base, rhs_base, dt],
        outputs=[elastic_matrix, elastic_force, matrix_out, rhs_out],
        device=model.device,
        block_dim=spread_block_dim(count, model.device),
    )
    refresh_preconditioner(model, matrix_out, diag_inv_out, solving)


def refresh_preconditioner(model: Model, matrix: wp.array, diag_inv_out: wp.array, solving: wp.array) -> None:
    """The inverse diagonal blocks of ``matrix`` again (after late contacts changed them).

    ``solving``: per body, which bodies a solve with them moves (zero blocks on the others); empty: all.
    """
    wp.launch(
        K.refresh_preconditioner,
        dim=model.vertex_count,
        inputs=[model.free, model.diag_slot, matrix, model.vertex_body, solving],
        outputs=[diag_inv_out],
        device=model.device,
        block_dim=spread_block_dim(model.vertex_count, model.device),
    )


def moving_bodies(model: Model, late: tuple[wp.array, wp.array], pairs: Pairs, moving_out: wp.array) -> None:
    """Mark in ``moving_out`` (per body, zeroed at the step's start) the bodies an extra solve of the step moves.

    Those a late static contact touched and those touching another body (``kernels.integrate.moving_bodies``);
    what else a solve moves (the bodies a rotation update re-linearised) is marked by its own launch.
    ``late``: the late static contacts' marks (tet vertices, skin points; empty: none); ``pairs``: CG's contact
    pairs (:attr:`~warpfem.sim.cg.CGSolver.pairs`; none without a collision stage).
    """
    dim = max(late[0].shape[0], late[1].shape[0], pairs.verts_a.shape[0], 1)
    wp.launch(
        K.moving_bodies,
        dim=dim,
        inputs=[late[0], model.vertex_body, late[1], model.skin_cell, model.cell_body, pairs.count, pairs.verts_a,
                pairs.verts_b],
        outputs=[moving_out],
        device=model.device,
        block_dim=spread_block_dim(dim, model.device),
    )  # fmt: skip


def advance_positions(
    model: Model,
    x: wp.array,
    v: wp.array,
    v_new: wp.array,
    dt: float,
    x_out: wp.array,
    dv_out: wp.array,
    bad_vertex_out: wp.array,
) -> None:
    """x_out = x + dt v_new and dv_out = v_new - v (the direction the next step's CG start moves along).

    The lowest index of a non-finite vertex goes to ``bad_vertex_out[0]`` (atomic min).
    """
    wp.launch(
        K.advance_positions,
        dim=model.vertex_count,
        inputs=[x, v, v_new, dt],
        outputs=[x_out, dv_out, bad_vertex_out],
        device=model.device,
        block_dim=spread_block_dim(model.vertex_count, model.device),
    )
