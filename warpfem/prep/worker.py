"""Preprocessing stages run in a child process under a time limit: ``python -m warpfem.prep.worker TASK IN OUT``.

Netgen can hang, print 'SYSTEM ERROR' or abort the whole process ('double free or corruption') on bad
input, and QEM on a large mesh can run long, so these stages run in a child: a crash, hang or timeout
there becomes an :class:`~warpfem.errors.InputError` in the parent (or the next rung of the retry
ladder), never the end of the caller's process. IN.npz holds the task's input arrays, OUT.npz receives
its outputs; the child's console output (Netgen's log) is returned for error messages.

Tasks:
    ``netgen``: ``vertices`` (n, 3) float64, ``faces`` (m, 3) int32 outward, ``maxh``, ``optsteps`` ->
        ``points`` (p, 3) float64 (the n surface points first) and 0-based ``tets`` (q, 4) int32.
    ``qslim``: ``vertices``, ``faces``, ``target``, optional ``first`` -> ``vertices``, ``faces`` (libigl's
        qslim with intersection blocking, unreferenced vertices kept; from ``first`` faces made by a fast QEM
        where given).
    ``outer``: ``vertices``, ``faces``, ``cells`` -> ``vertices``, ``faces``: the 1/2 level set of the
        generalized winding number (``igl.fast_winding_number``) sampled on a grid with ``cells`` cells
        along the longest side, by marching cubes.
    ``remesh``: ``vertices``, ``faces``, ``target`` -> ``vertices``, ``faces``: Netgen's STL surface mesh of
        the surface, its element size chosen for about ``target`` triangles.
"""

from __future__ import annotations

import signal
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from warpfem.errors import InputError


def last_message(log: str) -> str:
    """Return the last non-empty line of a child's console output (or a placeholder)."""
    lines = [line.strip() for line in log.splitlines() if line.strip()]
    return lines[-1] if lines else "no output"


def run_in_child(
    task: str, inputs: dict[str, np.ndarray], timeout_s: float, name: str, stage: str
) -> tuple[dict[str, np.ndarray], str]:
    """Run ``task`` in a child Python process and return its output arrays and console output.

    Args:
        task: ``"netgen"``, ``"qslim"``, ``"outer"`` or ``"remesh"``.
        inputs: The task's input arrays.
        timeout_s: Wall-clock limit, in seconds; the child is killed when it is exceeded.
        name: Name of the mesh for error messages.
        stage: Name of the stage for error messages (e.g. "Netgen").

    Returns:
        ``(outputs, log)``.

    Raises:
        InputError: If the child times out, is killed by a signal, or exits non-zero (one line).
    """
    with tempfile.TemporaryDirectory(prefix=f"warpfem-{task}-") as tmp:
        src, dst = Path(tmp) / "in.npz", Path(tmp) / "out.npz"
        np.savez(src, **inputs)
        try:
            proc = subprocess.run(
                [sys.executable, "-m", "warpfem.prep.worker", task, str(src), str(dst)],
                stdin=subprocess.DEVNULL,
                stdout=subprocess.PIPE,
                stderr=subprocess.STDOUT,
                text=True,
                errors="replace",
                timeout=timeout_s,
                cwd=tmp,
            )
        except subprocess.TimeoutExpired as exc:
            raise InputError(f"{name}: {stage} did not finish within {timeout_s:g} s") from exc
        if proc.returncode < 0:
            sig = signal.Signals(-proc.returncode).name
            raise InputError(f"{name}: {stage} crashed ({sig}); last output: {last_message(proc.stdout)}")
        if proc.returncode != 0 or not dst.exists():
            raise InputError(f"{name}: {stage} failed (exit {proc.returncode}): {last_message(proc.stdout)}")
        with np.load(dst, allow_pickle=False) as data:
            return {key: np.array(data[key]) for key in data.files}, proc.stdout


def mesh_volume(vertices: np.ndarray, faces: np.ndarray, maxh: float, optsteps: int) -> tuple[np.ndarray, np.ndarray]:
    """Fill a closed surface with tetrahedra, keeping the surface triangles as the boundary.

    Several disjoint closed shells are meshed together (one face descriptor, domain 1 inside each).

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


def qslim(vertices: np.ndarray, faces: np.ndarray, target: int, first: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Run libigl's QEM simplification with intersection blocking; return its (V, F).

    ``first`` > 0: reduce the surface to that many faces first with fast-simplification's QEM, which does not
    block intersections and is much faster; the blocked QEM then works on that.
    """
    import igl

    if first > 0:
        import fast_simplification

        vertices, faces = fast_simplification.simplify(
            np.asarray(vertices, dtype=np.float64), np.asarray(faces, dtype=np.int32), target_count=int(first)
        )
    out_v, out_f, _, _ = igl.qslim(
        np.asfortranarray(vertices, dtype=np.float64), np.asfortranarray(faces, dtype=np.int64), int(target), True
    )
    return np.asarray(out_v, dtype=np.float64), np.asarray(out_f, dtype=np.int64)


