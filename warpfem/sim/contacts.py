"""Contact buffers shared by the collision stage (which fills them) and CG (which applies them)."""

from __future__ import annotations

from dataclasses import dataclass

import warp as wp


@dataclass(frozen=True)
class Coupling:
    """Pairs of points embedded in the mesh, coupled by 3x3 matrices (contacts): a matrix-free term of A.

    Pair c ties point a (``sum_k weights_a[k] x[verts_a[k]]``) to point b through ``C_c``: it adds
    ``J^T C_c J`` to A with ``J x = x_a - x_b``, less the diagonal blocks (``weights^2 C_c``, which the
    assembled matrix holds so that the preconditioner sees them). Only the first ``count[0]`` pairs (capped
    at the capacity) are live.

    Attributes:
        count: (1,) int32 live pairs.
        verts_a: (capacity,) vec4i vertices of point a. weights_a: (capacity,) vec4 its weights.
        verts_b: (capacity,) vec4i vertices of point b. weights_b: (capacity,) vec4 its weights.
        matrix: (capacity,) mat33 C_c (N s/m after the dt factors of the implicit step).
    """

    count: wp.array
    verts_a: wp.array
    weights_a: wp.array
    verts_b: wp.array
    weights_b: wp.array
    matrix: wp.array
