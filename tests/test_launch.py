"""Launch shapes: small launches spread over every SM in whole warps."""

from types import SimpleNamespace

import pytest
import warp as wp

from warpfem.sim.launch import spread_block_dim

H100 = SimpleNamespace(is_cuda=True, sm_count=132)


@pytest.mark.parametrize(
    ("count", "expected"),
    [
        (1, 32),  # never below a warp
        (1376, 32),  # paper scene C's tets: 11 per SM, one warp each
        (132 * 33, 32),  # 33 per SM: one warp each (two would leave SMs idle)
        (132 * 64, 64),  # 64 per SM: two warps
        (132 * 256, 256),  # a block of 256 on every SM
        (557_056, 256),  # 1024 armadillos' tets: Warp's default
    ],
)
def test_block_dim_spreads_small_launches(count, expected):
    dim = spread_block_dim(count, H100)
    assert dim == expected
    assert -(-count // dim) >= min(H100.sm_count, -(-count // 32))  # as many blocks as SMs, where whole warps allow


def test_block_dim_on_the_device(device):
    """On the CPU the default; on CUDA whole warps, at most 256."""
    dim = spread_block_dim(1376, device)
    if wp.get_device(device).is_cuda:
        assert dim % 32 == 0 and 32 <= dim <= 256
    else:
        assert dim == 256
