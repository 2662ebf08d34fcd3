"""Launch shapes shared by the host stages."""

from __future__ import annotations

import warp as wp

WARP_THREADS = 32
"""Threads of a CUDA warp: block sizes are multiples of it."""

WIDE_BLOCK = 256
"""Threads per block of a launch large enough to fill the device (Warp's default)."""


def spread_block_dim(count: int, device) -> int:
    """Threads per block (32 to 256, whole warps) that spread a launch of ``count`` threads over every SM.

    In blocks of 256 a small launch runs on a handful of SMs, whose issue of its loads and atomic adds, not
    the memory, sets its time; smaller blocks put a block on every SM where the count allows. A launch of 256
    or more threads per SM keeps the default; the CPU ignores it. Meant for launches whose threads issue many
    loads or atomic adds of their own (elastic forces, the system's rows), not for tree walks, whose threads
    read the same nodes and gain from sharing an SM's cache.

    Args:
        count: Threads of the launch.
        device: A Warp device or its name (anything with ``is_cuda`` and ``sm_count`` is taken as it is).
    """
    if not hasattr(device, "is_cuda"):
        device = wp.get_device(device)
    if not device.is_cuda:
        return WIDE_BLOCK
    warps_per_sm = int(count) // (device.sm_count * WARP_THREADS)  # the most that still give every SM a block
    return min(WIDE_BLOCK, max(WARP_THREADS, warps_per_sm * WARP_THREADS))
