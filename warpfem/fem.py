"""Host side of the corotational FEM stage: launches the per-tet force and stiffness kernel."""

from __future__ import annotations

import warp as wp

from warpfem.kernels import fem as K
from warpfem.model import Model


def elastic_forces_and_stiffness(
    model: Model, x: wp.array, dt: float, rotation_out: wp.array, force_out: wp.array, matrix_out: wp.array
) -> None:
    """Add every tet's corotational elastic force (N) and (dt^2 + dt beta) R K R^T to the outputs.

    ``force_out`` and ``matrix_out`` are accumulated into (zero them first); ``rotation_out`` receives each
    tet's rotation. One launch for all bodies.
    """
    wp.launch(
        K.elastic_forces_and_stiffness,
        dim=model.tet_count,
        inputs=[
            x,
            model.tets,
            model.dm_inv,
            model.rest_volume,
            model.tet_mu,
            model.tet_lambda,
            model.tet_beta,
            model.tet_slots,
            dt,
        ],
        outputs=[rotation_out, force_out, matrix_out],
        device=model.device,
    )
