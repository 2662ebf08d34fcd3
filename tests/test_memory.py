"""The memory estimate of a mesh obstacle, against what Warp allocates for it on the CPU (glibc's heap count)."""

from __future__ import annotations

import ctypes
import ctypes.util
import gc

import numpy as np
import pytest
import trimesh

from warpfem import memory


class _MallInfo2(ctypes.Structure):
    _fields_ = [
        (name, ctypes.c_size_t)
        for name in ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks", "fsmblks", "uordblks", "fordblks")
    ] + [("keepcost", ctypes.c_size_t)]


def _heap_in_use():
    """A function returning the bytes malloc has handed out and not taken back (None without glibc's mallinfo2)."""
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallinfo2 = libc.mallinfo2
    except (OSError, AttributeError):
        return None
    mallinfo2.restype = _MallInfo2

    def in_use() -> int:
        info = mallinfo2()
        return info.uordblks + info.hblkhd

    return in_use


@pytest.mark.skipif(_heap_in_use() is None, reason="needs glibc's mallinfo2 to count the heap")
def test_a_mesh_obstacle_is_counted_at_least_as_warp_allocates_it():
    """Warp's CPU arrays live on the C heap: building the colliders of a 327,680-triangle mesh obstacle keeps
    at most what the estimate counts for it, and at least 1/1.75 of it (the estimate also holds the tree build's
    temporaries and the node counts of a CUDA build: 60 of its 176 bytes per triangle)."""
    import warp as wp

    from warpfem.sim.integrate import MeshCollider, StaticColliders

    in_use = _heap_in_use()
    ball = trimesh.creation.icosphere(subdivisions=7)
    vertices, faces = np.asarray(ball.vertices), np.asarray(ball.faces)
    obstacle = MeshCollider(vertices, faces, closed=True)
    wp.init()
    size = wp.array([1.0], dtype=float, device="cpu")
    StaticColliders([MeshCollider(np.eye(3), np.array([[0, 1, 2]]))], "cpu", size)  # Warp's first use allocates too
    gc.collect()  # nothing of earlier tests freed while counting
    gc.disable()
    try:
        before = in_use()
        colliders = StaticColliders([obstacle], "cpu", size)
        kept = in_use() - before
    finally:
        gc.enable()
    need = memory.estimate([], [], [], False, obstacle_meshes=[(len(vertices), len(faces))]).parts["obstacles"]
    assert colliders.meshes and kept <= need <= 1.75 * kept, (kept, need)


@pytest.mark.parametrize("quadratic", (False, True))
def test_the_estimate_counts_the_nodes_and_blocks_the_model_allocates(quadratic):
    """Tet vertices (with quadratic tets, the edge nodes too) and stored matrix blocks, counted by the estimate
    from the tets alone, are what the built model holds."""
    from warpfem.build import add_body
    from warpfem.prep.shapes import box_tet_mesh
    from warpfem.sim.model import ModelBuilder

    V, T = box_tet_mesh((0, 0, 0), (0.4, 0.2, 0.1), (4, 2, 1))
    b = ModelBuilder()
    add_body(b, "box", V, T, 1e6, 0.3, 1000.0, quadratic=quadratic)
    model = b.finalize("cpu")
    parts = memory.estimate([T], [0], [0], False, quadratic=quadratic).parts
    assert parts["tet vertices"] == memory.VERTEX_BYTES * model.vertex_count
    gather = memory.BLOCK_BYTES + memory.GATHER_BLOCK_BYTES
    assert parts["matrix"] == gather * model.nnz_blocks
    extra = memory.QUADRATIC_TET_BYTES if quadratic else 0
    assert parts["tets"] == (memory.TET_BYTES + extra) * len(T)
