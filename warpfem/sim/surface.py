"""Each body's dense surface at rest as a ``wp.Mesh``, for the exact depth of contacts near the surface.

Copies of one prepared body (a pile: the same mesh moved, turned and scaled) share one mesh; each body
keeps the similarity that takes its rest shape to that mesh's frame (:class:`warpfem.kernels.surface.VisibleSurface`).
"""

from __future__ import annotations

import hashlib

import numpy as np
import warp as wp

from warpfem.kernels.surface import VisibleSurface
from warpfem.sim.model import Model

REACH = 0.1
"""How far from a point the depth query looks, as a fraction of the body's size: a point in a tet on the
surface lies closer than that to the dense surface unless the coarse cage stands farther off (then the
face lattice's depth answers)."""

COPY_TOLERANCE = 1.0e-6
"""Largest rest-position mismatch, as a fraction of the body's size, for two bodies to share one mesh."""


def visible_surface(model: Model, offset: float = 0.0) -> tuple[VisibleSurface, list[wp.Mesh]]:
    """The model's :class:`VisibleSurface` and the meshes it names (keep them alive with it).

    ``offset`` (m): what a contact in a body with a dense surface adds to its depth, capped by the cage's margin
    (``kernels.surface.contact_offset``): with the collision points' lift, how far outside that surface a contact
    of a point on another body's surface starts.
    """
    dev = model.device
    rest, tets = model.rest_x.numpy().astype(np.float64), model.tets.numpy()
    cells, dense_cell = model.cells.numpy(), model.dense_cell.numpy()
    dense_bary = model.dense_bary.numpy().astype(np.float64)
    per_tet = len(cells) // len(tets)
    meshes: list[wp.Mesh] = []
    first: dict[bytes, tuple[int, np.ndarray]] = {}  # shape -> (its mesh, the first such body's rest tet vertices)
    mesh_of, to_mesh, origin, scale, reach = [], [], [], [], []
    for b in model.bodies:
        frame = (np.eye(3), np.zeros(3), 1.0)
        x = rest[b.vertex_start : b.vertex_start + b.vertex_count]
        body_tets = tets[b.tet_start : b.tet_start + b.tet_count] - b.vertex_start
        embed = slice(b.dense_start, b.dense_start + b.dense_count)
        if len(b.dense_faces) == 0 or b.dense_count == 0:
            mesh_of.append(0)
        else:
            key = _shape_key(body_tets, b.dense_faces, dense_cell[embed] - per_tet * b.tet_start, dense_bary[embed])
            copy = _similarity(first[key][1], x, b.size) if key in first else None
            if copy is None:
                dense = np.einsum("nk,nkd->nd", dense_bary[embed], rest[cells[dense_cell[embed]]])
                points = wp.array(dense.astype(np.float32), dtype=wp.vec3, device=dev)
                faces = wp.array(np.asarray(b.dense_faces, np.int32).reshape(-1), dtype=wp.int32, device=dev)
                meshes.append(wp.Mesh(points=points, indices=faces))
                first.setdefault(key, (meshes[-1].id, x))
                mesh_of.append(meshes[-1].id)
            else:
                frame = copy
                mesh_of.append(first[key][0])
        to_mesh.append(frame[0])
        origin.append(frame[1])
        scale.append(frame[2])
        reach.append(REACH * b.size / frame[2])
    s = VisibleSurface()
    s.rest_x, s.dm_inv, s.tet_body = model.rest_x, model.dm_inv, model.tet_body
    s.mesh = wp.array(np.array(mesh_of, np.uint64), dtype=wp.uint64, device=dev)
    s.to_mesh = wp.array(np.array(to_mesh, np.float32), dtype=wp.mat33, device=dev)
    s.mesh_origin = wp.array(np.array(origin, np.float32), dtype=wp.vec3, device=dev)
    s.mesh_scale = wp.array(np.array(scale, np.float32), dtype=float, device=dev)
    s.reach = wp.array(np.array(reach, np.float32), dtype=float, device=dev)
    s.offset = float(offset)  # applied to bodies with a dense surface only (kernels.surface.visible_depth)
    return s, meshes


def _shape_key(*arrays: np.ndarray) -> bytes:
    """A digest of what two copies of one prepared body have in common: tets, dense faces and embedding."""
    h = hashlib.blake2b(digest_size=16)
    for a in arrays:
        h.update(np.ascontiguousarray(a).tobytes())
    return h.digest()


def _similarity(ref: np.ndarray, x: np.ndarray, size: float) -> tuple[np.ndarray, np.ndarray, float] | None:
    """``(A, c, s)`` with ``A x + c = ref`` (A a rotation over s) if ``x`` is ``ref`` moved, turned and scaled."""
    mr, mx = ref.mean(axis=0), x.mean(axis=0)
    u, sv, vt = np.linalg.svd((ref - mr).T @ (x - mx))
    d = np.sign(np.linalg.det(u @ vt))
    rot = (u @ np.diag([1.0, 1.0, d]) @ vt).T  # x - mx = s rot (ref - mr)
    s = (sv * [1.0, 1.0, d]).sum() / ((ref - mr) ** 2).sum()
    if s <= 0.0 or np.abs(s * (ref - mr) @ rot.T + mx - x).max() > COPY_TOLERANCE * size:
        return None
    a = rot.T / s
    return a, mr - a @ mx, s
