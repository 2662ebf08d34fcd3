"""What never changes during a run (:class:`Model`) and what does (:class:`State`).

All bodies of a scene live in one set of flat arrays with per-body offsets, so every stage of a step is
one launch for the whole scene. :class:`ModelBuilder` collects bodies (in world coordinates, SI units)
and precomputes on the host what the step needs: inverse rest matrices, volumes, lumped masses, Lame
parameters, pins, the sparsity pattern of the 3x3-block system matrix and each tet's slots in it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from warpfem.collision import surface_points
from warpfem.distance import distance_field
from warpfem.errors import InputError
from warpfem.tetmesh import boundary_faces


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
    CG starts from ``v`` moved along ``dv`` (see :meth:`warpfem.cg.CGSolver.solve`), which in a free fall or a
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
    tet_slots: wp.array  # int32 (16 q), slot of block (a, b) of tet e at e*16 + a*4 + b; -1 below the diagonal
    dense_tet: wp.array  # int32, global tet of each dense vertex
    dense_bary: wp.array  # vec4, barycentric coordinates in that tet
    vertex_depth: wp.array  # float, distance of each tet vertex to its body's surface (m)
    vertex_grad: wp.array  # vec3, outward unit gradient of that distance at rest
    tet_body: wp.array  # int32, body of each tet
    tet_face_start: wp.array  # int32 (q+1), CSR rows: the surface faces touching each tet's corners
    tet_faces: wp.array  # vec3i, those faces (global vertex indices, wound outward)
    body_self: wp.array  # int32, 1 where a body collides with itself
    point_tet: wp.array  # int32, global tet of each collision point
    point_bary: wp.array  # vec4, its barycentric weights there
    point_anchor: wp.array  # vec3i, global vertices it lies on (-1: none), for the self-collision rule
    point_body: wp.array  # int32
    point_mass: wp.array  # float, lumped vertex mass interpolated at each collision point (kg)
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
        return self.dense_tet.shape[0]

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


def block_pattern(tets: np.ndarray, vertex_count: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Sparsity pattern of the upper triangle (row <= column) of the symmetric 3x3-block matrix of a tet mesh.

    Storing one triangle halves the bytes a product reads (the product applies each off-diagonal block
    and its transpose) and the assembly's atomics.

    Args:
        tets: (q, 4) vertex indices.
        vertex_count: Number of vertices n (every vertex gets a diagonal block).

    Returns:
        row_start (n+1), cols (nnz), diag_slot (n), tet_slots (16 q; -1 for the blocks below the diagonal,
        whose transposes are the slots of the blocks above) as int32 arrays.
    """
    n = np.int64(vertex_count)
    t = tets.astype(np.int64)
    rows = np.repeat(t[:, :, None], 4, axis=2).ravel()
    cols = np.repeat(t[:, None, :], 4, axis=1).ravel()
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


def tet_surface_faces(tets: np.ndarray, surface_faces: np.ndarray, vertex_count: int) -> tuple[np.ndarray, np.ndarray]:
    """For each tet, the surface faces that touch one of its corners (CSR: row offsets, face indices).

    The collision response measures a point's depth below these faces: the body's surface near the tet,
    not only the tet's own faces (a tet at an edge may have only a side face on the surface).
    """
    face_of_vertex = [[] for _ in range(vertex_count)]
    for f, face in enumerate(surface_faces):
        for v in face:
            face_of_vertex[v].append(f)
    rows = [sorted({f for v in t for f in face_of_vertex[v]}) for t in tets]
    start = np.zeros(len(tets) + 1, dtype=np.int64)
    np.cumsum([len(r) for r in rows], out=start[1:])
    flat = np.fromiter((f for r in rows for f in r), dtype=np.int64, count=int(start[-1]))
    return start, flat


