"""Device-wide synchronisation for persistent launches: grid barriers that also sum one or two values.

A persistent launch keeps at most one block per SM resident for its whole life, and its blocks meet at
:func:`grid_total` instead of at kernel boundaries (see ``warpfem.kernels.cg.cg_solve``). On the CPU a
launch is one thread and these reduce to plain operations.
"""

import warp as wp

GRID_TOTAL = r"""
#if defined(__CUDA_ARCH__)
__shared__ float grid_total_shared;
unsigned long long* word = (unsigned long long*)words.data + slot;
float v = value;  // the warp's sum in its lane 0: register shuffles, no shared memory
for (int offset = 16; offset > 0; offset >>= 1)
    v += __shfl_down_sync(0xffffffffu, v, offset);
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

GRID_TOTALS = r"""
#if defined(__CUDA_ARCH__)
__shared__ float grid_totals_shared[2];
unsigned long long* word = (unsigned long long*)words.data + slot;
float v = value.c[0];
float w = value.c[1];
for (int offset = 16; offset > 0; offset >>= 1) {
    v += __shfl_down_sync(0xffffffffu, v, offset);
    w += __shfl_down_sync(0xffffffffu, w, offset);
}
if ((threadIdx.x & 31) == 0) {
    atomicAdd((float*)word, v);
    atomicAdd((float*)(word + 1), w);
}
__syncthreads();
if (threadIdx.x == 0) {
    unsigned long long seen_v = 0, seen_w = 0;
    if (gridDim.x > 1) {
        int spins = 0;
        asm volatile("red.release.gpu.global.add.u32 [%0], %1;" :: "l"((unsigned int*)word + 1), "r"(1) : "memory");
        asm volatile("red.release.gpu.global.add.u32 [%0], %1;" :: "l"((unsigned int*)word + 3), "r"(1) : "memory");
        do {
            asm volatile("ld.acquire.gpu.global.v2.b64 {%0, %1}, [%2];"
                         : "=l"(seen_v), "=l"(seen_w) : "l"(word) : "memory");
            if (++spins > (1 << 24)) {
                atomicExch(stalled.data, 1);
                break;
            }
        } while ((unsigned int)(seen_v >> 32) < (unsigned int)blocks
                 || (unsigned int)(seen_w >> 32) < (unsigned int)blocks);
    } else {
        seen_v = ((volatile unsigned long long*)word)[0];
        seen_w = ((volatile unsigned long long*)word)[1];
    }
    grid_totals_shared[0] = __uint_as_float((unsigned int)(seen_v & 0xffffffffull));
    grid_totals_shared[1] = __uint_as_float((unsigned int)(seen_w & 0xffffffffull));
}
__syncthreads();
return wp::vec2(grid_totals_shared[0], grid_totals_shared[1]);
#else
float* total = (float*)((unsigned long long*)words.data + slot);
float* other = (float*)((unsigned long long*)words.data + slot + 1);
*total += value.c[0];
*other += value.c[1];
return wp::vec2(*total, *other);
#endif
"""


@wp.func_native(GRID_TOTAL)
def grid_total(
    value: float, words: wp.array(dtype=wp.uint64), slot: int, blocks: int, stalled: wp.array(dtype=wp.int32)
) -> float:
    """The sum of ``value`` over every thread of a persistent launch of ``blocks`` blocks, returned to all.

    Also the grid barrier: it returns once every block has arrived, and what a block wrote before it is
    visible after it. ``words[slot]`` (zeroed before; one slot per call) holds the sum in its low 32 bits (a
    float: one atomic add per warp of 32) and the blocks arrived in its high 32 bits. Each block's thread 0
    arrives with an atomic add with release semantics (the block's writes and sums before the block barrier
    are visible before it) and spins on 64-bit loads with acquire semantics that read the count and the sum
    at once: the sum costs no round trip to memory after the barrier. All blocks must be resident at once
    (the host launches at most one block per SM); a launch of one block needs only the block barrier. A
    barrier that waits for ~2^24 polls sets ``stalled[0]`` and lets its block go on rather than hang the
    device. On the CPU, where a launch is one thread, it adds ``value`` to the slot and returns it.
    """
    ...


@wp.func_native(GRID_TOTALS)
def grid_totals(
    value: wp.vec2, words: wp.array(dtype=wp.uint64), slot: int, blocks: int, stalled: wp.array(dtype=wp.int32)
) -> wp.vec2:
    """:func:`grid_total` of two values at once, in ``words[slot]`` and ``words[slot + 1]`` (``slot`` even).

    The two warp sums interleave their shuffles, and the arrival poll reads both words with one 128-bit
    load with acquire semantics (each word carries its own count: a word whose count is complete holds its
    whole sum), so the second sum costs no round trip to memory after the barrier. Each block arrives
    with an atomic add with release semantics on each count.
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
