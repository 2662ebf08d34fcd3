"""What never changes during a run (:class:`Model`) and what does (:class:`State`).

All bodies of a scene live in one set of flat arrays with per-body offsets, so every stage of a step is
one launch for the whole scene. :class:`ModelBuilder` collects bodies (in world coordinates, SI units)
and precomputes on the host what the step needs: inverse rest matrices, volumes, lumped masses, Lame
parameters, pins, the sparsity pattern of the 3x3-block system matrix and each tet's slots in it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np
import warp as wp

from warpfem.errors import InputError
from warpfem.kernels.fem import vec6i
from warpfem.sim.cells import CELLS_PER_QUADRATIC_TET, EDGES, cell_arrays, shortest_diagonals, sub_cells
from warpfem.sim.launch import DIRECT_BODIES


@dataclass(frozen=True)
class Body:
    """Where one body lives in the flat arrays, plus what output needs on the host.

    Attributes:
        name: Body name (USD prim name).
        vertex_start: First tet vertex of the body.
        vertex_count: Number of tet vertices.
        tet_start: First tet of the body.
        tet_count: Number of tets.
        dense_start: First dense (embedded) vertex.
        dense_count: Number of dense vertices.
        dense_faces: Dense triangles (m, 3) int32, indices local to the body.
        size: Rest bounding-box diagonal of the tet mesh (m).
    """

    name: str
    vertex_start: int
    vertex_count: int
    tet_start: int
    tet_count: int
    dense_start: int
    dense_count: int
    dense_faces: np.ndarray
    size: float


@dataclass
class State:
    """Tet-vertex positions (m) and velocities (m/s) of every body, flat.

    ``dv`` is the velocity change (m/s) of the step that produced the state (zero initially): the next step's
    CG starts from ``v`` moved along ``dv`` (see :meth:`warpfem.sim.cg.CGSolver.solve`), which in a free fall or a
    steady push is nearly the answer.
    """

    x: wp.array
    v: wp.array
    dv: wp.array

    def assign(self, other: State) -> None:
        """Copy ``other`` into this state (device copies, capturable)."""
        wp.copy(self.x, other.x)
        wp.copy(self.v, other.v)
        wp.copy(self.dv, other.dv)


@dataclass
class Model:
    """The rest shape, materials, pins and matrix structure of a scene; constant during a run."""

    device: wp.context.Device
    bodies: list[Body]
    rest_x: wp.array  # vec3, m
    initial_v: wp.array  # vec3, m/s
    tets: wp.array  # vec4i, global vertex indices
    dm_inv: wp.array  # mat33, inverse rest shape matrix (1/m)
    rest_volume: wp.array  # float, m^3
    tet_mu: wp.array  # float, Pa
    tet_lambda: wp.array  # float, Pa
    tet_beta: wp.array  # float, Rayleigh stiffness damping (s)
    mass: wp.array  # float, lumped vertex mass (kg)
    alpha: wp.array  # float, Rayleigh mass damping (1/s)
    free: wp.array  # int32, 0 for pinned vertices
    row_start: wp.array  # int32 (n+1), block CSR rows of the upper triangle (the matrix is symmetric)
    cols: wp.array  # int32 (nnz), block CSR columns (>= the row)
    diag_slot: wp.array  # int32 (n), the diagonal block of each row
    tet_slots: wp.array  # int32 (16 q), slot of block (a, b) of tet e's corners at e*16 + a*4 + b; -1 below
    tet_edges: wp.array  # vec6i, each quadratic tet's edge nodes (see kernels.fem.vec6i); empty: linear tets
    node_slots: wp.array  # int32 (100 q), quadratic tets: slot of block (a, b) of its 10 nodes; empty: linear tets
    cells: wp.array  # vec4i, what embedded points interpolate over: the tets, or quadratic tets' sub-tets (sim.cells)
    cell_slots: wp.array  # int32 (16 per cell), slot of block (a, b) of a cell's nodes, as tet_slots
    cell_body: wp.array  # int32, body of each cell
    dense_cell: wp.array  # int32, global cell of each dense vertex
    dense_bary: wp.array  # vec4, barycentric coordinates in that cell
    vertex_depth: wp.array  # float, signed depth of each tet vertex below its body's visible surface (m)
    vertex_grad: wp.array  # vec3, outward unit gradient of that distance at rest
    tet_body: wp.array  # int32, body of each tet
    vertex_body: wp.array  # int32, body of each tet vertex
    body_mass: wp.array  # float, each body's mass (kg)
    body_size: wp.array  # float, each body's size (m): Body.size
    body_volume: wp.array  # float, each body's rest volume (m^3)
    tet_face_start: wp.array  # int32 (q+1), CSR rows: the surface faces touching each tet's corners
    tet_faces: wp.array  # vec3i, those faces (global vertex indices, wound outward)
    tet_face_ids: wp.array  # int32, the global index of each of those faces
    face_depth: wp.array  # float (LATTICE_POINTS per face), depth of the visible surface below its lattice (m)
    body_self: wp.array  # int32, 1 where a body collides with itself
    point_cell: wp.array  # int32, global cell of each collision point
    point_bary: wp.array  # vec4, its barycentric weights there
    point_anchor: wp.array  # vec3i, global vertices it lies on (-1: none), for the self-collision rule
    point_body: wp.array  # int32
    point_mass: wp.array  # float, mass a collision point stands for (kg): a share, or the interpolated lumped mass
    point_normal: wp.array  # vec3, the visible surface's outward unit normal at rest at each collision point (0: none)
    skin_cell: wp.array  # int32, global cell of each skin point (static colliders): a dense surface sample
    skin_bary: wp.array  # vec4, its barycentric weights there (extrapolated outside the tets)
    skin_mass: wp.array  # float, the mass its penalty stands for (kg): a share, or its tet corners' interpolated
    tree_node_start: wp.array  # int32 (bodies+1), node offsets of each body's tree of tets
    tree_leaf_start: wp.array  # int32 (bodies+1), leaf offsets (a body's leaves are its last nodes)
    tree_leaf_tets: wp.array  # vec4i, global tets of each leaf (-1: none)
    tet_slack: wp.array  # float, how far below zero a point's weights in each tet may go for detection to test it
    tet_size: float  # typical tet size (m): the median largest edge component of a tet (tunnelling warning)

    @property
    def vertex_count(self) -> int:
        """Number of tet vertices over all bodies."""
        return self.rest_x.shape[0]

    @property
    def tet_count(self) -> int:
        """Number of tets over all bodies."""
        return self.tets.shape[0]

    @property
    def dense_count(self) -> int:
        """Number of dense (embedded) vertices over all bodies."""
        return self.dense_cell.shape[0]

    @property
    def quadratic(self) -> bool:
        """True if the tets are quadratic (10 nodes: corners and edge midpoints), False if linear."""
        return self.tet_edges.shape[0] > 0

    @property
    def nnz_blocks(self) -> int:
        """Number of 3x3 blocks stored for the system matrix (its upper triangle)."""
        return self.cols.shape[0]

    def state(self) -> State:
        """A new state at the rest shape with the bodies' initial velocities."""
        return State(x=wp.clone(self.rest_x), v=wp.clone(self.initial_v), dv=wp.zeros_like(self.initial_v))

    @property
    def has_collisions(self) -> bool:
        """True if any two bodies can touch (several bodies) or some body collides with itself."""
        return len(self.bodies) > 1 or bool(self.body_self.numpy().any())

    def body_of_vertex(self, vertex: int) -> Body:
        """The body owning tet vertex ``vertex``."""
        for body in self.bodies:
            if body.vertex_start <= vertex < body.vertex_start + body.vertex_count:
                return body
        raise IndexError(vertex)


