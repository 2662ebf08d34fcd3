"""Meshes of the kinds public collections hold, made here: scans with defects, a CAD part, many shells.

Each function returns ``(vertices, faces)`` (float64, int64) or writes a file; tests and
scripts/prep_kinds.py (the table in docs/preprocessing.md) use the same shapes.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh


def write_obj(path: Path, vertices: np.ndarray, faces: np.ndarray) -> Path:
    """Write a plain OBJ (positions and triangles only)."""
    lines = [f"v {x:.17g} {y:.17g} {z:.17g}" for x, y, z in vertices]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in faces]
    Path(path).write_text("\n".join(lines) + "\n")
    return Path(path)


def write_strip_ply(path: Path, vertices: np.ndarray, faces: np.ndarray) -> Path:
    """Write a binary PLY whose faces are triangle strips (``element tristrips``), one strip per triangle."""
    flat = np.column_stack([faces, np.full(len(faces), -1)]).reshape(-1).astype("<i4")
    header = (
        "ply\nformat binary_little_endian 1.0\ncomment triangle strips, as Cyberware scans store them\n"
        f"element vertex {len(vertices)}\nproperty float x\nproperty float y\nproperty float z\n"
        "element tristrips 1\nproperty list int int vertex_indices\nend_header\n"
    )
    with open(path, "wb") as stream:
        stream.write(header.encode())
        stream.write(np.asarray(vertices, "<f4").tobytes())
        stream.write(np.array([len(flat)], "<i4").tobytes() + flat.tobytes())
    return Path(path)


def with_flaps(vertices: np.ndarray, faces: np.ndarray, count: int, height: float = 0.05, seed: int = 0):
    """Weld ``count`` single-triangle flaps onto surface edges: each such edge is shared by three faces.

    A flap stands ``height`` (fraction of the bounding-box diagonal) off the edge along the surface normal,
    as stray triangles do in a scan.
    """
    rng = np.random.default_rng(seed)
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    diag = float(np.linalg.norm(np.ptp(vertices, axis=0)))
    picked = rng.choice(len(faces), size=count, replace=False)
    new_v, new_f = [vertices], [faces]
    for n, f in enumerate(picked):
        a, b, c = vertices[faces[f]]
        normal = np.cross(b - a, c - a)
        tip = 0.5 * (a + b) + height * diag * normal / np.linalg.norm(normal)
        new_v.append(tip[None])
        new_f.append(np.array([[faces[f, 1], faces[f, 0], len(vertices) + n]]))
    return np.concatenate(new_v), np.concatenate(new_f)


def with_flipped_faces(vertices: np.ndarray, faces: np.ndarray, count: int, seed: int = 0):
    """Reverse the winding of ``count`` faces chosen at random."""
    faces = np.array(faces, dtype=np.int64)
    picked = np.random.default_rng(seed).choice(len(faces), size=count, replace=False)
    faces[picked] = faces[picked, ::-1]
    return np.asarray(vertices, dtype=np.float64), faces


def bowtie() -> tuple[np.ndarray, np.ndarray]:
    """Two tetrahedra sharing one edge (0-1): that edge has four faces."""
    vertices = np.array([[0, 0, 0], [0, 0, 1], [1, 0, 0.5], [0.5, 1, 0.5], [-1, 0, 0.5], [-0.5, -1, 0.5]], float)
    tet = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    second = np.where(tet == 2, 4, np.where(tet == 3, 5, tet))
    return vertices, np.vstack([tet, second])


def cad_bracket() -> tuple[np.ndarray, np.ndarray]:
    """An angle bracket as a CAD exporter writes it (manifold3d booleans): a 6 mm plate and web, two
    gussets, a boss and five bolt holes, in millimetres; flat faces of long thin triangles."""
    from manifold3d import Manifold

    plate = Manifold.cube([120.0, 70.0, 6.0])
    web = Manifold.cube([120.0, 6.0, 60.0])
    gussets = [
        Manifold.hull_points([[x, 6, 6], [x + 5, 6, 6], [x, 50, 6], [x + 5, 50, 6], [x, 6, 50], [x + 5, 6, 50]])
        for x in (20.0, 95.0)
    ]
    boss = Manifold.cylinder(16.0, 12.0, 12.0, 64).translate([60.0, 45.0, 0.0])
    solid = Manifold.batch_boolean([plate, web, *gussets, boss], _op("Add"))
    holes = [Manifold.cylinder(40.0, 4.0, 4.0, 48).translate([x, y, -5.0]) for x, y in ((10, 60), (110, 60))]
    holes.append(Manifold.cylinder(40.0, 6.0, 6.0, 48).translate([60.0, 45.0, -5.0]))
    holes += [
        Manifold.cylinder(20.0, 4.0, 4.0, 48).rotate([-90.0, 0.0, 0.0]).translate([x, -5.0, 40.0]) for x in (45, 75)
    ]
    part = solid - Manifold.batch_boolean(holes, _op("Add"))
    mesh = part.to_mesh()
    return np.asarray(mesh.vert_properties[:, :3], dtype=np.float64), np.asarray(mesh.tri_verts, dtype=np.int64)


def _op(name: str):
    from manifold3d import OpType

    return getattr(OpType, name)


def many_shells(count: int = 44, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A model of ``count`` parts (spheres and boxes of several sizes) in a loose pile, some overlapping."""
    rng = np.random.default_rng(seed)
    vertices, faces, offset = [], [], 0
    for k in range(count):
        if k % 2:
            part = trimesh.creation.icosphere(subdivisions=2, radius=rng.uniform(0.3, 0.6))
        else:
            part = trimesh.creation.box(extents=rng.uniform(0.4, 1.0, size=3))
        center = np.array([k % 11, (k // 11) % 2, k // 22], dtype=float) * 0.9 + rng.uniform(-0.1, 0.1, 3)
        vertices.append(part.vertices + center)
        faces.append(part.faces + offset)
        offset += len(part.vertices)
    return np.concatenate(vertices), np.concatenate(faces)


def flat_sheet(n: int = 20) -> tuple[np.ndarray, np.ndarray]:
    """A flat, open square sheet at z = 0 (n x n cells): it encloses no volume."""
    grid = np.stack(np.meshgrid(np.arange(n + 1), np.arange(n + 1), indexing="ij"), -1).reshape(-1, 2) / n
    vertices = np.column_stack([grid, np.zeros(len(grid))])
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    c = (i * (n + 1) + j).reshape(-1)
    faces = np.concatenate([np.column_stack([c, c + n + 1, c + 1]), np.column_stack([c + 1, c + n + 1, c + n + 2])])
    return vertices, faces
