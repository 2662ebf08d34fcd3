"""Memory a scene needs on its device, estimated before anything is allocated, and the memory free there.

The estimate adds up the arrays :class:`warpfem.sim.model.Model`, :class:`warpfem.sim.solver.Solver` (with its CG
workspace and collider) and :class:`warpfem.simulation.Simulation` allocate, from the preprocessed bodies'
sizes: per tet vertex (rest and initial state, two states, masses, forces, preconditioner, CG vectors),
per tet (indices, inverse rest matrix, rotation, matrix slots), per matrix block (a 3x3 float block of the
stored upper triangle and its column; blocks are counted exactly from the tets' edges), per dense vertex
(embedding and mapped position), for collisions per collision point, per contact slot and per tet (its
inverse edge matrix and tree nodes), and per vertex and triangle of each mesh obstacle (its ``wp.Mesh``).
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from warpfem.errors import InputError

if TYPE_CHECKING:
    from warpfem.prep.geometry import BodyGeometry
    from warpfem.prep.pipeline import PreparedBody
    from warpfem.scene import Scene

VERTEX_BYTES = 308
"""Device bytes per tet vertex: rest/initial x and v, 2 states (x, v, dv), mass, damping, pins, depth and gradient,
CSR row and diagonal slot, force, rhs, CG direction, inverse diagonal block, 5 CG vectors and zero ones,
collision gradient, body index, and the elastic force and right-hand side kept apart for rotation updates."""

TET_BYTES = 176
"""Device bytes per tet: indices, inverse rest matrix, volume, Lame and damping, body, surface bits,
16 matrix slots, rotation."""

QUADRATIC_TET_BYTES = 1096
"""More bytes per quadratic tet: its 6 edge nodes, the matrix slots of its 10 x 10 node blocks, and its 8 sub-tets
(nodes, 4 x 4 slots and body each: ``warpfem.sim.cells``)."""

BLOCK_BYTES = 115
"""Device bytes per stored 3x3 matrix block: the float block, its int32 column, its share of CG's chunk table, and
the elastic and other blocks kept apart for rotation updates."""

GATHER_BLOCK_BYTES = 18
"""More bytes per stored block where CG's product gathers (on CUDA up to ``warpfem.sim.cg.GATHER_MAX_ROWS`` rows;
counted there on the CPU too, an upper bound): the entries (column and slot, about 1.9 per stored block: the
block and its mirror) and their longer chunk table."""

DENSE_BYTES = 60
"""Device bytes per dense vertex at most: embedding cell and barycentric weights, mapped position, and where it is
a skin point, the skin point's cell, weights, mass and late-contact mark."""

POINT_BYTES = 40
"""Model bytes per collision point: tet, weights, anchors, body, mass (allocated even without collisions)."""

COLLIDER_POINT_BYTES = 28
"""Collider bytes per collision point: position, velocity, stiffness."""

COLLIDER_TET_BYTES = 36
"""Collider bytes per tet: inverse edge matrix."""

TREE_TET_BYTES = 32
"""Bytes per tet of the bodies' tet trees at most: under one 24-byte node box and half a 16-byte leaf (a
power of two of leaves of up to four tets)."""

TET_FACE_BYTES = 16
"""Model bytes per (tet, nearby surface face) pair: the face's vertex indices and its index (the contact depth
rule)."""

LATTICE_POINT_BYTES = 4
"""Model bytes per point of a surface face's lattice of depths below the visible surface (one float; a face has
``warpfem.kernels.distance.LATTICE_POINTS``)."""

CONTACT_BYTES = 140
"""Device bytes per contact slot: point, tet, weights, normal, depth, 3x3 block, the pair's vertices and weights."""

MESH_VERTEX_BYTES = 12
"""Device bytes per vertex of a mesh obstacle or a dense surface the collider queries: its float32 position."""

MESH_FACE_BYTES = 176
"""Device bytes per triangle of a mesh obstacle or queried dense surface at most: its indices and open-edge
flags, and Warp's ``wp.Mesh`` around it: the triangle's bounds (24), its tree (two nodes of 32, their
parents and counts, an index: 84) and the temporaries of the tree's build (52)."""

