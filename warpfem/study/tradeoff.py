"""Speed against accuracy, measured: sweeps of the knobs that cost time, and the quality presets.

The measured scene is a clamped cantilever (:class:`warpfem.study.reference.Cantilever`) released straight
under gravity: it swings down, is damped (Rayleigh mass damping) and settles at its static sag. A dense
surface point cloud (the beam's faces sampled on a fixed fine grid) is embedded in each coarse tet mesh
exactly as the pipeline embeds a dense mesh, and each setting is scored by

- its wall time per output frame (ms), frames after the first (which compiles or captures) only;
- the *trajectory error*: RMS over frames and dense points of the distance to the same points of a
  converged run (finest mesh, smallest step, CG to the tightest tolerance float32 reaches);
- the *sag error*: the final tip sag against NGSolve's converged geometrically nonlinear solution
  (:func:`warpfem.study.reference.converged_sag`), an independent reference.

A setting is one point of the sweep (:class:`Setting`); a knob is a field of it. New knobs (penalty
stiffness, once bodies collide) are new fields of :class:`Setting` read by :func:`run_setting`.
"""

from __future__ import annotations

import csv
import dataclasses
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from warpfem.errors import InputError
from warpfem.presets import PRESETS
from warpfem.study.reference import Cantilever

FPS = 60.0
"""Output frames per second of the measured scene."""

TIGHTEST_TOLERANCE = 1e-6
"""The tightest relative CG residual that float32 reaches reliably (1e-8, the textbook choice, does not)."""


@dataclass(frozen=True)
class Setting:
    """One point of a sweep: the knobs that cost time.

    Attributes:
        knob: Which knob this setting varies (a label for tables and plots).
        cells: Coarse-mesh resolution: cells across the beam's thickness (its length gets ``aspect`` times
            as many); the scene-file counterpart is an object's ``faces`` / ``maxh``.
        substeps: Simulation steps per output frame (dt = 1 / (60 substeps) s).
        cg_mode: ``"fixed"``: always ``cg_iterations`` iterations; ``"tolerance"``: iterate to ``cg_tolerance``.
        cg_iterations: The fixed count, or the cap in tolerance mode.
        cg_tolerance: Relative residual to stop at (tolerance mode only).
        rotation_updates: Solves of a step re-linearised about the rotations its last solve reached
            (``[solver] rotation_updates``; 0: one linear solve per step; None: the solver's default).
        elements: ``"linear"`` (4-node) or ``"quadratic"`` (10-node) tets (``[solver] elements``).
    """

    knob: str = "baseline"
    cells: int = 2
    substeps: int = 4
    cg_mode: str = "tolerance"
    cg_iterations: int = 200
    cg_tolerance: float = 1e-4
    rotation_updates: int | None = None
    elements: str = "linear"

    def __post_init__(self) -> None:
        if self.cells < 1 or self.substeps < 1 or self.cg_iterations < 1:
            raise InputError(f"cells, substeps and cg_iterations must be >= 1, got {self}")
        if self.rotation_updates is not None and self.rotation_updates < 0:
            raise InputError(f"rotation_updates must be >= 0, got {self.rotation_updates}")
        if self.cg_mode not in ("fixed", "tolerance"):
            raise InputError(f"cg_mode must be 'fixed' or 'tolerance', got {self.cg_mode!r}")
        if self.cg_mode == "tolerance" and not 0.0 < self.cg_tolerance < 1.0:
            raise InputError(f"cg_tolerance must be in (0, 1), got {self.cg_tolerance}")
        if self.elements not in ("linear", "quadratic"):
            raise InputError(f"elements must be 'linear' or 'quadratic', got {self.elements!r}")

    @property
    def dt(self) -> float:
        """The simulation time step (s)."""
        return 1.0 / (FPS * self.substeps)

    @property
    def label(self) -> str:
        """A short description, e.g. ``cells 2, 4 substeps, CG tol 1e-04`` (``, quadratic`` for 10-node tets)."""
        cg = f"CG {self.cg_iterations} it" if self.cg_mode == "fixed" else f"CG tol {self.cg_tolerance:.0e}"
        n = self.rotation_updates
        updates = "" if n is None else f", {n} rotation update{'' if n == 1 else 's'}"
        quadratic = ", quadratic" if self.elements == "quadratic" else ""
        return f"cells {self.cells}, {self.substeps} substeps, {cg}{updates}{quadratic}"


