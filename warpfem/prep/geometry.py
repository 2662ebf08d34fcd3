"""Build-time geometry of a body that the simulation model receives as arrays.

For a tet mesh placed in the world: its outward boundary faces, the distance field at its vertices, the
collision points, the surface faces near each tet (where a contact measures its depth) and the tree of tet
boxes contact detection walks. A body with a dense (visible) surface collides with samples of that
surface; a bare tet mesh with its surface vertices, plus samples on its surface triangles for thin parts.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from warpfem.kernels.distance import LATTICE, LATTICE_POINTS
from warpfem.prep.distance import distance_field
from warpfem.prep.embedding import boundary_face_tets
from warpfem.prep.samples import SKIN_TOLERANCE, SurfaceSamples, spacings, surface_samples
from warpfem.prep.surface import signed_volume, vertex_normals
from warpfem.prep.tetmesh import boundary_faces

LEAF_TETS = 4
"""Tets per leaf of a body's tree (the detection kernel tests a leaf's four tets together)."""

MAX_TREE_LEVELS = 27
"""Deepest tree the detection walk can keep its place in (it descends three levels at a time and stacks 8
bits per step in an int64): 2^27 leaves, half a billion tets in one body."""


@dataclass(frozen=True)
class BodyGeometry:
    """What :meth:`warpfem.sim.model.ModelBuilder.add_body` needs besides vertices, tets and materials.

    All indices are local to the body.

    Attributes:
        surface_faces: (l, 3) int32 outward boundary triangles.
        vertex_depth: (p,) distance of each tet vertex below the surface (m).
        vertex_grad: (p, 3) outward unit gradient of that distance.
        point_tet: (c,) int32 tet holding each collision point.
        point_bary: (c, 4) its barycentric weights there.
        point_anchor: (c, 3) int32 vertices it lies on (-1: unused): one for a vertex, three for a sample.
        tet_face_start: (q + 1,) CSR offsets into ``tet_faces``.
        tet_faces: Indices into ``surface_faces`` of the faces touching each tet's corners.
        leaf_tets: (L, 4) int32 tets of each leaf of the body's tree (-1: none); L is a power of two and the
            tree is complete, in heap order (node k has children 2k+1 and 2k+2, the leaves last).
        face_depth: (l, :data:`LATTICE_POINTS`) depth below the visible surface at each surface face's
            lattice points (:func:`face_lattice`), m; zeros where the face is the visible surface.
        dense_points: Whether the collision points sample the dense surface: each then carries an equal
            share of the body's mass.
        skin_tet: (s,) int32 tet of each point the static colliders act on besides the tet vertices inside
            the visible surface (with a dense surface: :attr:`SurfaceSamples.skin`); empty: none given.
        skin_bary: (s, 4) its barycentric weights there.
        point_normal: (c, 3) the visible surface's outward unit normal at each collision point, along which
            the collider lifts it by the contact offset; zero where the tets' surface is the visible one, or
            where not given.
    """

    surface_faces: np.ndarray
    vertex_depth: np.ndarray
    vertex_grad: np.ndarray
    point_tet: np.ndarray
    point_bary: np.ndarray
    point_anchor: np.ndarray
    tet_face_start: np.ndarray
    tet_faces: np.ndarray
    leaf_tets: np.ndarray
    face_depth: np.ndarray
    dense_points: bool = False
    skin_tet: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int32))
    skin_bary: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))
    point_normal: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))


def face_lattice(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """The lattice points of every face, (l, LATTICE_POINTS, 3).

    Point (i, j) lies at weights ((m-i-j)/m, i/m, j/m) on the face's corners 0, 1, 2; row by row in i, the
    order the collision kernels read.
    """
    m = LATTICE
    ij = np.array([(i, j) for i in range(m + 1) for j in range(m + 1 - i)], dtype=np.float64) / m
    w = np.stack([1.0 - ij[:, 0] - ij[:, 1], ij[:, 0], ij[:, 1]], axis=1)
    return np.einsum("sk,fkd->fsd", w, np.asarray(vertices, np.float64)[np.asarray(faces)])


def body_geometry(
    vertices: np.ndarray,
    tets: np.ndarray,
    collision_spacing: float = 0.0,
    surface_faces: np.ndarray | None = None,
    vertex_depth: np.ndarray | None = None,
    vertex_grad: np.ndarray | None = None,
    dense: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
    face_depth: np.ndarray | None = None,
    samples: SurfaceSamples | None = None,
    dense_faces: np.ndarray | None = None,
) -> BodyGeometry:
    """The geometry of a body placed in the world.

    Args:
        vertices: (p, 3) tet vertex positions (m).
        tets: (q, 4) positive tets.
        collision_spacing: Spacing of collision samples (m). With ``dense``: of the dense vertices used as
            collision points (0: :data:`~warpfem.prep.samples.DEFAULT_SPACING` of the size, and the skin's grid
            :data:`~warpfem.prep.samples.SKIN_SPACING`). Without: of extra samples on the tet mesh's surface
            triangles (0: its vertices only, the paper's method).
        surface_faces: Outward boundary triangles (default: the tet mesh's boundary).
        vertex_depth: Signed distance below the visible surface at each vertex (m); computed from the tet
            mesh's surface when not given.
        vertex_grad: Outward unit gradient of that distance; computed when not given.
        dense: The dense surface as ``(positions (n, 3) m, embedding tets (n,), weights (n, 4))``, or None.
        samples: With ``dense``: which dense vertices collide (default: :func:`surface_samples` at
            ``collision_spacing``, which then needs ``dense_faces``).
        dense_faces: With ``dense``: its (m, 3) triangles, needed where there are no ``samples`` or they hold
            points on its triangles (:attr:`SurfaceSamples.face`).
        face_depth: Depth of the visible surface below each surface face's lattice points (m); zeros
            (the faces are the visible surface) when not given.
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    tets = np.asarray(tets, dtype=np.int32)
    faces = boundary_faces(tets) if surface_faces is None else np.asarray(surface_faces, np.int32)
    if vertex_depth is None or vertex_grad is None:
        vertex_depth, vertex_grad = distance_field(vertices, vertices, faces)
    skin = None
    normals = None
    if dense is None:
        points = surface_points(tets, faces, vertices, collision_spacing)
    else:
        if samples is None:
            size = float(np.linalg.norm(vertices.max(axis=0) - vertices.min(axis=0)))
            spacing, skin_spacing = spacings(collision_spacing, size)
            samples = surface_samples(dense[0], dense_faces, spacing, SKIN_TOLERANCE * size, skin_spacing)
        points = dense_samples(samples.collision, dense[1], dense[2], tets)
        if len(samples.face):
            if dense_faces is None:
                raise ValueError("samples on the dense triangles need dense_faces")
            points = _joined(points, face_samples(samples, dense[0], dense_faces, vertices, tets, faces))
        skin = dense_samples(samples.skin, dense[1], dense[2], tets)
        if dense_faces is not None:
            normals = surface_normals(dense[0], dense_faces, samples)
    start, flat = tet_surface_faces(tets, faces, len(vertices))
    return BodyGeometry(
        surface_faces=faces,
        vertex_depth=np.asarray(vertex_depth, np.float64),
        vertex_grad=np.asarray(vertex_grad, np.float64),
        point_tet=points.tet,
        point_bary=points.bary,
        point_anchor=points.anchor,
        tet_face_start=start,
        tet_faces=flat,
        leaf_tets=tet_tree(tets, vertices),
        face_depth=np.zeros((len(faces), LATTICE_POINTS)) if face_depth is None else np.asarray(face_depth, np.float64),
        dense_points=dense is not None,
        **({} if skin is None else dict(skin_tet=skin.tet, skin_bary=skin.bary)),
        point_normal=np.zeros((len(points.tet), 3)) if normals is None else normals,
    )


def surface_normals(dense_x: np.ndarray, dense_faces: np.ndarray, samples: SurfaceSamples) -> np.ndarray:
    """The outward unit normal of the dense surface at each collision point of ``samples`` (vertices, then faces).

    A vertex's is the area-weighted mean of its faces' normals (:func:`~warpfem.prep.surface.vertex_normals`); a
    point on a face, the face's. Outward: turned where the faces enclose a negative volume.
    """
    x = np.asarray(dense_x, np.float64)
    f = np.asarray(dense_faces, np.int64)
    sign = -1.0 if signed_volume(x, f) < 0.0 else 1.0
    face = np.asarray(samples.face, np.int64)
    face_n = np.cross(x[f[face, 1]] - x[f[face, 0]], x[f[face, 2]] - x[f[face, 0]])
    length = np.linalg.norm(face_n, axis=1, keepdims=True)
    face_n = np.divide(face_n, length, out=np.zeros_like(face_n), where=length > 0.0)
    return sign * np.concatenate([vertex_normals(x, f)[np.asarray(samples.collision, np.int64)], face_n])


def tet_tree(tets: np.ndarray, x: np.ndarray) -> np.ndarray:
    """A balanced tree of a body's tets, split at the median centroid along the widest axis, level by level.

    Args:
        tets: (q, 4) tets.
        x: (p, 3) rest positions (m).

    Returns:
        (L, 4) int32 leaves (see :attr:`BodyGeometry.leaf_tets`).

    Raises:
        ValueError: The body needs a deeper tree than the detection walk can keep its place in.
    """
    centroid = x[tets].mean(axis=1)
    count = len(tets)
    depth = int(np.ceil(np.log2(max(1, -(-count // LEAF_TETS)))))
    if depth > MAX_TREE_LEVELS:
        raise ValueError(
            f"a body of {count} tets needs a tree of {depth} levels; the walk keeps at most {MAX_TREE_LEVELS}"
        )
    order = np.arange(count)
    bounds = np.array([0, count])
    for _ in range(depth):  # every segment holds at least LEAF_TETS tets until the last split
        sizes = np.diff(bounds)
        seg = np.repeat(np.arange(len(sizes)), sizes)
        c = centroid[order]
        widest = np.argmax(np.maximum.reduceat(c, bounds[:-1]) - np.minimum.reduceat(c, bounds[:-1]), axis=1)
        order = order[np.lexsort((c[np.arange(count), widest[seg]], seg))]
        bounds = np.sort(np.concatenate([bounds, bounds[:-1] + (sizes + 1) // 2]))
    sizes = np.diff(bounds)
    slot = np.arange(LEAF_TETS)
    index = np.minimum(bounds[:-1, None] + slot[None, :], count - 1)
    return np.where(slot[None, :] < sizes[:, None], order[index], -1).astype(np.int32)


@dataclass(frozen=True)
class CollisionPoints:
    """Collision points of one body, in its local vertex and tet indices.

    Attributes:
        tet: (c,) owning tet of each point.
        bary: (c, 4) barycentric weights in that tet.
        anchor: (c, 3) vertices the point lies on (-1 for unused): one for a vertex, three for a sample.
    """

    tet: np.ndarray
    bary: np.ndarray
    anchor: np.ndarray


def surface_points(
    tets: np.ndarray, surface_faces: np.ndarray, vertices: np.ndarray, spacing: float
) -> CollisionPoints:
    """The surface vertices of a body, plus samples on its surface triangles every ``spacing`` metres.

    Each triangle is split into m^2 sub-triangles with m = ceil(longest edge / spacing) and a sample is put at
    each sub-triangle's centroid, so no gap between samples exceeds about ``spacing``. ``spacing`` <= 0
    gives the vertices only (the paper's method).

    Args:
        tets: (q, 4) positive tets.
        surface_faces: (l, 3) outward boundary triangles indexing the tet vertices.
        vertices: (p, 3) tet vertex positions (m).
        spacing: Sample spacing (m).
    """
    face_tet = boundary_face_tets(tets, surface_faces)
    corner = np.argmax(tets[face_tet][:, :, None] == surface_faces[:, None, :], axis=1)  # (l, 3) slot in tet
    verts, first = np.unique(surface_faces.ravel(), return_index=True)
    f_idx, k_idx = np.divmod(first, 3)
    tet = [face_tet[f_idx]]
    bary = np.zeros((len(verts), 4))
    bary[np.arange(len(verts)), corner[f_idx, k_idx]] = 1.0
    bary = [bary]
    anchor = [np.stack([verts, np.full_like(verts, -1), np.full_like(verts, -1)], axis=1)]
    if spacing > 0.0:
        tri = vertices[surface_faces]
        longest = np.max(np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2), axis=1)
        for m in np.unique(np.ceil(longest / spacing).astype(int)):
            faces = np.flatnonzero(np.ceil(longest / spacing).astype(int) == m)
            up = [(i + 1 / 3, j + 1 / 3, m - 1 - i - j + 1 / 3) for i in range(m) for j in range(m - i)]
            down = [(i + 2 / 3, j + 2 / 3, m - 2 - i - j + 2 / 3) for i in range(m - 1) for j in range(m - 1 - i)]
            uvw = np.array(up + down) / m  # (s, 3) weights on the triangle's corners
            n = len(uvw)
            w = np.zeros((len(faces), n, 4))
            rows = np.arange(len(faces))[:, None]
            for k in range(3):
                w[rows, np.arange(n)[None, :], corner[faces, k][:, None]] += uvw[None, :, k]
            tet.append(np.repeat(face_tet[faces], n))
            bary.append(w.reshape(-1, 4))
            anchor.append(np.repeat(surface_faces[faces], n, axis=0))
    return CollisionPoints(
        tet=np.concatenate(tet).astype(np.int32),
        bary=np.concatenate(bary),
        anchor=np.concatenate(anchor).astype(np.int32),
    )


def dense_samples(
    picks: np.ndarray, embed_tet: np.ndarray, embed_bary: np.ndarray, tets: np.ndarray
) -> CollisionPoints:
    """The dense vertices ``picks`` as collision points.

    Each keeps its embedding; its anchors, for the self-collision rule, are three corners of its tet.
    """
    tet = np.asarray(embed_tet, np.int32)[picks]
    return CollisionPoints(tet=tet, bary=np.asarray(embed_bary, np.float64)[picks], anchor=tets[tet][:, :3].copy())


def face_samples(
    samples: SurfaceSamples,
    dense_x: np.ndarray,
    dense_faces: np.ndarray,
    vertices: np.ndarray,
    tets: np.ndarray,
    surface_faces: np.ndarray,
) -> CollisionPoints:
    """The points ``samples`` holds on the dense triangles, embedded in the tets as the dense vertices are."""
    from warpfem.prep.embedding import embed

    corners = np.asarray(dense_x, np.float64)[np.asarray(dense_faces, np.int64)[samples.face]]
    tet, bary = embed(np.einsum("kj,kjd->kd", samples.face_bary, corners), vertices, tets, surface_faces)
    return CollisionPoints(tet=tet, bary=bary, anchor=tets[tet][:, :3].copy())


def _joined(a: CollisionPoints, b: CollisionPoints) -> CollisionPoints:
    return CollisionPoints(
        tet=np.concatenate([a.tet, b.tet]).astype(np.int32),
        bary=np.concatenate([a.bary, b.bary]),
        anchor=np.concatenate([a.anchor, b.anchor]),
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
