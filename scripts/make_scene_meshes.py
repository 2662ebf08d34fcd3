"""Write the small obstacle meshes the shipped scenes use (scenes/meshes/*.obj); run again to regenerate them.

    .venv/bin/python scripts/make_scene_meshes.py

- ``ramp.obj``: an open 2 m x 1 m rectangle in the XZ plane, facing +Y (a terrain: it pushes along its normals).
- ``bowl.obj``: an open hemisphere of radius 1 m, rim at y = 1, bottom at y = 0, facing its centre (bodies
  rest inside it).
"""

from pathlib import Path

import numpy as np

OUT = Path(__file__).resolve().parents[1] / "scenes" / "meshes"


def write_obj(path: Path, vertices: np.ndarray, faces: np.ndarray, comment: str) -> None:
    lines = [f"# {comment}"]
    lines += [f"v {x:.5f} {y:.5f} {z:.5f}" for x, y, z in vertices]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in faces]
    path.write_text("\n".join(lines) + "\n")


def ramp(nx: int = 8, nz: int = 4) -> tuple[np.ndarray, np.ndarray]:
    x, z = np.meshgrid(np.linspace(-1.0, 1.0, nx + 1), np.linspace(-0.5, 0.5, nz + 1), indexing="ij")
    vertices = np.stack([x.ravel(), np.zeros(x.size), z.ravel()], axis=1)
    faces = []
    for i in range(nx):
        for k in range(nz):
            a, b, c, d = i * (nz + 1) + k, (i + 1) * (nz + 1) + k, (i + 1) * (nz + 1) + k + 1, i * (nz + 1) + k + 1
            faces += [(a, d, c), (a, c, b)]  # counter-clockwise seen from +Y
    return vertices, np.asarray(faces)


def bowl(around: int = 32, down: int = 10) -> tuple[np.ndarray, np.ndarray]:
    vertices = [(0.0, 0.0, 0.0)]  # the bottom
    for j in range(1, down + 1):
        polar = 0.5 * np.pi * j / down  # from the bottom up to the rim
        for i in range(around):
            a = 2 * np.pi * i / around
            vertices.append((np.sin(polar) * np.cos(a), 1.0 - np.cos(polar), np.sin(polar) * np.sin(a)))
    faces = [(0, 1 + (i + 1) % around, 1 + i) for i in range(around)]
    for j in range(down - 1):
        for i in range(around):
            a, b = 1 + j * around + i, 1 + j * around + (i + 1) % around
            faces += [(a, b, b + around), (a, b + around, a + around)]
    v, f = np.asarray(vertices), np.asarray(faces)
    centre = np.array([0.0, 1.0, 0.0])
    normal = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    if np.einsum("ij,ij->i", normal, centre - v[f].mean(axis=1)).mean() < 0:  # face the centre
        f = f[:, ::-1]
    return v, f


if __name__ == "__main__":
    OUT.mkdir(exist_ok=True)
    write_obj(OUT / "ramp.obj", *ramp(), "warpfem scripts/make_scene_meshes.py: open ramp, 2 m x 1 m, facing +Y")
    write_obj(OUT / "bowl.obj", *bowl(), "warpfem scripts/make_scene_meshes.py: open hemisphere, r 1 m, facing in")