@dataclass(frozen=True)
class BeamScene:
    """The measured scene.

    Attributes:
        beam: The cantilever's geometry and material.
        aspect: Cells along the length per cell across the thickness.
        seconds: Simulated time (s).
        damping_mass: Rayleigh mass damping (1/s), enough to settle the beam within ``seconds``.
        dense_cells: Cells across the thickness of the fine grid whose surface vertices are the dense points.
    """

    beam: Cantilever = Cantilever()
    aspect: int = 10
    seconds: float = 2.0
    damping_mass: float = 6.0
    dense_cells: int = 8

    @property
    def frames(self) -> int:
        """Output frames simulated."""
        return round(self.seconds * FPS)

    def box(self, cells: int) -> tuple[np.ndarray, np.ndarray]:
        """The structured tet mesh of the beam with ``cells`` cells across its thickness."""
        from warpfem.prep.shapes import box_tet_mesh

        b = self.beam
        return box_tet_mesh((0, 0, 0), (b.length, b.height, b.width), (self.aspect * cells, cells, cells))

    def dense_points(self) -> np.ndarray:
        """The dense points (m): the surface vertices of a fine grid over the beam."""
        from warpfem.prep.tetmesh import boundary_faces

        vertices, tets = self.box(self.dense_cells)
        return vertices[np.unique(boundary_faces(tets))]


@dataclass(frozen=True)
class Run:
    """What one setting did.

    Attributes:
        setting: The setting.
        tets: Tets of the coarse mesh (of 4 or 10 nodes, as the setting's ``elements``).
        coarse_faces: Boundary triangles of the coarse mesh.
        ms_per_frame: Mean wall time per output frame after the first (ms): steps, dense mapping, read-back.
        cg_iterations_per_step: Mean CG iterations per step.
        points: (frames, n, 3) dense points at every output frame after frame 0 (m).
    """

    setting: Setting
    tets: int
    coarse_faces: int
    ms_per_frame: float
    cg_iterations_per_step: float
    points: np.ndarray


def run_setting(scene: BeamScene, setting: Setting, device: str | None = None) -> Run:
    """Simulate the scene with one setting, timing every frame.

    Raises:
        SimulationError: the state became NaN/Inf (the message names the frame).
    """
    from warpfem.build import add_body
    from warpfem.prep.embedding import embed
    from warpfem.prep.tetmesh import boundary_faces
    from warpfem.sim.model import ModelBuilder
    from warpfem.sim.solver import Solver
    from warpfem.simulation import Simulation

    beam = scene.beam
    vertices, tets = scene.box(setting.cells)
    faces = boundary_faces(tets)
    dense = scene.dense_points()
    dense_tet, dense_bary = embed(dense, vertices, tets, faces)
    builder = ModelBuilder()
    add_body(
        builder,
        "beam",
        vertices,
        tets,
        beam.young,
        beam.poisson,
        beam.density,
        damping_mass=scene.damping_mass,
        pinned=vertices[:, 0] < 1e-9 * beam.length,
        embed_tet=dense_tet,
        embed_bary=dense_bary,
        quadratic=setting.elements == "quadratic",
    )
    model = builder.finalize(device)
    solver = Solver(
        model,
        gravity=(0.0, -beam.gravity, 0.0),
        ground=None,
        cg_iterations=setting.cg_iterations,
        cg_tolerance=setting.cg_tolerance if setting.cg_mode == "tolerance" else 0.0,
        **({} if setting.rotation_updates is None else {"rotation_updates": setting.rotation_updates}),
    )
    sim = Simulation.from_model(model, solver, setting.substeps, FPS)
    points = np.empty((scene.frames, len(dense), 3), dtype=np.float32)
    seconds = []
    for frame in range(1, scene.frames + 1):
        t0 = time.perf_counter()
        sim.step_frame()
        points[frame - 1] = sim.dense_points()[0]  # reads back: the frame's work is done when this returns
        seconds.append(time.perf_counter() - t0)
    return Run(
        setting=setting,
        tets=len(tets),
        coarse_faces=len(faces),
        ms_per_frame=1e3 * float(np.mean(seconds[1:] if len(seconds) > 1 else seconds)),
        cg_iterations_per_step=sim.totals.cg_iterations / max(sim.totals.cg_solves, 1),
        points=points,
    )


