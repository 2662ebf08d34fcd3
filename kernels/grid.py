"""Synchronisation and reductions across threads: grid barriers, warp and lane-group sums, warp maxima.

A persistent launch keeps at most one block per SM resident for its whole life, and its blocks meet at
:func:`grid_total` instead of at kernel boundaries (see ``warpfem.kernels.cg.cg_solve``). On the CPU a
launch is one thread and these reduce to plain operations.
"""

import warp as wp

WARP_SUM = r"""
float v = value;
for (int offset = 16; offset > 0; offset >>= 1)
    v += __shfl_down_sync(0xffffffffu, v, offset);
"""
"""CUDA: ``v``, the sum of ``value`` over the warp, in its lane 0 (register shuffles, no shared memory)."""

GRID_TOTAL = (
    r"""
#if defined(__CUDA_ARCH__)
__shared__ float grid_total_shared;
unsigned long long* word = (unsigned long long*)words.data + slot;
"""
    + WARP_SUM
    + r"""
if ((threadIdx.x & 31) == 0)
    atomicAdd((float*)word, v);
__syncthreads();
if (threadIdx.x == 0) {
    unsigned long long seen = 0;
    if (gridDim.x > 1) {
        int spins = 0;
        asm volatile("red.release.gpu.global.add.u32 [%0], %1;" :: "l"((unsigned int*)word + 1), "r"(1) : "memory");
        do {
            asm volatile("ld.acquire.gpu.global.b64 %0, [%1];" : "=l"(seen) : "l"(word) : "memory");
            if (++spins > (1 << 24)) {
                atomicExch(stalled.data, 1);
                break;
            }
        } while ((unsigned int)(seen >> 32) < (unsigned int)blocks);
    } else {
        seen = *((volatile unsigned long long*)word);
    }
    grid_total_shared = __uint_as_float((unsigned int)(seen & 0xffffffffull));
}
__syncthreads();
return grid_total_shared;
#else
float* total = (float*)((unsigned long long*)words.data + slot);
*total += value;
return *total;
#endif
"""
)

WARP_SUM_ADD = (
    r"""
#if defined(__CUDA_ARCH__)
"""
    + WARP_SUM
    + r"""
if ((threadIdx.x & 31) == 0)
    atomicAdd(totals.data + slot, v);
#else
totals.data[slot] += value;
#endif
"""
)

LOAD_COHERENT = r"""
#if defined(__CUDA_ARCH__)
return *((volatile float*)values.data + index);
#else
return values.data[index];
#endif
"""


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


@wp.func_native(GRID_TOTAL)
def grid_total(
    value: float, words: wp.array(dtype=wp.uint64), slot: int, blocks: int, stalled: wp.array(dtype=wp.int32)
) -> float:
    """The sum of ``value`` over every thread of a persistent launch of ``blocks`` blocks, returned to all.

    Also the grid barrier: it returns once every block has arrived, and what a block wrote before it is
    visible after it. ``words[slot]`` (zeroed before; one slot per call) holds the float sum in its low 32
    bits (one atomic add per warp) and the arrival count in its high 32; each block's thread 0 arrives with a
    release add and spins on acquire loads that read count and sum at once, so the sum costs no extra round
    trip. All blocks must be resident (at most one per SM; one block needs only the block barrier). After
    ~2^24 polls it sets ``stalled[0]`` and goes on rather than hang the device. On the CPU it adds ``value``
    to the slot and returns it.
    """
    ...


QUAD_SUM = r"""
#if defined(__CUDA_ARCH__)
unsigned int group = 0xfu << (threadIdx.x & 28);
float x = value.c[0];
float y = value.c[1];
float z = value.c[2];
for (int offset = 2; offset > 0; offset >>= 1) {
    x += __shfl_xor_sync(group, x, offset);
    y += __shfl_xor_sync(group, y, offset);
    z += __shfl_xor_sync(group, z, offset);
}
return wp::vec3(x, y, z);
#else
return value;
#endif
"""


@wp.func_native(QUAD_SUM)
def quad_sum(value: wp.vec3) -> wp.vec3:
    """The sum of ``value`` over the caller's group of four lanes (lanes 4g to 4g + 3 of its warp), to each.

    Register shuffles; the four lanes must reach it together (the others of the warp need not). The block
    size must be a multiple of 32. On the CPU, where a launch is one thread, it returns ``value``.
    """
    ...


WARP_SUM_AT = r"""
wp::vec3* slot = wp::address(totals, key);
#if defined(__CUDA_ARCH__)
unsigned int lanes = __activemask();
if (lanes == 0xffffffffu && __all_sync(lanes, key == __shfl_sync(lanes, key, 0))) {
    float x = value[0], y = value[1], z = value[2];
    for (int offset = 16; offset > 0; offset >>= 1) {
        x += __shfl_xor_sync(lanes, x, offset);
        y += __shfl_xor_sync(lanes, y, offset);
        z += __shfl_xor_sync(lanes, z, offset);
    }
    if ((threadIdx.x & 31) == 0)
        wp::atomic_add(slot, wp::vec3(x, y, z));
    return;
}
#endif
wp::atomic_add(slot, value);
"""


@wp.func_native(WARP_SUM_AT)
def warp_sum_at(value: wp.vec3, key: int, totals: wp.array(dtype=wp.vec3)):
    """``totals[key] += value``, one atomic per warp where the whole warp shares ``key`` (register shuffles).

    Threads adding into a few slots serialise there; other warps, and the CPU, add per thread.
    """
    ...


WARP_MAX_AT = r"""
float* slot = wp::address(maxima, key);
#if defined(__CUDA_ARCH__)
unsigned int lanes = __activemask();
if (lanes == 0xffffffffu && __all_sync(lanes, key == __shfl_sync(lanes, key, 0))) {
    float m = value;
    for (int offset = 16; offset > 0; offset >>= 1)
        m = fmaxf(m, __shfl_xor_sync(lanes, m, offset));
    if ((threadIdx.x & 31) == 0 && m > *slot)
        wp::atomic_max(slot, m);
    return;
}
#endif
if (value > *slot)
    wp::atomic_max(slot, value);
"""


@wp.func_native(WARP_MAX_AT)
def warp_max_at(value: float, key: int, maxima: wp.array(dtype=float)):
    """``maxima[key] = max(maxima[key], value)``, one atomic per warp where the whole warp shares ``key``.

    A full warp of one key takes its maximum with register shuffles and its lane 0 alone reads the slot and
    adds (a launch's threads hammering a few slots serialise there); other warps, and the CPU, do it per
    thread, each only when its value is above what the slot already holds.
    """
    ...
