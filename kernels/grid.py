"""Device-wide synchronisation for persistent launches: a grid barrier, warp sums and coherent loads.

A persistent launch keeps at most one block per SM resident for its whole life, and its blocks meet at
:func:`grid_sync` instead of at kernel boundaries (see ``warpfem.kernels.cg.cg_solve``). On the CPU a
launch is one thread and these reduce to plain operations.
"""

import warp as wp

GRID_SYNC = r"""
#if defined(__CUDA_ARCH__)
__syncthreads();
if (gridDim.x > 1 && threadIdx.x == 0) {
    int* counter = barrier.data;
    int seen = 0;
    int spins = 0;
    asm volatile("red.release.gpu.global.add.s32 [%0], %1;" :: "l"(counter), "r"(1) : "memory");
    do {
        asm volatile("ld.acquire.gpu.global.s32 %0, [%1];" : "=r"(seen) : "l"(counter) : "memory");
        if (++spins > (1 << 24)) {
            atomicExch(stalled.data, 1);
            break;
        }
    } while (seen < target);
}
__syncthreads();
#endif
"""

WARP_SUM_ADD = r"""
#if defined(__CUDA_ARCH__)
float v = value;
for (int offset = 16; offset > 0; offset >>= 1)
    v += __shfl_down_sync(0xffffffffu, v, offset);
if ((threadIdx.x & 31) == 0)
    atomicAdd(totals.data + slot, v);
#else
totals.data[slot] += value;
#endif
"""

LOAD_COHERENT = r"""
#if defined(__CUDA_ARCH__)
return *((volatile float*)values.data + index);
#else
return values.data[index];
#endif
"""


@wp.func_native(GRID_SYNC)
def grid_sync(barrier: wp.array(dtype=wp.int32), target: int, stalled: wp.array(dtype=wp.int32)):
    """Grid-wide barrier of a persistent launch: returns once ``barrier[0]`` reaches ``target``.

    Every block's thread 0 arrives (an atomic add with release semantics: the block's writes before the
    block barrier are visible before it) and spins on loads with acquire semantics (what other blocks wrote
    before arriving is visible after it), lighter than full fences around a relaxed atomic; the counter
    only grows, so the n-th barrier of a launch of B blocks waits for n B arrivals. All blocks must be
    resident at once (the host launches at most one block per SM); a launch of one block needs only the
    block barrier. A barrier that waits for ~2^24 polls sets ``stalled[0]`` and lets its block go on rather
    than hang the device. A no-op on the CPU, where a launch is one thread.
    """
    ...


@wp.func_native(WARP_SUM_ADD)
def warp_sum_add(value: float, totals: wp.array(dtype=float), slot: int):
    """Add ``value`` of every thread into ``totals[slot]``, one atomic per warp of 32.

    A register shuffle sum per warp (no shared memory, no block barrier). Every thread of the warp must
    reach it.
    """
    ...


@wp.func_native(LOAD_COHERENT)
def load_coherent(values: wp.array(dtype=float), index: int) -> float:
    """``values[index]`` read from the device's shared cache (not a stale per-SM copy), after a barrier."""
    ...


@wp.func
def grid_total(
    value: float,
    totals: wp.array(dtype=float),
    slot: int,
    barrier: wp.array(dtype=wp.int32),
    target: int,
    stalled_out: wp.array(dtype=wp.int32),
) -> float:
    """The sum of ``value`` over every thread of the launch, returned to all (``totals[slot]`` zeroed before).

    One atomic per warp, then the grid barrier ``target``: also orders every write before it.
    """
    warp_sum_add(value, totals, slot)
    grid_sync(barrier, target, stalled_out)
    return load_coherent(totals, slot)