def tip_sag(scene: BeamScene, points: np.ndarray) -> float:
    """Downward displacement of the dense points on the tip face (x = L), averaged (m)."""
    rest = scene.dense_points()
    tip = rest[:, 0] > scene.beam.length * (1.0 - 1e-9)
    return float(rest[tip, 1].mean() - points[tip, 1].mean())


@dataclass(frozen=True)
class Row:
    """One line of the tradeoff table.

    Attributes:
        run: The run (its setting, cost and trajectory).
        trajectory_error: RMS distance of the dense points to the converged run's, over all frames (m).
        sag: Final tip sag (m).
        sag_error: Relative deviation of ``sag`` from NGSolve's converged nonlinear sag.
        pareto: On the Pareto front of (ms per frame, trajectory error).
    """

    run: Run
    trajectory_error: float
    sag: float
    sag_error: float
    pareto: bool = False


def pareto_front(costs: np.ndarray, errors: np.ndarray) -> np.ndarray:
    """Mask of the points no other point beats: none is at most as costly and as wrong, and better in one."""
    costs, errors = np.asarray(costs, float), np.asarray(errors, float)
    dominated = (
        (costs[None, :] <= costs[:, None])
        & (errors[None, :] <= errors[:, None])
        & ((costs[None, :] < costs[:, None]) | (errors[None, :] < errors[:, None]))
    )
    return ~dominated.any(axis=1)


def score(scene: BeamScene, runs: list[Run], reference: Run, reference_sag: float) -> list[Row]:
    """Errors of each run against the converged run and the NGSolve sag, with the Pareto front marked."""
    rows = []
    for run in runs:
        deviation = np.linalg.norm(run.points - reference.points, axis=2)
        sag = tip_sag(scene, run.points[-1])
        rows.append(Row(run, float(np.sqrt(np.mean(deviation**2))), sag, abs(sag - reference_sag) / reference_sag))
    front = pareto_front([r.run.ms_per_frame for r in rows], [r.trajectory_error for r in rows])
    return [dataclasses.replace(r, pareto=bool(p)) for r, p in zip(rows, front, strict=True)]


def quick_settings() -> tuple[list[Setting], Setting]:
    """The CPU sweep (a few minutes) and its converged reference setting."""
    base = Setting()
    settings = [base]
    settings += [Setting("cg_iterations", cg_mode="fixed", cg_iterations=n) for n in (3, 10, 30, 100)]
    settings += [Setting("cg_tolerance", cg_tolerance=t, cg_iterations=1000) for t in (1e-1, 1e-2, 1e-3, 1e-5)]
    settings += [Setting("cells", cells=c) for c in (1, 3)]
    settings += [Setting("substeps", substeps=s) for s in (1, 2, 8)]
    settings += [Setting("rotation_updates", rotation_updates=r) for r in (0, 1)]
    settings += [Setting("elements", cells=c, elements="quadratic") for c in (1, 2)]
    settings += [
        Setting("combined", cells=1, substeps=1, cg_mode="fixed", cg_iterations=10),
        Setting("combined", cells=1, substeps=2, cg_tolerance=1e-2),
        Setting("combined", cells=3, substeps=2, cg_tolerance=1e-3),
        Setting("combined", cells=3, substeps=8, cg_tolerance=1e-5, cg_iterations=1000),
    ]
    return settings, converged(cells=3, substeps=16, cg_iterations=5000)


