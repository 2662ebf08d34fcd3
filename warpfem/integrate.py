"""Host side of the implicit Euler stage: system assembly per vertex and the position update."""

from __future__ import annotations

import warp as wp

from warpfem.kernels import integrate as K
from warpfem.model import Model, State


def build_system(
    model: Model,
    state: State,
    force: wp.array,
    gravity: wp.array,
    up: wp.array,
    ground: wp.array,
    dt: float,
    matrix_out: wp.array,
    rhs_out: wp.array,
    diag_inv_out: wp.array,
    v_guess_out: wp.array,
) -> None:
    """Complete the backward-Euler system for the new velocity (see :mod:`warpfem.kernels.integrate`).

    ``matrix_out`` must already hold the elastic blocks; mass, damping and ground terms are added to its
    diagonal. ``v_guess_out`` receives the CG start (the current velocity; zero on pinned vertices).
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
            force,
            gravity,
            up,
            ground,
            dt,
        ],
        outputs=[matrix_out, rhs_out, diag_inv_out, v_guess_out],
        device=model.device,
    )


def advance_positions(model: Model, x: wp.array, v_new: wp.array, dt: float, x_out: wp.array, bad_vertex_out: wp.array):
    """x_out = x + dt v_new; the lowest index of a non-finite vertex goes to ``bad_vertex_out[0]`` (atomic min)."""
    wp.launch(
        K.advance_positions,
        dim=model.vertex_count,
        inputs=[x, v_new, dt],
        outputs=[x_out, bad_vertex_out],
        device=model.device,
    )