def lame(young: float, poisson: float) -> tuple[float, float]:
    """Lame parameters (mu, lambda) in Pa from Young's modulus (Pa) and Poisson's ratio."""
    mu = young / (2.0 * (1.0 + poisson))
    lam = young * poisson / ((1.0 + poisson) * (1.0 - 2.0 * poisson))
    return mu, lam


def block_pattern(elements: np.ndarray, vertex_count: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Sparsity pattern of the upper triangle (row <= column) of the symmetric 3x3-block matrix of a tet mesh.

    Storing one triangle halves the bytes a product reads (the product applies each off-diagonal block
    and its transpose) and the assembly's atomics.

    Args:
        elements: (q, k) node indices of each tet (k = 4 corners, or 10 for quadratic tets).
        vertex_count: Number of vertices n (every vertex gets a diagonal block).

    Returns:
        row_start (n+1), cols (nnz), diag_slot (n), slots (k*k q: block (a, b) of tet e at e*k*k + a*k + b;
        -1 for the blocks below the diagonal, whose transposes are the slots of the blocks above) as int32 arrays.
    """
    n = np.int64(vertex_count)
    t = elements.astype(np.int64)
    k = t.shape[1]
    rows = np.repeat(t[:, :, None], k, axis=2).ravel()
    cols = np.repeat(t[:, None, :], k, axis=1).ravel()
    keys = rows * n + cols
    upper = rows <= cols
    diag = np.arange(n, dtype=np.int64) * (n + 1)
    unique = np.unique(np.concatenate([keys[upper], diag]))
    row_of = unique // n
    row_start = np.zeros(vertex_count + 1, dtype=np.int64)
    np.cumsum(np.bincount(row_of, minlength=vertex_count), out=row_start[1:])
    return (
        row_start.astype(np.int32),
        (unique % n).astype(np.int32),
        np.searchsorted(unique, diag).astype(np.int32),
        np.where(upper, np.searchsorted(unique, keys), -1).astype(np.int32),
    )


def _pattern(tets: np.ndarray, edges: np.ndarray | None, nodes: int) -> dict[str, np.ndarray]:
    """The block pattern of linear tets (``edges`` None) or quadratic ones, and each tet's slots in it.

    Keys: ``row_start``, ``cols``, ``diag_slot``, ``tet_slots`` (the corners' 4 x 4 blocks) and ``node_slots``
    (the 10 x 10 node blocks of quadratic tets; empty for linear ones).
    """
    if edges is None:
        row_start, cols, diag_slot, tet_slots = block_pattern(tets, nodes)
        node_slots = np.zeros(0, np.int32)
    else:
        row_start, cols, diag_slot, node_slots = block_pattern(np.hstack([tets, edges]), nodes)
        tet_slots = node_slots.reshape(len(tets), 10, 10)[:, :4, :4].ravel()
    return dict(row_start=row_start, cols=cols, diag_slot=diag_slot, tet_slots=tet_slots, node_slots=node_slots)


def _edge_ends(tets: np.ndarray) -> np.ndarray:
    """(6 q, 2) the two corners of each tet's edges in the order of :data:`EDGES`, the smaller first."""
    return np.sort(np.asarray(tets, np.int64)[:, np.array(EDGES)], axis=2).reshape(-1, 2)


def quadratic_nodes(vertices: np.ndarray, tets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The nodes of quadratic tets on a linear tet mesh: its vertices, then one node at each edge's midpoint.

    Args:
        vertices: (p, 3) tet vertices (m).
        tets: (q, 4) tets.

    Returns:
        (p + e, 3) node positions and (q, 6) each tet's edge nodes, in the order of :data:`EDGES`.
    """
    vertices = np.asarray(vertices, np.float64)
    unique, which = np.unique(_edge_ends(tets), axis=0, return_inverse=True)
    edges = (len(vertices) + which.reshape(-1, 6)).astype(np.int32)
    return on_edge_nodes(vertices, tets, edges, len(vertices) + len(unique)), edges


def on_edge_nodes(values: np.ndarray, tets: np.ndarray, edges: np.ndarray, nodes: int, merge=None) -> np.ndarray:
    """Per-vertex ``values`` of a tet mesh extended to the ``nodes`` nodes of its quadratic tets.

    Each edge node (``edges``, as :func:`quadratic_nodes` numbers them) takes ``merge`` of its edge's two
    corners' values: their mean by default (``np.logical_and``: true where both are).
    """
    values = np.asarray(values)
    merge = merge or (lambda a, b: 0.5 * (a + b))
    ends = _edge_ends(tets)
    out = np.zeros((nodes, *values.shape[1:]), dtype=merge(values[:1], values[:1]).dtype)
    out[: len(values)] = values
    out[np.asarray(edges).ravel()] = merge(values[ends[:, 0]], values[ends[:, 1]])
    return out


def lumped_mass(vertex_count: int, tets: np.ndarray, tet_mass: np.ndarray, tet_edges: np.ndarray | None) -> np.ndarray:
    """Each node's lumped mass (kg) from each tet's mass ``tet_mass`` (kg).

    Linear tets: a quarter per corner. Quadratic tets (``tet_edges`` given): the diagonal of the consistent
    mass matrix scaled to the tet's mass (HRZ: 1/36 per corner, 4/27 per edge node; row sums would give the
    corners negative masses).
    """
    mass = np.zeros(vertex_count)
    if tet_edges is None:
        np.add.at(mass, tets.ravel(), np.repeat(tet_mass / 4.0, 4))
    else:
        np.add.at(mass, tets.ravel(), np.repeat(tet_mass / 36.0, 4))
        np.add.at(mass, tet_edges.ravel(), np.repeat(tet_mass * 4.0 / 27.0, 6))
    return mass


SKIN_WEIGHT = 1.0e-2
"""For a body whose collision points are not dense surface samples: a dense vertex whose most negative
barycentric weight is below minus this lies outside the tets, a skin point the static colliders act on
(inside the tets, where the weights are convex, the corners' own contacts already keep it out of the ground)."""


def space_order(points: np.ndarray) -> np.ndarray:
    """The order of ``points`` (n, 3) along a Z-order curve through their bounding box (1,024 cells a side)."""
    if len(points) == 0:
        return np.zeros(0, np.int64)
    lo = points.min(axis=0)
    cells = ((points - lo) * (1023.0 / max(float(np.ptp(points, axis=0).max()), 1e-30))).astype(np.int64)
    code = np.zeros(len(points), np.int64)
    for bit in range(10):
        for axis in range(3):
            code |= ((cells[:, axis] >> bit) & 1) << (3 * bit + axis)
    return np.argsort(code, kind="stable")


def _spatially_ordered(flat: dict[str, np.ndarray], cells: np.ndarray) -> None:
    """Reorder ``flat``'s collision and skin points in space (``cells``: each cell's nodes).

    Each body's points of each kind follow :func:`space_order` of their rest positions; the bodies keep their
    order.
    """
    for prefix, keys in (("point", ("anchor", "mass", "normal")), ("skin", ("mass",))):
        cell, body = flat[f"{prefix}_cell"], flat[f"{prefix}_body"]
        if len(cell) == 0:
            continue
        rest = np.einsum("pk,pkj->pj", flat[f"{prefix}_bary"].reshape(-1, 4), flat["x"][cells[cell]])
        ends = np.flatnonzero(np.diff(body)) + 1  # a body's points are consecutive
        spans = zip(np.r_[0, ends], np.r_[ends, len(body)], strict=True)
        order = np.concatenate([a + space_order(rest[a:b]) for a, b in spans])
        for key in ("cell", "bary", "body", *keys):
            data = flat[f"{prefix}_{key}"]
            flat[f"{prefix}_{key}"] = data.reshape(len(cell), -1)[order].reshape(data.shape)


def _embedded_points(
    g: BodyArrays,
    tets: np.ndarray,
    corner_mass: np.ndarray,
    embed_tet: np.ndarray | None,
    embed_bary: np.ndarray | None,
    quadratic_at: np.ndarray | None,
) -> dict[str, np.ndarray]:
    """A body's embedded points (dense vertices, skin and collision points) in its cells, and their masses.

    ``quadratic_at``: for quadratic tets, the vertices whose shortest octahedron diagonals cut each tet into its
    sub-tets (:mod:`warpfem.sim.cells`); None: linear tets, their own cells.
    """
    point_bary = np.asarray(g.point_bary, np.float64)
    embed_tet = np.zeros(0, np.int32) if embed_tet is None else np.asarray(embed_tet, np.int32)
    embed_bary = np.zeros((0, 4)) if len(embed_tet) == 0 else np.asarray(embed_bary, np.float64).reshape(-1, 4)
    if len(g.skin_tet):  # the static colliders' points, given: each holds as its tet's corners would
        skin_tet, skin_bary = np.asarray(g.skin_tet, np.int32), np.asarray(g.skin_bary, np.float64)
        skin_mass = np.einsum("pk,pk->p", skin_bary, corner_mass[tets[skin_tet]])
    else:  # the dense vertices outside the tets, each an equal share of the body's mass
        skin = embed_bary.min(axis=1) < -SKIN_WEIGHT if len(embed_tet) else np.zeros(0, bool)
        skin_tet, skin_bary = embed_tet[skin], embed_bary[skin]
        skin_mass = np.full(len(skin_tet), corner_mass.sum() / max(len(embed_tet), 1))
    point_tet = np.asarray(g.point_tet, np.int32)
    if g.dense_points:  # samples of the visible surface: equal shares of the body's mass
        point_mass = np.full(len(point_tet), corner_mass.sum() / max(len(point_tet), 1))
    else:
        point_mass = np.einsum("pk,pk->p", point_bary, corner_mass[tets[point_tet]])
    embed_cell, skin_cell, point_cell = embed_tet, skin_tet, point_tet  # linear tets are their own cells
    diagonal = np.zeros(0, np.int8)
    if quadratic_at is not None:  # every embedded point in its sub-tet
        diagonal = shortest_diagonals(quadratic_at, tets)
        embed_cell, embed_bary = sub_cells(embed_tet, embed_bary, diagonal)
        skin_cell, skin_bary = sub_cells(skin_tet, skin_bary, diagonal)
        point_cell, point_bary = sub_cells(point_tet, point_bary, diagonal)
    return dict(
        embed_cell=embed_cell,
        embed_bary=embed_bary,
        skin_cell=skin_cell,
        skin_bary=skin_bary,
        skin_mass=skin_mass,
        point_cell=point_cell,
        point_bary=point_bary,
        point_mass=point_mass,
        diagonal=diagonal,
    )


def _point_normals(name: str, g: BodyArrays) -> np.ndarray:
    """A body's collision points' outward normals (c, 3): zeros where its geometry gives none (empty)."""
    normals = np.asarray(g.point_normal, np.float64).reshape(-1, 3)
    if len(normals) == 0:
        return np.zeros((len(g.point_tet), 3))
    if len(normals) != len(g.point_tet):
        raise InputError(f"body '{name}': point_normal has {len(normals)} rows for {len(g.point_tet)} collision points")
    return normals


def _checked_tets(
    name: str, vertices: np.ndarray, tets: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, float]:
    """Vertices and tets as arrays, each tet's edge vectors and volume, and the body's size (m).

    Raises:
        InputError: Non-finite vertices, malformed or out-of-range tets, a tet of zero or negative volume.
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    tets = np.asarray(tets, dtype=np.int32)
    if not np.isfinite(vertices).all():
        raise InputError(f"body '{name}': tet vertices are not finite")
    if tets.ndim != 2 or tets.shape[1] != 4 or len(tets) == 0:
        raise InputError(f"body '{name}': needs at least one tet, got tets of shape {tets.shape}")
    if tets.min() < 0 or tets.max() >= len(vertices):
        raise InputError(f"body '{name}': tet indices out of range")
    d = vertices[tets[:, 1:]] - vertices[tets[:, :1]]
    volume = np.linalg.det(d) / 6.0
    size = float(np.linalg.norm(vertices.max(0) - vertices.min(0)))
    if (volume <= 1e-12 * size**3).any():
        bad = int(np.argmin(volume))
        raise InputError(f"body '{name}': tet {bad} has zero or negative volume ({volume[bad]:.3g} m^3)")
    return vertices, tets, d, volume, size


def _checked_edges(name: str, tets: np.ndarray, edges: np.ndarray, corners: int, nodes: int) -> np.ndarray:
    """``edges`` checked against ``tets``: what :func:`quadratic_nodes` makes.

    (q, 6) node indices past the ``corners`` that the tets use, one node of its own for each edge.

    Raises:
        InputError: Wrong shape, an index out of range, or edge nodes that do not match the tets' edges.
    """
    if edges.shape != (len(tets), 6):
        raise InputError(f"body '{name}': tet_edges must have shape ({len(tets)}, 6), got {edges.shape}")
    if tets.max() >= corners or edges.min() < corners or edges.max() >= nodes:
        raise InputError(f"body '{name}': tet_edges must index the nodes after the {corners} tet corners")
    pairs = np.unique(np.column_stack([edges.ravel(), _edge_ends(tets)]), axis=0)
    if len(np.unique(pairs[:, 0])) != len(pairs) or len(np.unique(pairs[:, 1:], axis=0)) != len(pairs):
        raise InputError(f"body '{name}': tet_edges do not give each tet edge one node of its own")
    return edges


class BodyArrays(Protocol):
    """Build-time geometry of a body (made by :func:`warpfem.prep.geometry.body_geometry`), local indices.

    Attributes:
        surface_faces: (l, 3) outward boundary triangles.
        vertex_depth: (p,) distance of each tet vertex below the surface (m).
        vertex_grad: (p, 3) outward unit gradient of that distance at rest.
        point_tet, point_bary, point_anchor: Collision points: tet, barycentric weights, vertices they lie on.
        point_normal: (c, 3) the visible surface's outward unit normal at each (zero or empty: none).
        tet_face_start, tet_faces: CSR, the surface faces touching each tet's corners.
        face_depth: (l, LATTICE_POINTS) depth of the visible surface below each surface face's lattice points (m).
        leaf_tets: (L, 4) leaves of the body's tree of tets (-1: none), L a power of two.
    """

    surface_faces: np.ndarray
    vertex_depth: np.ndarray
    vertex_grad: np.ndarray
    point_tet: np.ndarray
    point_bary: np.ndarray
    point_anchor: np.ndarray
    point_normal: np.ndarray
    tet_face_start: np.ndarray
    tet_faces: np.ndarray
    leaf_tets: np.ndarray
    face_depth: np.ndarray


_FLAT_FIELDS = {
    "rest_x": ("x", wp.vec3, np.float32),
    "initial_v": ("v", wp.vec3, np.float32),
    "dm_inv": ("dm_inv", wp.mat33, np.float32),
    "rest_volume": ("volume", float, np.float32),
    "tet_mu": ("mu", float, np.float32),
    "tet_lambda": ("lam", float, np.float32),
    "tet_beta": ("beta", float, np.float32),
    "mass": ("mass", float, np.float32),
    "alpha": ("alpha", float, np.float32),
    "free": ("free", wp.int32, np.int32),
    "dense_cell": ("embed_cell", wp.int32, np.int32),
    "dense_bary": ("embed_bary", wp.vec4, np.float32),
    "vertex_depth": ("depth", float, np.float32),
    "vertex_grad": ("grad", wp.vec3, np.float32),
    "vertex_body": ("vertex_body", wp.int32, np.int32),
    "tet_face_start": ("tet_face_start", wp.int32, np.int32),
    "tet_faces": ("tet_faces", wp.vec3i, np.int32),
    "tet_face_ids": ("tet_face_ids", wp.int32, np.int32),
    "face_depth": ("face_depth", float, np.float32),
    "point_cell": ("point_cell", wp.int32, np.int32),
    "point_bary": ("point_bary", wp.vec4, np.float32),
    "point_anchor": ("point_anchor", wp.vec3i, np.int32),
    "point_body": ("point_body", wp.int32, np.int32),
    "point_mass": ("point_mass", float, np.float32),
    "point_normal": ("point_normal", wp.vec3, np.float32),
    "skin_cell": ("skin_cell", wp.int32, np.int32),
    "skin_bary": ("skin_bary", wp.vec4, np.float32),
    "skin_mass": ("skin_mass", float, np.float32),
    "tree_node_start": ("node_start", wp.int32, np.int32),
    "tree_leaf_start": ("leaf_start", wp.int32, np.int32),
    "tree_leaf_tets": ("leaf_tets", wp.vec4i, np.int32),
    "tet_slack": ("slack", float, np.float32),
}
"""The :class:`Model` fields copied as they are from the builder's flat arrays: (flat key, Warp dtype, NumPy dtype)."""


TET_SLACK_MARGIN = 1.25
"""A tet's detection slack over the lowest weight of its own dense vertices and collision points outside it."""


def tet_slack(tet_count: int, *embeddings: tuple[np.ndarray | None, np.ndarray | None]) -> np.ndarray:
    """Per tet, how far below zero a point's weights in it may go for contact detection to test the tet.

    Where the dense surface stands outside the tets, its vertices and collision points are carried by the tet
    nearest them with weights below zero; another body's point pressed into that part of the surface lies in
    no tet either. A tet's slack is :data:`TET_SLACK_MARGIN` times the lowest weight of a point it carries
    (zero where it carries none outside it), so detection finds such a point in the tet that carries the
    surface there, where the tet's leaf box holds it (the boxes do not grow: a leaf's box already reaches
    past its tets, and grown boxes cost detection more than they find). ``embeddings``: (tet, weights) per
    kind of embedded point, local indices (None: none).
    """
    slack = np.zeros(tet_count)
    for tet, bary in embeddings:
        if tet is not None and len(tet):
            w = np.asarray(bary).reshape(len(tet), 4)
            # column by column: NumPy reduces axis 1 of an (n, 4) array several times slower
            lowest = np.minimum(np.minimum(w[:, 0], w[:, 1]), np.minimum(w[:, 2], w[:, 3]))
            outside = lowest < 0.0
            np.maximum.at(slack, np.asarray(tet)[outside], -lowest[outside].astype(np.float64))
    return TET_SLACK_MARGIN * slack


class ModelBuilder:
    """Collects bodies, then builds one flat :class:`Model` on a device."""

    def __init__(self) -> None:
        self._bodies: list[dict] = []

    def add_body(
        self,
        name: str,
        vertices: np.ndarray,
        tets: np.ndarray,
        geometry: BodyArrays,
        young: float,
        poisson: float,
        density: float,
        damping_mass: float = 0.0,
        damping_stiffness: float = 0.0,
        velocity: tuple[float, float, float] | np.ndarray = (0.0, 0.0, 0.0),
        pinned: np.ndarray | None = None,
        dense_faces: np.ndarray | None = None,
        embed_tet: np.ndarray | None = None,
        embed_bary: np.ndarray | None = None,
        self_collision: bool = False,
        tet_edges: np.ndarray | None = None,
    ) -> int:
        """Add a body in world coordinates.

        Args:
            name: Body name.
            vertices: (p, 3) tet vertex rest positions (m).
            tets: (q, 4) positively oriented tets.
            geometry: Its surface, distance field, collision points and tree (local indices).
            young: Young's modulus (Pa).
            poisson: Poisson's ratio.
            density: Density (kg/m^3).
            damping_mass: Rayleigh mass damping alpha (1/s).
            damping_stiffness: Rayleigh stiffness damping beta (s).
            velocity: Initial velocity (m/s): one for every vertex, or (p, 3), one each.
            pinned: Optional (p,) bool mask of fixed vertices.
            dense_faces: Optional (m, 3) dense triangles.
            embed_tet: (n,) tet of each dense vertex (local index); None: no dense mesh.
            embed_bary: (n, 4) barycentric coordinates; required with ``embed_tet``.
            self_collision: Whether the body collides with itself.
            tet_edges: For quadratic tets, (q, 6) each tet's edge nodes among ``vertices`` (made by
                :func:`quadratic_nodes`, which puts them after the corners ``geometry`` describes); None: linear.
                The elastic force is quadratic; the dense mesh and the collision and skin points follow each
                tet's sub-tets (:mod:`warpfem.sim.cells`).

        Returns:
            The body's index.

        Raises:
            InputError: a tet of zero or negative volume, or non-finite input.
        """
        vertices, tets, d, volume, size = _checked_tets(name, vertices, tets)
        mu, lam = lame(young, poisson)
        corner_mass = lumped_mass(len(vertices), tets, density * volume, None)
        g = geometry
        depth, grad = np.asarray(g.vertex_depth, np.float64), np.asarray(g.vertex_grad, np.float64).reshape(-1, 3)
        if tet_edges is not None:
            tet_edges = _checked_edges(name, tets, np.asarray(tet_edges, np.int32), len(depth), len(vertices))
            nodes = len(vertices)
            depth, grad = on_edge_nodes(depth, tets, tet_edges, nodes), on_edge_nodes(grad, tets, tet_edges, nodes)
        mass = corner_mass if tet_edges is None else lumped_mass(len(vertices), tets, density * volume, tet_edges)
        free = mass > 0.0
        if pinned is not None:
            free &= ~np.asarray(pinned, dtype=bool)
        embedded = _embedded_points(
            g, tets, corner_mass, embed_tet, embed_bary, vertices if tet_edges is not None else None
        )
        self._bodies.append(
            dict(
                name=name,
                x=vertices,
                tets=tets,
                dm_inv=np.linalg.inv(np.transpose(d, (0, 2, 1))),
                volume=volume,
                mu=np.full(len(tets), mu),
                lam=np.full(len(tets), lam),
                beta=np.full(len(tets), damping_stiffness),
                mass=mass,
                alpha=np.full(len(vertices), damping_mass),
                free=free.astype(np.int32),
                v=np.broadcast_to(np.asarray(velocity, dtype=np.float64), (len(vertices), 3)).copy(),
                dense_faces=np.zeros((0, 3), np.int32) if dense_faces is None else np.asarray(dense_faces, np.int32),
                depth=depth,
                grad=grad,
                edges=np.zeros((0, 6), np.int32) if tet_edges is None else tet_edges,
                size=size,
                self_collision=bool(self_collision),
                point_anchor=np.asarray(g.point_anchor, np.int32),
                point_normal=_point_normals(name, g),
                tet_extent=np.abs(d).max(axis=(1, 2)),
                surface_faces=np.asarray(g.surface_faces, np.int32),
                tet_faces=(np.asarray(g.tet_face_start), np.asarray(g.tet_faces)),
                face_depth=np.asarray(g.face_depth, np.float64).reshape(-1),
                leaf_tets=np.asarray(g.leaf_tets, np.int32).reshape(-1, 4),
                slack=tet_slack(len(tets), (embed_tet, embed_bary), (g.point_tet, g.point_bary)),
                **embedded,
            )
        )
        return len(self._bodies) - 1

    def finalize(self, device: str | wp.context.Device | None = None, ordered: bool | None = None) -> Model:
        """Build the flat model on ``device`` (default: Warp's default device).

        ``ordered``: each body's collision and skin points along a Z-order curve (:func:`space_order`), so that a
        warp's threads walk the same tree branches; default: on CUDA with more than
        :data:`~warpfem.sim.launch.DIRECT_BODIES` bodies, where it makes detection faster (docs/decisions.md).
        """
        if not self._bodies:
            raise InputError("a scene needs at least one body")
        device = wp.get_device(device)
        bodies, flat = self._flatten()
        quadratic = [len(b["edges"]) > 0 for b in self._bodies]
        if any(quadratic) and not all(quadratic):
            raise InputError("a scene's bodies must all have linear tets or all quadratic tets")
        edges = flat["edges"].astype(np.int32)
        pattern = _pattern(flat["tets"], edges if all(quadratic) else None, len(flat["x"]))

        def arr(key: str, dtype, np_type=np.float32) -> wp.array:
            return wp.array(np.ascontiguousarray(flat[key].astype(np_type)), dtype=dtype, device=device)

        def arr_of(data: np.ndarray, dtype) -> wp.array:
            return wp.array(np.ascontiguousarray(data), dtype=dtype, device=device)

        tets, tet_slots = arr("tets", wp.vec4i, np.int32), arr_of(pattern["tet_slots"], wp.int32)
        tet_body = arr("tet_body", wp.int32, np.int32)
        cells, cell_slots, cell_body = tets, tet_slots, tet_body  # linear tets are their own cells
        corners = flat["tets"]
        if all(quadratic):
            corners, slots, owner = cell_arrays(
                corners, edges, flat["diagonal"], pattern["node_slots"], flat["tet_body"]
            )
            cells, cell_slots = arr_of(corners, wp.vec4i), arr_of(slots, wp.int32)
            cell_body = arr_of(owner.astype(np.int32), wp.int32)
        if (device.is_cuda and len(bodies) > DIRECT_BODIES) if ordered is None else ordered:
            _spatially_ordered(flat, corners)
        per_body = [(b["mass"].sum(), b["size"], b["volume"].sum(), b["self_collision"]) for b in self._bodies]
        mass, size, volume, self_collision = (np.array(column) for column in zip(*per_body, strict=True))
        return Model(
            device=device,
            bodies=bodies,
            **{field: arr(key, dtype, np_type) for field, (key, dtype, np_type) in _FLAT_FIELDS.items()},
            tets=tets,
            row_start=arr_of(pattern["row_start"], wp.int32),
            cols=arr_of(pattern["cols"], wp.int32),
            diag_slot=arr_of(pattern["diag_slot"], wp.int32),
            tet_slots=tet_slots,
            tet_edges=arr_of(edges, vec6i),
            node_slots=arr_of(pattern["node_slots"], wp.int32),
            cells=cells,
            cell_slots=cell_slots,
            cell_body=cell_body,
            tet_body=tet_body,
            body_mass=arr_of(mass.astype(np.float32), float),
            body_size=arr_of(size.astype(np.float32), float),
            body_volume=arr_of(volume.astype(np.float32), float),
            body_self=arr_of(self_collision.astype(np.int32), wp.int32),
            tet_size=float(np.median(flat["tet_extent"])),
        )

    def _flatten(self) -> tuple[list[Body], dict[str, np.ndarray]]:
        """Every body's arrays concatenated, local indices offset to global ones."""
        per: dict[str, list[np.ndarray]] = {}
        bodies, v0, t0, d0, f0, s0, leaves = [], 0, 0, 0, 0, 0, 0

        def add(key: str, value: np.ndarray) -> None:
            per.setdefault(key, []).append(value)

        for index, b in enumerate(self._bodies):
            c0 = t0 * (CELLS_PER_QUADRATIC_TET if len(b["edges"]) else 1)
            for key in ("x", "v", "dm_inv", "volume", "mu", "lam", "beta", "mass", "alpha", "free"):
                add(key, b[key])
            for key in (
                "embed_bary",
                "depth",
                "grad",
                "point_bary",
                "point_mass",
                "point_normal",
                "tet_extent",
                "skin_bary",
                "skin_mass",
                "face_depth",
                "slack",
            ):
                add(key, b[key])
            start, flat = b["tet_faces"]
            add("tet_face_start", start[1:] + f0)
            add("tet_faces", b["surface_faces"][flat] + v0)
            add("tet_face_ids", flat + s0)
            f0 += len(flat)
            s0 += len(b["surface_faces"])
            add("tets", b["tets"] + v0)
            add("edges", b["edges"] + v0)
            add("diagonal", b["diagonal"])
            add("embed_cell", b["embed_cell"] + c0)
            add("skin_cell", b["skin_cell"] + c0)
            add("point_cell", b["point_cell"] + c0)
            add("point_anchor", np.where(b["point_anchor"] >= 0, b["point_anchor"] + v0, -1))
            add("point_body", np.full(len(b["point_cell"]), index))
            add("skin_body", np.full(len(b["skin_cell"]), index))
            add("tet_body", np.full(len(b["tets"]), index))
            add("vertex_body", np.full(len(b["x"]), index))
            add("leaf_tets", np.where(b["leaf_tets"] >= 0, b["leaf_tets"] + t0, -1))
            leaves += len(b["leaf_tets"])
            add("leaf_start", np.array([leaves]))
            add("node_start", np.array([2 * leaves - index - 1]))
            n_x, n_t, n_d = len(b["x"]), len(b["tets"]), len(b["embed_cell"])
            bodies.append(Body(b["name"], v0, n_x, t0, n_t, d0, n_d, b["dense_faces"], b["size"]))
            v0, t0, d0 = v0 + n_x, t0 + n_t, d0 + n_d
        flat = {key: np.concatenate(values) for key, values in per.items()}
        for key in ("tet_face_start", "leaf_start", "node_start"):
            flat[key] = np.concatenate([[0], flat[key]])
        flat["embed_bary"] = flat["embed_bary"].reshape(-1, 4)
        flat["skin_bary"] = flat["skin_bary"].reshape(-1, 4)
        flat["grad"] = flat["grad"].reshape(-1, 3)
        flat["edges"] = flat["edges"].reshape(-1, 6)
        flat["tet_faces"] = flat["tet_faces"].reshape(-1, 3)
        return bodies, flat