def full_settings() -> tuple[list[Setting], Setting]:
    """The GPU sweep: every knob over a wider range, and a grid of mesh x time step; a finer reference."""
    settings = [Setting()]
    settings += [Setting("cg_iterations", cg_mode="fixed", cg_iterations=n) for n in (2, 3, 5, 10, 20, 30, 50, 100)]
    settings += [
        Setting("cg_tolerance", cg_tolerance=t, cg_iterations=2000) for t in (1e-1, 3e-2, 1e-2, 1e-3, 1e-5, 1e-6)
    ]
    settings += [Setting("rotation_updates", substeps=n, rotation_updates=r) for n in (1, 4) for r in (0, 1, 4)]
    settings += [Setting("elements", cells=c, elements="quadratic") for c in (1, 2, 3, 4)]
    for cells in (1, 2, 3, 4, 6):
        for substeps in (1, 2, 4, 8, 16):
            for tol in (1e-2, 1e-4):
                settings.append(Setting("cells x substeps", cells=cells, substeps=substeps, cg_tolerance=tol))
    return settings, converged(cells=6, substeps=32, cg_iterations=10000)


def converged(cells: int, substeps: int, cg_iterations: int) -> Setting:
    """A converged run's setting: quadratic tets, CG to :data:`TIGHTEST_TOLERANCE`, 8 rotation updates."""
    return Setting(
        "reference",
        cells=cells,
        substeps=substeps,
        cg_tolerance=TIGHTEST_TOLERANCE,
        cg_iterations=cg_iterations,
        rotation_updates=8,
        elements="quadratic",
    )


def sweep(
    scene: BeamScene,
    settings: list[Setting],
    reference: Setting,
    device: str | None = None,
    progress: Callable[[str], None] | None = None,
    reference_sag: float | None = None,
) -> tuple[list[Row], Run, float]:
    """Run the reference and every setting; score them.

    Args:
        scene: The beam scene.
        settings: The settings to measure.
        reference: The converged setting the trajectories are compared with.
        device: Warp device.
        progress: Receives one-line progress messages.
        reference_sag: NGSolve's converged nonlinear sag (m) if already known (a machine without NGSolve, such
            as the GPU machine, takes the value computed elsewhere); None computes it here.

    Returns:
        The rows (in ``settings`` order), the reference run, and NGSolve's converged nonlinear sag (m).
    """
    say = progress or (lambda message: None)
    if reference_sag is None:
        from warpfem.study.reference import converged_sag

        say("NGSolve reference: nonlinear cantilever, raising the order until the sag settles")
        ngsolve_sag = converged_sag(scene.beam, nonlinear=True, rtol=1e-3, orders=(2, 3, 4)).sag
    else:
        ngsolve_sag = reference_sag
    say(f"converged run: {reference.label}")
    ref = run_setting(scene, reference, device)
    runs = []
    for k, setting in enumerate(settings):
        say(f"[{k + 1}/{len(settings)}] {setting.label}")
        runs.append(run_setting(scene, setting, device))
    return score(scene, runs, ref, ngsolve_sag), ref, ngsolve_sag


PENALTIES = (1e4, 1e5, 1e6, 1e7, 1e8, 1e9)
"""Collision penalty stiffnesses (1/s^2) of the contact sweep."""


@dataclass(frozen=True)
class ContactRow:
    """One penalty setting of the contact sweep: a 0.15 m cube dropped 0.1 m onto a 0.2 m cube on the ground.

    Attributes:
        stiffness: Collision penalty per unit mass (1/s^2).
        ms_per_frame: Wall time per 1/60 s frame (4 substeps, CG to 1e-4).
        impact_depth: Deepest contact over the run (m): the penetration at impact.
        resting_depth: Deepest contact over the last half second (m): the penetration at rest.
        cg_iterations_per_step: Mean CG iterations per step (stiffer contacts cost iterations).
        pareto: On the front of time against impact depth.
    """

    stiffness: float
    ms_per_frame: float
    impact_depth: float
    resting_depth: float
    cg_iterations_per_step: float
    pareto: bool = False