class ModelBuilder:
    """Collects bodies, then builds one flat :class:`Model` on a device."""

    def __init__(self) -> None:
        self._bodies: list[dict] = []

    def add_body(
        self,
        name: str,
        vertices: np.ndarray,
        tets: np.ndarray,
        young: float,
        poisson: float,
        density: float,
        damping_mass: float = 0.0,
        damping_stiffness: float = 0.0,
        velocity: tuple[float, float, float] = (0.0, 0.0, 0.0),
        pinned: np.ndarray | None = None,
        dense_vertices: np.ndarray | None = None,
        dense_faces: np.ndarray | None = None,
        embed_tet: np.ndarray | None = None,
        embed_bary: np.ndarray | None = None,
        vertex_depth: np.ndarray | None = None,
        vertex_grad: np.ndarray | None = None,
        surface_faces: np.ndarray | None = None,
        self_collision: bool = False,
        collision_spacing: float = 0.0,
    ) -> int:
        """Add a body in world coordinates.

        Args:
            name: Body name.
            vertices: (p, 3) tet vertex rest positions (m).
            tets: (q, 4) positively oriented tets.
            young: Young's modulus (Pa).
            poisson: Poisson's ratio.
            density: Density (kg/m^3).
            damping_mass: Rayleigh mass damping alpha (1/s).
            damping_stiffness: Rayleigh stiffness damping beta (s).
            velocity: Initial velocity (m/s).
            pinned: Optional (p,) bool mask of fixed vertices.
            dense_vertices: Optional (n, 3) rest dense vertices (m), only to size the body's output.
            dense_faces: Optional (m, 3) dense triangles.
            embed_tet: (n,) tet of each dense vertex (local index); required with dense_vertices.
            embed_bary: (n, 4) barycentric coordinates; required with dense_vertices.
            vertex_depth: (p,) distance to the surface (m); computed from the surface when not given.
            vertex_grad: (p, 3) outward unit gradient of that distance; computed when not given.
            surface_faces: Optional (l, 3) outward boundary triangles (default: the tet mesh's boundary).
            self_collision: Whether the body collides with itself.
            collision_spacing: Spacing of extra collision samples on the surface (m); 0: vertices only.

        Returns:
            The body's index.

        Raises:
            InputError: a tet of zero or negative volume, or non-finite input.
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
        mu, lam = lame(young, poisson)
        mass = np.zeros(len(vertices))
        np.add.at(mass, tets.ravel(), np.repeat(density * volume / 4.0, 4))
        free = mass > 0.0
        if pinned is not None:
            free &= ~np.asarray(pinned, dtype=bool)
        n_dense = 0 if dense_vertices is None else len(dense_vertices)
        if surface_faces is None:
            surface_faces = boundary_faces(tets)
        if vertex_depth is None or vertex_grad is None:
            vertex_depth, vertex_grad = distance_field(vertices, vertices, np.asarray(surface_faces, np.int32))
        points = surface_points(tets, np.asarray(surface_faces, np.int32), vertices, collision_spacing)
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
                v=np.tile(np.asarray(velocity, dtype=np.float64), (len(vertices), 1)),
                dense_faces=np.zeros((0, 3), np.int32) if dense_faces is None else np.asarray(dense_faces, np.int32),
                embed_tet=np.zeros(0, np.int32) if n_dense == 0 else np.asarray(embed_tet, np.int32),
                embed_bary=np.zeros((0, 4)) if n_dense == 0 else np.asarray(embed_bary, np.float64),
                depth=np.asarray(vertex_depth, np.float64),
                grad=np.asarray(vertex_grad, np.float64),
                size=size,
                self_collision=bool(self_collision),
                points=points,
                point_mass=np.einsum("pk,pk->p", points.bary, mass[tets[points.tet]]),
                tet_extent=np.abs(d).max(axis=(1, 2)),
                surface_faces=np.asarray(surface_faces, np.int32),
                tet_faces=tet_surface_faces(tets, np.asarray(surface_faces, np.int32), len(vertices)),
            )
        )
        return len(self._bodies) - 1

    def finalize(self, device: str | wp.context.Device | None = None) -> Model:
        """Build the flat model on ``device`` (default: Warp's default device)."""
        if not self._bodies:
            raise InputError("a scene needs at least one body")
        device = wp.get_device(device)
        bodies, v0, t0, d0 = [], 0, 0, 0
        tets, dense_tet, point_tet, point_anchor, point_body, tet_body = [], [], [], [], [], []
        face_start, faces = [np.zeros(1, np.int64)], []
        for index, b in enumerate(self._bodies):
            start, flat = b["tet_faces"]
            face_start.append(start[1:] + sum(len(f) for f in faces))
            faces.append(b["surface_faces"][flat] + v0)
            tets.append(b["tets"] + v0)
            dense_tet.append(b["embed_tet"] + t0)
            point_tet.append(b["points"].tet + t0)
            point_anchor.append(np.where(b["points"].anchor >= 0, b["points"].anchor + v0, -1))
            point_body.append(np.full(len(b["points"].tet), index))
            tet_body.append(np.full(len(b["tets"]), index))
            bodies.append(
                Body(
                    b["name"],
                    v0,
                    len(b["x"]),
                    t0,
                    len(b["tets"]),
                    d0,
                    len(b["embed_tet"]),
                    b["dense_faces"],
                    b["size"],
                )
            )
            v0 += len(b["x"])
            t0 += len(b["tets"])
            d0 += len(b["embed_tet"])
        all_tets = np.concatenate(tets)
        row_start, cols, diag_slot, tet_slots = block_pattern(all_tets, v0)

        def cat(key: str) -> np.ndarray:
            return np.concatenate([b[key] for b in self._bodies])

        def arr(data: np.ndarray, dtype) -> wp.array:
            return wp.array(np.ascontiguousarray(data), dtype=dtype, device=device)

        f32 = np.float32
        return Model(
            device=device,
            bodies=bodies,
            rest_x=arr(cat("x").astype(f32), wp.vec3),
            initial_v=arr(cat("v").astype(f32), wp.vec3),
            tets=arr(all_tets.astype(np.int32), wp.vec4i),
            dm_inv=arr(cat("dm_inv").astype(f32), wp.mat33),
            rest_volume=arr(cat("volume").astype(f32), float),
            tet_mu=arr(cat("mu").astype(f32), float),
            tet_lambda=arr(cat("lam").astype(f32), float),
            tet_beta=arr(cat("beta").astype(f32), float),
            mass=arr(cat("mass").astype(f32), float),
            alpha=arr(cat("alpha").astype(f32), float),
            free=arr(cat("free"), wp.int32),
            row_start=arr(row_start, wp.int32),
            cols=arr(cols, wp.int32),
            diag_slot=arr(diag_slot, wp.int32),
            tet_slots=arr(tet_slots, wp.int32),
            dense_tet=arr(np.concatenate(dense_tet).astype(np.int32), wp.int32),
            dense_bary=arr(cat("embed_bary").astype(f32).reshape(-1, 4), wp.vec4),
            vertex_depth=arr(cat("depth").astype(f32), float),
            vertex_grad=arr(cat("grad").astype(f32).reshape(-1, 3), wp.vec3),
            tet_body=arr(np.concatenate(tet_body).astype(np.int32), wp.int32),
            tet_face_start=arr(np.concatenate(face_start).astype(np.int32), wp.int32),
            tet_faces=arr(np.concatenate(faces).astype(np.int32).reshape(-1, 3), wp.vec3i),
            body_self=arr(np.array([b["self_collision"] for b in self._bodies], np.int32), wp.int32),
            point_tet=arr(np.concatenate(point_tet).astype(np.int32), wp.int32),
            point_bary=arr(np.concatenate([b["points"].bary for b in self._bodies]).astype(f32), wp.vec4),
            point_anchor=arr(np.concatenate(point_anchor).astype(np.int32), wp.vec3i),
            point_body=arr(np.concatenate(point_body).astype(np.int32), wp.int32),
            point_mass=arr(cat("point_mass").astype(f32), float),
            tet_size=float(np.median(cat("tet_extent"))),
        )
