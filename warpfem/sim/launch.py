"""Launch shapes shared by the host stages, from a fixed set so that no scene compiles a module of its own."""

from __future__ import annotations

import warp as wp

WARP_THREADS = 32
"""Threads of a CUDA warp: block sizes are multiples of it."""

WIDE_BLOCK = 256
"""Threads per block of a launch large enough to fill the device (Warp's default)."""

DIRECT_BODIES = 16
"""Scenes of at most this many bodies: contact detection tests each collision point against every body's box
itself instead of querying a ``wp.Bvh`` of them, whose traversal stack costs shared memory in every block of
the detection launch and whose refit is a launch of its own each step. Larger scenes store their collision and
skin points in space order on CUDA (``warpfem.sim.model.ModelBuilder.finalize``; docs/decisions.md)."""

CARRY_BODIES = 64
"""Scenes of more than this many bodies start a frame's later steps from the step before's contacts (the
carried look) instead of a look at every collision point: it pays where that look walks millions of points,
and costs smaller scenes, whose full look is cheaper than the carried contacts' walks and dense queries
(measured in docs/decisions.md, "Start contacts the step before already had")."""

SPREAD_BLOCKS = (WARP_THREADS, WIDE_BLOCK)
"""The block sizes :func:`spread_block_dim` chooses from. Warp compiles a module once per block size it is
launched with, so a size that followed the scene's would compile again for a scene of another size; the
modules of the spread launches are compiled (and loaded) in both sizes instead (docs/decisions.md)."""


def spread_block_dim(count: int, device) -> int:
    """Threads per block (one of :data:`SPREAD_BLOCKS`) that spread a launch of ``count`` threads over every SM.

    In blocks of 256 a small launch runs on a handful of SMs, whose issue of its loads and atomic adds, not
    the memory, sets its time; blocks of one warp put work on every SM where the count allows. Below 256
    threads per SM every block of a warp is resident at once (an SM holds 32 blocks), so a single warp per
    block costs no occupancy; from 256 per SM on, the default. The CPU ignores it. Meant for launches whose
    threads issue many loads or atomic adds of their own (elastic forces, the system's rows); contact
    detection has a size of its own (``warpfem.sim.collision.DETECT_BLOCK``), set by its registers.

    Args:
        count: Threads of the launch.
        device: A Warp device or its name (anything with ``is_cuda`` and ``sm_count`` is taken as it is).
    """
    if not hasattr(device, "is_cuda"):
        device = wp.get_device(device)
    if not device.is_cuda or int(count) >= device.sm_count * WIDE_BLOCK:
        return WIDE_BLOCK
    return WARP_THREADS


SM_THREADS = 2048
"""Threads a multiprocessor keeps resident at most (sm_80, sm_90)."""


def resident_blocks(device, block_dim: int = WIDE_BLOCK) -> int:
    """``max_blocks`` for a launch sized by a buffer's capacity whose threads past a device-side count leave at once.

    Warp then runs the kernel as a grid-stride loop over at most as many blocks as the device keeps resident,
    so the threads past the count cost a loop test each instead of a block of their own: a buffer of millions
    of slots holding thousands of entries would otherwise spend its time launching empty blocks. 0 (no cap)
    off CUDA, where the launch is a loop anyway.
    """
    if not hasattr(device, "is_cuda"):
        device = wp.get_device(device)
    if not device.is_cuda:
        return 0
    return device.sm_count * max(1, SM_THREADS // block_dim)