def contact_sweep(device: str | None = None, frames: int = 120, cells: int = 3) -> list[ContactRow]:
    """Time and penetration of a cube stacked on a cube for each of :data:`PENALTIES`."""
    from warpfem.build import add_body
    from warpfem.prep.shapes import box_tet_mesh
    from warpfem.sim.collision import CollisionSettings
    from warpfem.sim.model import ModelBuilder
    from warpfem.sim.solver import Ground, Solver
    from warpfem.simulation import Simulation

    rows = []
    for stiffness in PENALTIES:
        builder = ModelBuilder()
        add_body(
            builder,
            "a",
            *box_tet_mesh((0, 0, 0), (0.2, 0.2, 0.2), (cells,) * 3),
            1e5,
            0.3,
            1000.0,
            damping_stiffness=0.01,
        )
        add_body(
            builder,
            "b",
            *box_tet_mesh((0.025, 0.3, 0.025), (0.175, 0.45, 0.175), (cells,) * 3),
            1e5,
            0.3,
            1000.0,
            damping_stiffness=0.01,
        )
        model = builder.finalize(device)
        solver = Solver(
            model,
            ground=Ground(),
            cg_iterations=500,
            cg_tolerance=1e-4,
            collision=CollisionSettings(stiffness=stiffness),
        )
        sim = Simulation.from_model(model, solver, 4, FPS)
        seconds, impact, resting = [], 0.0, 0.0
        for frame in range(1, frames + 1):
            t0 = time.perf_counter()
            deepest = sim.step_frame().deepest_contact
            seconds.append(time.perf_counter() - t0)
            impact = max(impact, deepest)
            if frame > frames - FPS / 2:
                resting = max(resting, deepest)
        totals = sim.totals
        rows.append(
            ContactRow(
                stiffness,
                1e3 * float(np.mean(seconds[1:])),
                impact,
                resting,
                totals.cg_iterations / max(totals.cg_solves, 1),
            )
        )
    front = pareto_front(np.array([r.ms_per_frame for r in rows]), np.array([r.impact_depth for r in rows]))
    return [dataclasses.replace(r, pareto=bool(on)) for r, on in zip(rows, front, strict=True)]


