"""Mapping the dense meshes through the tets: each dense vertex a barycentric combination of its tet's corners."""

from __future__ import annotations

import warp as wp

from warpfem.kernels import embedding as K


def map_dense(
    tets: wp.array,
    positions: wp.array,
    dense_tet: wp.array,
    dense_bary: wp.array,
    dense_out: wp.array,
) -> None:
    """Write the dense vertices as barycentric combinations of the current tet vertex positions.

    One launch over the dense points, on the device of ``positions``.

    Args:
        tets: (q,) ``wp.vec4i`` tets.
        positions: (p,) ``wp.vec3`` current tet vertex positions (m).
        dense_tet: (n,) ``wp.int32`` tet of each dense vertex.
        dense_bary: (n,) ``wp.vec4`` barycentric coordinates of each dense vertex in its tet.
        dense_out: (n,) ``wp.vec3`` output dense vertex positions (m).
    """
    wp.launch(
        K.map_dense,
        dim=dense_out.shape[0],
        inputs=[tets, positions, dense_tet, dense_bary],
        outputs=[dense_out],
        device=positions.device,
    )
