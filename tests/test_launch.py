"""Launch shapes: small launches spread over every SM in whole warps."""

from types import SimpleNamespace

import pytest
import warp as wp

from warpfem.sim.launch import SPREAD_BLOCKS, spread_block_dim

H100 = SimpleNamespace(is_cuda=True, sm_count=132)


@pytest.mark.parametrize(
    ("count", "expected"),
    [
        (1, 32),  # never below a warp
        (1376, 32),  # paper scene C's tets: 11 per SM, one warp each
        (132 * 33, 32),  # 33 per SM: one warp each (two would leave SMs idle)
        (132 * 64, 32),  # 64 per SM: two blocks of one warp each, both resident
        (132 * 256 - 1, 32),  # just under a block of 256 per SM
        (132 * 256, 256),  # a block of 256 on every SM
        (557_056, 256),  # 1024 armadillos' tets: Warp's default
    ],
)
def test_block_dim_spreads_small_launches(count, expected):
    dim = spread_block_dim(count, H100)
    assert dim == expected
    assert -(-count // dim) >= min(H100.sm_count, -(-count // 32))  # as many blocks as SMs, where whole warps allow


def test_block_dims_come_from_a_fixed_set():
    """Any launch size, on a GPU of any SM count, gets one of the block sizes the modules are compiled for."""
    for sms in (1, 46, 132, 144):
        gpu = SimpleNamespace(is_cuda=True, sm_count=sms)
        for count in (1, 31, 33, 1000, 4095, 8449, 20_000, 33_791, 33_792, 10**6):
            dim = spread_block_dim(count, gpu)
            assert dim in SPREAD_BLOCKS
            # blocks on min(SMs, warps) SMs at least, and at most 8 warps of a block size below the default per SM
            assert -(-count // dim) >= min(sms, -(-count // 32))
            assert dim == 256 or -(-count // dim) <= 8 * sms


def test_block_dim_on_the_device(device):
    """On the CPU the default; on CUDA whole warps, at most 256."""
    dim = spread_block_dim(1376, device)
    if wp.get_device(device).is_cuda:
        assert dim in SPREAD_BLOCKS
    else:
        assert dim == 256
