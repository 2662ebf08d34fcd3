"""Host side of the implicit Euler stage: static colliders, system assembly per vertex, position update."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import warp as wp

from warpfem.kernels import integrate as K
from warpfem.sim.launch import spread_block_dim
from warpfem.sim.model import Model, State


@dataclass(frozen=True)
class Ground:
    """A ground plane (a plane collider).

    Attributes:
        height: Plane offset along ``up`` (m).
        stiffness: Penalty stiffness per unit vertex mass (1/s^2); resting penetration is about g / stiffness.
        friction: Coulomb friction coefficient.
        up: Unit normal of the plane, pointing into the free half-space.
    """

    height: float = 0.0
    stiffness: float = 1.0e7
    friction: float = 0.5
    up: tuple[float, float, float] = (0.0, 1.0, 0.0)


@dataclass(frozen=True)
class Sphere:
    """A static sphere collider: ``center`` (m), ``radius`` (m), penalty ``stiffness`` (1/s^2), ``friction``."""

    center: tuple[float, float, float]
    radius: float
    stiffness: float = 1.0e7
    friction: float = 0.5


@dataclass(frozen=True)
class Box:
    """A static axis-aligned box collider: ``center`` and ``half_extents`` (m), ``stiffness`` (1/s^2), ``friction``."""

    center: tuple[float, float, float]
    half_extents: tuple[float, float, float]
    stiffness: float = 1.0e7
    friction: float = 0.5


class StaticColliders:
    """Device arrays of the static colliders (ground, spheres, boxes); one loop over them per vertex."""

    def __init__(self, colliders: Sequence[Ground | Sphere | Box], device) -> None:
        kind, center, size, response = [], [], [], []
        for c in colliders:
            if isinstance(c, Ground):
                up = np.asarray(c.up, dtype=np.float64)
                up /= np.linalg.norm(up)
                kind.append(int(K.PLANE))
                center.append(c.height * up)
                size.append(up)
            elif isinstance(c, Sphere):
                kind.append(int(K.SPHERE))
                center.append(c.center)
                size.append((c.radius, 0.0, 0.0))
            else:
                kind.append(int(K.BOX))
                center.append(c.center)
                size.append(c.half_extents)
            response.append((c.stiffness, c.friction))

        def arr(data, dtype, shape):
            return wp.array(
                np.asarray(data, dtype=np.float32 if dtype != wp.int32 else np.int32).reshape(shape),
                dtype=dtype,
                device=device,
            )

        n = len(kind)
        self.kind = arr(kind, wp.int32, (n,))
        self.center = arr(center, wp.vec3, (n, 3))
        self.size = arr(size, wp.vec3, (n, 3))
        self.response = arr(response, wp.vec2, (n, 2))


def body_momentum(model: Model, state: State, momentum_out: wp.array) -> None:
    """Each body's momentum (kg m/s) into ``momentum_out`` (zeroed here): the static contacts' body speed."""
    momentum_out.zero_()
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
) -> None:
    """Complete the backward-Euler system for the new velocity (see :mod:`warpfem.kernels.integrate`).

    ``matrix_out`` must already hold the elastic blocks; mass, damping and static-collider terms are added to
    its diagonal. ``v_guess_out`` receives the CG start (the current velocity) and ``direction_out`` the direction
    CG moves it along first: ``state.dv``, the velocity change of the step that produced the state (zero on
    pinned vertices and where not finite).
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
            gravity,
            colliders.kind,
            colliders.center,
            colliders.size,
            colliders.response,
            state.dv,
            model.vertex_body,
            momentum,
            model.body_mass,
            dt,
        ],
        outputs=[matrix_out, rhs_out, diag_inv_out, v_guess_out, direction_out],
        device=model.device,
        block_dim=spread_block_dim(model.vertex_count, model.device),
    )


def skin_colliders(
    model: Model,
    state: State,
    colliders: StaticColliders,
    momentum: wp.array,
    dt: float,
    force_out: wp.array,
    matrix_out: wp.array,
) -> None:
    """Add the static colliders' penalty and friction on the model's skin points to the forces and the matrix.

    A launch over the skin points (dense vertices outside the coarse tets), none where there are none.
    """
    count = model.skin_tet.shape[0]
    if count == 0 or colliders.kind.shape[0] == 0:
        return
    wp.launch(
        K.skin_colliders,
        dim=count,
        inputs=[
            state.x,
            state.v,
            model.tets,
            model.tet_slots,
            model.skin_tet,
            model.skin_bary,
            model.skin_mass,
            model.tet_body,
            momentum,
            model.body_mass,
            colliders.kind,
            colliders.center,
            colliders.size,
            colliders.response,
            dt,
        ],
        outputs=[force_out, matrix_out],
        device=model.device,
    )


def late_contacts(
    model: Model,
    state: State,
    v_new: wp.array,
    colliders: StaticColliders,
    momentum: wp.array,
    dt: float,
    late: tuple[wp.array, wp.array],
    count_out: wp.array,
    matrix_out: wp.array,
    rhs_out: wp.array,
) -> None:
    """Add to the system the static contacts that a solve's ``v_new`` crosses unseen (see ``kernels.integrate``).

    ``late`` marks the tet vertices and skin points already given one this step (zero them at its start);
    ``count_out[0]`` counts those added.
    """
    c = colliders
    wp.launch(
        K.late_vertex_contacts,
        dim=model.vertex_count,
        inputs=[state.x, state.v, v_new, model.mass, model.free, model.diag_slot, model.vertex_depth, c.kind,
                c.center, c.size, c.response, model.vertex_body, momentum, model.body_mass, dt],
        outputs=[late[0], count_out, matrix_out, rhs_out],
        device=model.device,
        block_dim=spread_block_dim(model.vertex_count, model.device),
    )  # fmt: skip
    if model.skin_tet.shape[0]:
        wp.launch(
            K.late_skin_contacts,
            dim=model.skin_tet.shape[0],
            inputs=[state.x, state.v, v_new, model.tets, model.tet_slots, model.free, model.skin_tet, model.skin_bary,
                    model.skin_mass, model.tet_body, momentum, model.body_mass, c.kind, c.center, c.size, c.response,
                    dt],
            outputs=[late[1], count_out, matrix_out, rhs_out],
            device=model.device,
        )  # fmt: skip


def refresh_preconditioner(model: Model, matrix: wp.array, diag_inv_out: wp.array) -> None:
    """The inverse diagonal blocks of ``matrix`` again (after late contacts changed them)."""
    wp.launch(
        K.refresh_preconditioner,
        dim=model.vertex_count,
        inputs=[model.free, model.diag_slot, matrix],
        outputs=[diag_inv_out],
        device=model.device,
        block_dim=spread_block_dim(model.vertex_count, model.device),
    )


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