CONTACTS_PER_POINT = 2.0
"""Contact slots per collision point (the collider's default capacity)."""


@dataclass(frozen=True)
class Estimate:
    """Estimated device bytes of a scene, by part.

    Attributes:
        parts: Bytes per part: tets, tet vertices, matrix, dense vertices, collision.
    """

    parts: dict[str, int]

    @property
    def total(self) -> int:
        """All parts together (bytes)."""
        return sum(self.parts.values())

    def describe(self) -> str:
        """The parts as ``tets 1.2 MB, ...``."""
        return ", ".join(f"{name} {format_bytes(size)}" for name, size in self.parts.items())


def format_bytes(size: int | float) -> str:
    """A byte count in B, kB, MB, GB or TB (powers of 1000), e.g. ``'18.4 MB'``."""
    for unit in ("B", "kB", "MB", "GB"):
        if abs(size) < 1000:
            return f"{size:.0f} {unit}" if unit == "B" else f"{size:.1f} {unit}"
        size /= 1000
    return f"{size:.1f} TB"


def matrix_blocks(elements: np.ndarray) -> int:
    """Stored blocks of the 3x3-block stiffness matrix of a mesh of (q, k)-node elements (its upper triangle).

    One per node and one per pair of nodes that share an element.
    """
    elements = np.asarray(elements, dtype=np.int64)
    if elements.size == 0:
        return 0
    k = elements.shape[1]
    a, b = np.triu_indices(k, 1)
    lo = np.minimum(elements[:, a], elements[:, b]).ravel()
    hi = np.maximum(elements[:, a], elements[:, b]).ravel()
    pairs = np.unique(lo * (int(elements.max()) + 1) + hi).size
    return int(np.unique(elements).size) + pairs


def quadratic_elements(tets: np.ndarray) -> np.ndarray:
    """The (q, 10) nodes of quadratic tets on a (q, 4) tet mesh: its corners, then its edge nodes.

    The edge nodes are numbered as the model numbers them (:func:`warpfem.sim.model.quadratic_nodes`).
    """
    from warpfem.sim.model import quadratic_nodes

    tets = np.asarray(tets, dtype=np.int64).reshape(-1, 4)
    if len(tets) == 0:
        return np.zeros((0, 10), dtype=np.int64)
    _, edges = quadratic_nodes(np.zeros((int(tets.max()) + 1, 3)), tets)
    return np.concatenate([tets, edges], axis=1)


def estimate(
    tets: Sequence[np.ndarray],
    dense_vertices: Sequence[int],
    collision_points: Sequence[int],
    collision: bool,
    tet_face_refs: Sequence[int] = (),
    surface_faces: Sequence[int] = (),
    obstacle_meshes: Sequence[tuple[int, int]] = (),
    dense_meshes: Sequence[tuple[int, int]] = (),
    quadratic: bool = False,
) -> Estimate:
    """Estimate the device memory of a scene from its preprocessed bodies.

    Args:
        tets: Each body's (q, 4) tet array (local vertex indices).
        dense_vertices: Each body's dense vertex count.
        collision_points: Each body's collision point count (:func:`warpfem.prep.geometry.surface_points`).
        collision: Whether the solver has a collider (contacts, BVHs): collisions are on and there are
            several bodies or one colliding with itself.
        tet_face_refs: Each body's count of (tet, surface face around its corners) pairs
            (:func:`warpfem.prep.geometry.tet_surface_faces`).
        surface_faces: Each body's count of surface faces of its tets.
        obstacle_meshes: ``(vertices, triangles)`` of each mesh obstacle.
        dense_meshes: ``(vertices, triangles)`` of each distinct dense surface (copies of one prepared body
            share one), which the collider keeps as a ``wp.Mesh`` for the depth of contacts.
        quadratic: Quadratic (10-node) tets: a node on each edge, which the solver counts as a vertex, and
            100 blocks' slots and 6 edge nodes per tet.

    Returns:
        The estimate by part.
    """
    from warpfem.kernels.distance import LATTICE_POINTS
    from warpfem.sim.cg import GATHER_MAX_ROWS

    q = sum(len(t) for t in tets)
    elements = [quadratic_elements(t) if quadratic else np.asarray(t).reshape(-1, 4) for t in tets]
    n = sum(int(np.unique(e).size) for e in elements)
    blocks = sum(matrix_blocks(e) for e in elements)
    parts = {
        "tets": (TET_BYTES + (QUADRATIC_TET_BYTES if quadratic else 0)) * q
        + TET_FACE_BYTES * sum(tet_face_refs)
        + LATTICE_POINT_BYTES * LATTICE_POINTS * sum(surface_faces),
        "tet vertices": VERTEX_BYTES * n,
        "matrix": (BLOCK_BYTES + (GATHER_BLOCK_BYTES if n <= GATHER_MAX_ROWS else 0)) * blocks,
        "dense vertices": DENSE_BYTES * sum(dense_vertices),
    }
    points = sum(collision_points)
    parts["collision"] = POINT_BYTES * points
    if collision:
        contacts = max(64, int(CONTACTS_PER_POINT * points))
        per_tet = COLLIDER_TET_BYTES + TREE_TET_BYTES
        parts["collision"] += COLLIDER_POINT_BYTES * points + CONTACT_BYTES * contacts + per_tet * q
        parts["collision"] += sum(MESH_VERTEX_BYTES * nv + MESH_FACE_BYTES * nf for nv, nf in dense_meshes)
    if obstacle_meshes:
        parts["obstacles"] = sum(MESH_VERTEX_BYTES * nv + MESH_FACE_BYTES * nf for nv, nf in obstacle_meshes)
    return Estimate(parts)