def pyplot():
    """matplotlib's pyplot on the headless Agg backend.

    Raises:
        InputError: matplotlib is not installed (it is the optional ``plot`` extra).
    """
    try:
        import matplotlib
    except ImportError:
        raise InputError(
            "drawing the tradeoff plot needs matplotlib: pip install 'warpfem[plot]' (or pass --no-plot)"
        ) from None
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_contact(path: Path, rows: list[ContactRow], title: str) -> None:
    """Plot penetration at impact and at rest against time per frame, one point per penalty (PNG)."""
    plt = pyplot()

    fig, ax = plt.subplots(figsize=(7, 5), layout="constrained")
    cost = np.array([r.ms_per_frame for r in rows])
    for key, label, marker in (("impact_depth", "at impact", "o"), ("resting_depth", "at rest", "s")):
        depth = np.array([1e3 * max(getattr(r, key), 1e-6) for r in rows])
        ax.plot(cost, depth, marker=marker, label=f"penetration {label}")
        for r, x, y in zip(rows, cost, depth, strict=True):
            ax.annotate(f"{r.stiffness:.0e}", (x, y), textcoords="offset points", xytext=(4, 4), fontsize=7)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("wall time per frame (ms)")
    ax.set_ylabel("deepest contact (mm)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.suptitle(title)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write_contact_csv(path: Path, rows: list[ContactRow]) -> None:
    """Write the contact sweep, one row per penalty stiffness."""
    with open(path, "w", newline="") as f:
        out = csv.writer(f)
        out.writerow(
            [
                "penalty_per_unit_mass",
                "ms_per_frame",
                "impact_depth_m",
                "resting_depth_m",
                "cg_iterations_per_step",
                "pareto",
            ]
        )
        for r in rows:
            out.writerow(
                [
                    f"{r.stiffness:.0e}",
                    f"{r.ms_per_frame:.4g}",
                    f"{r.impact_depth:.4g}",
                    f"{r.resting_depth:.4g}",
                    f"{r.cg_iterations_per_step:.4g}",
                    int(r.pareto),
                ]
            )


CSV_FIELDS = (
    "knob",
    "cells",
    "tets",
    "coarse_faces",
    "substeps",
    "dt_s",
    "cg_mode",
    "cg_iterations",
    "cg_tolerance",
    "rotation_updates",
    "elements",
    "ms_per_frame",
    "cg_iterations_per_step",
    "trajectory_error_m",
    "sag_m",
    "sag_error",
    "pareto",
)


def write_csv(path: Path, rows: list[Row]) -> None:
    """Write the tradeoff table, one row per setting (columns: :data:`CSV_FIELDS`)."""
    with open(path, "w", newline="") as f:
        out = csv.writer(f)
        out.writerow(CSV_FIELDS)
        for r in rows:
            s = r.run.setting
            out.writerow(
                [
                    s.knob,
                    s.cells,
                    r.run.tets,
                    r.run.coarse_faces,
                    s.substeps,
                    f"{s.dt:.6g}",
                    s.cg_mode,
                    s.cg_iterations,
                    f"{s.cg_tolerance:.0e}" if s.cg_mode == "tolerance" else "",
                    "default" if s.rotation_updates is None else s.rotation_updates,
                    s.elements,
                    f"{r.run.ms_per_frame:.4g}",
                    f"{r.run.cg_iterations_per_step:.4g}",
                    f"{r.trajectory_error:.4g}",
                    f"{r.sag:.5g}",
                    f"{r.sag_error:.4g}",
                    int(r.pareto),
                ]
            )


def read_csv(path: Path) -> list[SimpleNamespace]:
    """Rows of a tradeoff.csv with what :func:`plot` reads (knob, ms per frame, both errors)."""
    with open(path, newline="") as f:
        return [
            SimpleNamespace(
                run=SimpleNamespace(setting=SimpleNamespace(knob=r["knob"]), ms_per_frame=float(r["ms_per_frame"])),
                trajectory_error=float(r["trajectory_error_m"]),
                sag_error=float(r["sag_error"]),
            )
            for r in csv.DictReader(f)
        ]


def plot(path: Path, rows: list[Row], title: str) -> None:
    """Plot trajectory error and sag error against time per frame (log-log), the Pareto front marked (PNG)."""
    plt = pyplot()

    fig, axes = plt.subplots(1, 2, figsize=(13, 5.5), layout="constrained")
    knobs = list(dict.fromkeys(r.run.setting.knob for r in rows))
    cost = np.array([r.run.ms_per_frame for r in rows])
    panels = (
        ([1e3 * r.trajectory_error for r in rows], "trajectory error vs converged run (mm RMS)"),
        ([100.0 * max(r.sag_error, 1e-4) for r in rows], "final sag error vs NGSolve nonlinear (%)"),
    )
    for ax, (error, ylabel) in zip(axes, panels, strict=True):
        error = np.asarray(error)
        for k, knob in enumerate(knobs):
            mask = np.array([r.run.setting.knob == knob for r in rows])
            ax.scatter(cost[mask], error[mask], label=knob, color=f"C{k}", s=28, zorder=3)
        front = pareto_front(cost, error)
        order = np.argsort(cost[front])
        ax.plot(cost[front][order], error[front][order], "k--", lw=1, zorder=2, label="Pareto front")
        ax.scatter(cost[front], error[front], facecolors="none", edgecolors="k", s=90, zorder=4)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("wall time per frame (ms)")
        ax.set_ylabel(ylabel)
        ax.grid(True, which="both", alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.suptitle(title)
    fig.savefig(path, dpi=110)
    plt.close(fig)


PRESET_CELLS = {"preview": 1, "default": 2, "high": 4}
"""The beam's cells across its thickness standing in for each preset's ``tets_across`` (preview, which sizes by
``faces``/``maxh``, by one cell)."""

PRESET_SETTINGS: dict[str, Setting] = {
    name: Setting(
        f"preset {name}",
        cells=PRESET_CELLS[name],
        substeps=int(p["substeps"]),
        cg_mode=str(p["cg_mode"]),
        cg_iterations=int(p["cg_iterations"]),
        cg_tolerance=float(p["cg_tolerance"]),
        elements=str(p["elements"]),
    )
    for name, p in PRESETS.items()
}
"""The measured-scene counterpart of each preset (:data:`warpfem.presets.PRESETS`): its step, CG and elements on
the beam at :data:`PRESET_CELLS`."""
