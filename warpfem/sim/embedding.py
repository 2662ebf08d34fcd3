"""Mapping the dense meshes through the tets: each dense vertex a barycentric combination of its cell's nodes."""

from __future__ import annotations

import warp as wp

from warpfem.kernels import embedding as K


def map_dense(
    cells: wp.array,
    positions: wp.array,
    dense_cell: wp.array,
    dense_bary: wp.array,
    dense_out: wp.array,
) -> None:
    """Write the dense vertices as barycentric combinations of the current tet node positions.

    One launch over the dense points, on the device of ``positions``.

    Args:
        cells: (c,) ``wp.vec4i`` the model's cells (its tets, or quadratic tets' sub-tets: ``warpfem.sim.cells``).
        positions: (p,) ``wp.vec3`` current tet node positions (m).
        dense_cell: (n,) ``wp.int32`` cell of each dense vertex.
        dense_bary: (n,) ``wp.vec4`` barycentric coordinates of each dense vertex in its cell.
        dense_out: (n,) ``wp.vec3`` output dense vertex positions (m).
    """
    wp.launch(
        K.map_dense,
        dim=dense_out.shape[0],
        inputs=[cells, positions, dense_cell, dense_bary],
        outputs=[dense_out],
        device=positions.device,
    )