def scene_estimate(scene: Scene, prepared: Sequence[PreparedBody], geometry: Sequence[BodyGeometry]) -> Estimate:
    """Estimate the device memory of ``scene`` from its preprocessed bodies and their placed geometry (scene order)."""
    points = [len(g.point_tet) for g in geometry]
    collider = scene.collision.enabled and (len(prepared) > 1 or any(obj.self_collision for obj in scene.objects))
    refs = [len(g.tet_faces) for g in geometry]
    meshes = [_mesh_size(scene, i) for i, o in enumerate(scene.obstacles) if o.kind == "mesh"]
    dense = [len(p.dense_vertices) for p in prepared]
    shapes = {id(p): (len(p.dense_vertices), len(p.dense_faces)) for p in prepared}
    faces = [len(g.face_depth) for g in geometry]
    quadratic = scene.solver.elements == "quadratic"
    tets = [p.tets for p in prepared]
    return estimate(tets, dense, points, collider, refs, faces, meshes, list(shapes.values()), quadratic)


def _mesh_size(scene: Scene, index: int) -> tuple[int, int]:
    """Vertices and triangles of mesh obstacle ``index`` of ``scene`` (its file read, as the solver will)."""
    from warpfem.build import obstacle_of

    mesh = obstacle_of(scene, index)
    return len(mesh.vertices), len(mesh.faces)


def free_bytes(device: str) -> tuple[int, int]:
    """Free and total memory of a Warp device in bytes (the CPU: available and total RAM).

    Args:
        device: A Warp device alias, ``cpu`` or ``cuda:N``.

    Returns:
        ``(free, total)``.
    """
    import warp as wp

    dev = wp.get_device(device)
    if dev.is_cuda:
        return int(dev.free_memory), int(dev.total_memory)
    total = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    try:
        with open("/proc/meminfo") as stream:
            info = dict(line.split(":", 1) for line in stream)
        return int(info["MemAvailable"].split()[0]) * 1024, total
    except (OSError, KeyError, ValueError):
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_AVPHYS_PAGES"), total


def check_fits(need: Estimate, device: str) -> None:
    """Refuse a scene whose estimate exceeds the free memory of ``device``.

    Raises:
        InputError: One line with the estimate (by part) and the free and total memory.
    """
    free, total = free_bytes(device)
    if need.total > free:
        raise InputError(
            f"the scene needs about {format_bytes(need.total)} of {device} memory ({need.describe()}), "
            f"but only {format_bytes(free)} of {format_bytes(total)} is free; use fewer faces or tets "
            "(faces, maxh), fewer bodies, or another device"
        )
