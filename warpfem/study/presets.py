"""The quality presets measured through the whole pipeline: a clamped beam given as a dense surface mesh.

A user's view of a preset: a dense triangulated cantilever (:class:`~warpfem.study.reference.Cantilever`)
goes through preprocessing (QEM, Netgen, embedding) with ``[solver] quality`` set and nothing else, is held
at x <= 0 by a still ``[[handle]]``, sags under gravity with Rayleigh mass damping until it settles, and
the settled sag of the dense mesh's tip is compared with NGSolve's converged nonlinear answer.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from warpfem.study.reference import Cantilever

DENSE_SPACING = 0.01
"""Largest edge of the dense beam surface (m): 56,320 triangles for the 1 x 0.1 x 0.1 m beam."""

SETTLE_DAMPING = 20.0
"""Rayleigh mass damping (1/s) of the measurement: about critical for the beam's first bending mode
(1.6 Hz), so it settles within a second."""

SETTLE_SECONDS = 1.5
"""Simulated time before the sag is read (s)."""


@dataclass(frozen=True)
class PresetPoint:
    """What one preset made of the beam and how far it sagged.

    Attributes:
        preset: The preset's name.
        tets: Tets of the simulated mesh.
        coarse_faces: Faces of the coarse (simplified) surface.
        ms_per_frame: Mean wall time per output frame after the first (ms).
        sag: Settled tip sag of the dense mesh (m, downwards).
        sag_error: ``sag / reference - 1`` (negative: too stiff).
        elements: The tets' elements, ``"linear"`` or ``"quadratic"``.
    """

    preset: str
    tets: int
    coarse_faces: int
    ms_per_frame: float
    sag: float
    sag_error: float
    elements: str = "linear"


def beam_surface(beam: Cantilever, spacing: float = DENSE_SPACING) -> tuple[np.ndarray, np.ndarray]:
    """A closed triangulated surface of the beam ``[0, L] x [0, h] x [0, w]``, no edge longer than ``spacing`` (m)."""
    import trimesh

    box = trimesh.creation.box(extents=(beam.length, beam.height, beam.width))
    box.apply_translation((beam.length / 2, beam.height / 2, beam.width / 2))
    vertices, faces = trimesh.remesh.subdivide_to_size(box.vertices, box.faces, max_edge=spacing)
    mesh = trimesh.Trimesh(vertices, faces, process=True)
    return np.asarray(mesh.vertices), np.asarray(mesh.faces)


def write_beam(path: Path, beam: Cantilever, spacing: float = DENSE_SPACING) -> Path:
    """Write :func:`beam_surface` as an OBJ file; return ``path``."""
    import trimesh

    vertices, faces = beam_surface(beam, spacing)
    trimesh.Trimesh(vertices, faces, process=False).export(path)
    return Path(path)


def beam_scene(mesh: Path, preset: str, beam: Cantilever, seconds: float = SETTLE_SECONDS, elements: str | None = None):
    """The scene: the beam from ``mesh`` with ``quality = preset``, held still at x <= 0, no ground.

    ``elements``: ``[solver] elements`` instead of the preset's.
    """
    from warpfem.scene import Scene

    fps = 60.0
    margin = beam.length  # the handle's box reaches well past the beam except at its clamped end
    doc = {
        "scene": {"frames": round(seconds * fps), "fps": fps, "gravity": [0.0, -beam.gravity, 0.0]},
        "solver": {"quality": preset} | ({} if elements is None else {"elements": elements}),
        "ground": {"enabled": False},
        "object": [
            {
                "name": "beam",
                "mesh": str(mesh),
                "young": beam.young,
                "poisson": beam.poisson,
                "density": beam.density,
                "damping_mass": SETTLE_DAMPING,
            }
        ],
        "handle": [
            {
                "object": "beam",
                "min": [-margin, -margin, -margin],
                "max": [1e-6 * beam.length, margin, margin],
                "keys": [[0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]],
            }
        ],
    }
    return Scene.from_dict(doc, base_dir=str(Path(mesh).parent), name=f"beam-{preset}")


def tip_sag(rest: np.ndarray, now: np.ndarray, beam: Cantilever) -> float:
    """Mean downward displacement of the dense vertices on the tip face x = L (m)."""
    tip = rest[:, 0] > beam.length * (1.0 - 1e-6)
    return float(-(now[tip, 1] - rest[tip, 1]).mean())


def measure(
    preset: str,
    mesh: Path,
    reference_sag: float,
    cache_dir: Path,
    beam: Cantilever | None = None,
    device: str = "cpu",
    elements: str | None = None,
) -> PresetPoint:
    """Prepare and simulate the beam at ``preset``; score its settled dense tip sag against ``reference_sag`` (m).

    ``cache_dir`` is the preprocessing cache (the body is prepared once, for its stats, then read back);
    ``beam``: default :class:`~warpfem.study.reference.Cantilever`; ``elements``: instead of the preset's.
    """
    from warpfem.build import prepare_scene
    from warpfem.simulation import Simulation

    beam = beam or Cantilever()
    scene = beam_scene(mesh, preset, beam, elements=elements)
    stats = prepare_scene(scene, cache_dir)[0].stats
    sim = Simulation(scene, device=device, cache_dir=cache_dir)
    rest = np.asarray(sim.dense_points("beam"), dtype=np.float64)
    seconds = []
    for _ in range(scene.frames):
        start = time.perf_counter()
        sim.step_frame()
        seconds.append(time.perf_counter() - start)
    sag = tip_sag(rest, np.asarray(sim.dense_points("beam"), dtype=np.float64), beam)
    ms = 1e3 * float(np.mean(seconds[1:]))
    tets, faces = int(stats["tets"]), int(stats["coarse_faces"])
    return PresetPoint(preset, tets, faces, ms, sag, sag / reference_sag - 1.0, scene.solver.elements)
