"""Host side of the skin's static contacts: the dense vertices outside the coarse tets against the colliders.

Each stage is two launches (``kernels.skin``): a light one over every skin point lists those a collider can
reach within the step, and the contact's own kernel runs over that list, in a grid the device keeps resident
(the list's length is known on the device only).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import warp as wp

from warpfem.kernels import skin as K
from warpfem.sim.launch import resident_blocks
from warpfem.sim.model import Model, State

if TYPE_CHECKING:
    from warpfem.sim.integrate import StaticColliders


def skin_colliders(
    model: Model,
    state: State,
    colliders: StaticColliders,
    momentum: wp.array,
    dt: float,
    force_out: wp.array,
    matrix_out: wp.array,
    clear_out: wp.array,
    skin_list: tuple[wp.array, wp.array],
) -> None:
    """Add the static colliders' penalty and friction on the model's skin points to the forces and the matrix.

    None where there are no skin points or colliders. Each point's clearance from the colliders goes to
    ``clear_out`` where it is not empty (what lets a late pass leave it out: ``kernels.skin.skin_colliders``).
    ``skin_list``: a count, zero before the call, and room for every skin point (what the launches list).
    """
    count = model.skin_cell.shape[0]
    if count == 0 or colliders.kind.shape[0] == 0:
        return
    listed, listing = skin_list
    common = [model.skin_cell, model.skin_bary]
    wp.launch(
        K.skin_reach,
        dim=count,
        inputs=[state.x, state.v, model.cells, *common, model.cell_body, momentum, model.body_mass,
                colliders.arrays, dt],
        outputs=[listed, listing, clear_out],
        device=model.device,
    )  # fmt: skip
    wp.launch(
        K.skin_colliders,
        dim=count,
        inputs=[listed, listing, state.x, state.v, model.cells, model.cell_slots, *common, model.skin_mass,
                model.cell_body, momentum, model.body_mass, colliders.arrays, dt],
        outputs=[force_out, matrix_out, clear_out],
        device=model.device,
        max_blocks=resident_blocks(model.device),
    )  # fmt: skip


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
    clear: wp.array,
    body_speed: wp.array,
    skin_list: tuple[wp.array, wp.array],
) -> None:
    """Add to the system the static contacts on skin points that a solve's ``v_new`` crosses unseen.

    As :func:`warpfem.sim.integrate.late_contacts` does for the tet vertices (run that first: it sets
    ``body_speed``, each body's fastest vertex in the step's answers so far). ``late`` marks the skin points
    already given one this step. ``clear``: their clearances from this step's :func:`skin_colliders`; the
    points the bodies' speeds cannot carry to a collider are left out (none where ``clear`` is empty).
    ``skin_list``: a count, zero before the call, and room for every skin point.
    """
    count = model.skin_cell.shape[0]
    if count == 0 or colliders.kind.shape[0] == 0:
        return
    listed, listing = skin_list
    wp.launch(
        K.list_late_skin,
        dim=count,
        inputs=[late, model.skin_cell, model.cell_body, dt, clear, body_speed],
        outputs=[listed, listing],
        device=model.device,
    )
    wp.launch(
        K.late_skin_contacts,
        dim=count,
        inputs=[listed, listing, state.x, state.v, v_new, model.cells, model.cell_slots, model.free,
                model.skin_cell, model.skin_bary, model.skin_mass, model.cell_body, momentum, model.body_mass,
                colliders.arrays, dt],
        outputs=[late, count_out, matrix_out, rhs_out, matrix_base_out, rhs_base_out],
        device=model.device,
        max_blocks=resident_blocks(model.device),
    )  # fmt: skip
