"""Child process that runs Netgen's volume mesher: ``python -m warpfem._netgen_worker IN.npz OUT.npz``.

Netgen can hang or abort the process on bad input, so ``warpfem.tetmesh`` runs this module in a child
with a time limit. IN.npz holds ``vertices`` (n, 3) float64, ``faces`` (m, 3) int32 (outward winding,
0-based), ``maxh`` and ``optsteps``. OUT.npz receives Netgen's ``points`` (p, 3) float64 and ``tets``
(q, 4) int32 (0-based, Netgen's own corner order). Netgen's console output goes to this process's stdout.
"""

from __future__ import annotations

import sys

import numpy as np


def mesh_volume(vertices: np.ndarray, faces: np.ndarray, maxh: float, optsteps: int) -> tuple[np.ndarray, np.ndarray]:
    """Fill a closed surface with tetrahedra, keeping the surface triangles as the boundary.

    Args:
        vertices: (n, 3) surface positions.
        faces: (m, 3) 0-based triangles, wound outward (Netgen makes no tets from an inward surface).
        maxh: Largest tet edge length, in mesh units.
        optsteps: Netgen's number of 3D optimization steps.

    Returns:
        ``(points, tets)``: Netgen's points (the n surface points first, unchanged) and its 0-based tets.
    """
    from netgen.meshing import Element2D, FaceDescriptor, Mesh, MeshPoint, Pnt

    mesh = Mesh(dim=3)
    ids = [mesh.Add(MeshPoint(Pnt(*map(float, p)))) for p in vertices]
    region = mesh.Add(FaceDescriptor(surfnr=1, domin=1, domout=0, bc=1))
    for a, b, c in faces:
        mesh.Add(Element2D(region, [ids[a], ids[b], ids[c]]))
    mesh.GenerateVolumeMesh(maxh=maxh, optsteps3d=optsteps)
    # copy while the mesh is alive: both are views into Netgen's memory
    points = np.array(mesh.Coordinates(), dtype=np.float64, copy=True).reshape(-1, 3)
    tets = np.array(mesh.Elements3D().NumPy()["nodes"], dtype=np.int32, copy=True).reshape(-1, 4) - 1
    return points, tets


def main(argv: list[str]) -> int:
    """Read IN.npz, mesh it, write OUT.npz; return the process exit code."""
    if len(argv) != 2:
        print("usage: python -m warpfem._netgen_worker IN.npz OUT.npz", file=sys.stderr)
        return 2
    with np.load(argv[0], allow_pickle=False) as data:
        points, tets = mesh_volume(data["vertices"], data["faces"], float(data["maxh"]), int(data["optsteps"]))
    np.savez(argv[1], points=points, tets=tets)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