def outer_surface(vertices: np.ndarray, faces: np.ndarray, cells: int) -> tuple[np.ndarray, np.ndarray]:
    """Return the marching-cubes 1/2 level set of the generalized winding number of a triangle soup.

    Args:
        vertices: (n, 3) positions.
        faces: (m, 3) triangles, outward (self-intersections and nested shells allowed).
        cells: Grid cells along the bounding box's longest side.

    Returns:
        ``(V, F)`` of the extracted surface, wound like ``faces``.
    """
    import igl

    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    step = float((hi - lo).max()) / cells
    lo = lo - 2.0 * step
    counts = np.ceil((hi + 2.0 * step - lo) / step).astype(int) + 1
    axes = [lo[k] + step * np.arange(counts[k]) for k in range(3)]
    gz, gy, gx = np.meshgrid(axes[2], axes[1], axes[0], indexing="ij")  # x varies fastest
    grid = np.column_stack([gx.reshape(-1), gy.reshape(-1), gz.reshape(-1)])
    winding = igl.fast_winding_number(vertices, faces.astype(np.int64), grid)
    out_v, out_f, _ = igl.marching_cubes(-winding, grid, int(counts[0]), int(counts[1]), int(counts[2]), -0.5)
    return np.asarray(out_v, dtype=np.float64), np.asarray(out_f, dtype=np.int64)


REMESH_TRIES = 3
"""Netgen surface meshes made to approach the target count (each rescales the element size)."""


def _write_stl(path: Path, vertices: np.ndarray, faces: np.ndarray) -> None:
    """Write a binary STL (normals from the winding)."""
    corners = vertices[faces].astype(np.float32)
    normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-30)
    records = np.zeros(len(faces), dtype=[("n", "<f4", 3), ("v", "<f4", (3, 3)), ("attr", "<u2")])
    records["n"], records["v"] = normals, corners
    with open(path, "wb") as stream:
        stream.write(b"warpfem remesh".ljust(80, b" ") + np.uint32(len(faces)).tobytes() + records.tobytes())


def remesh_surface(vertices: np.ndarray, faces: np.ndarray, target: int) -> tuple[np.ndarray, np.ndarray]:
    """Netgen's STL surface mesh of a closed surface, with about ``target`` triangles where its features allow.

    The element size starts at that of ``target`` equilateral triangles covering the area and is rescaled
    by the square root of the count's ratio to the target, up to :data:`REMESH_TRIES` meshes.
    """
    from netgen.meshing import MeshingStep
    from netgen.stl import STLGeometry

    path = Path("surface.stl")
    _write_stl(path, vertices, faces)
    corners = vertices[faces]
    area = 0.5 * np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1).sum()
    size = float(np.sqrt(4.0 * area / (np.sqrt(3.0) * target)))
    best = None
    for _ in range(REMESH_TRIES):
        mesh = STLGeometry(str(path)).GenerateMesh(maxh=size, perfstepsend=MeshingStep.MESHSURFACE)
        points = np.array(mesh.Coordinates(), dtype=np.float64, copy=True).reshape(-1, 3)
        tris = np.array(mesh.Elements2D().NumPy()["nodes"], dtype=np.int64, copy=True)[:, :3] - 1
        if best is None or abs(np.log(len(tris) / target)) < abs(np.log(len(best[1]) / target)):
            best = (points, tris)
        ratio = len(tris) / target
        if 0.8 < ratio < 1.25:
            break
        size *= float(np.sqrt(ratio))
    return best


def main(argv: list[str]) -> int:
    """Read IN.npz, run the task, write OUT.npz; return the process exit code."""
    if len(argv) != 3 or argv[0] not in ("netgen", "qslim", "outer", "remesh"):
        print("usage: python -m warpfem.prep.worker netgen|qslim|outer|remesh IN.npz OUT.npz", file=sys.stderr)
        return 2
    task, src, dst = argv
    with np.load(src, allow_pickle=False) as data:
        inputs = {key: np.array(data[key]) for key in data.files}
    vertices, faces = inputs["vertices"].astype(np.float64), inputs["faces"]
    if task == "netgen":
        points, tets = mesh_volume(vertices, faces, float(inputs["maxh"]), int(inputs["optsteps"]))
        np.savez(dst, points=points, tets=tets)
    elif task == "remesh":
        out_v, out_f = remesh_surface(vertices, faces, int(inputs["target"]))
        np.savez(dst, vertices=out_v, faces=out_f)
    elif task == "qslim":
        out_v, out_f = qslim(vertices, faces.astype(np.int32), int(inputs["target"]), int(inputs.get("first", 0)))
        np.savez(dst, vertices=out_v, faces=out_f)
    else:
        out_v, out_f = outer_surface(vertices, faces, int(inputs["cells"]))
        np.savez(dst, vertices=out_v, faces=out_f)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
