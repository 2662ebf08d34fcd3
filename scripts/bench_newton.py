"""Benchmark peer: the piles of scripts/bench.py run with Newton 1.8 (``SolverVBD``), same tet meshes.

Each pile is the one ``scripts/bench.py`` builds (``pile``: N armadillos of 541 tets, E 1e6 Pa,
nu 0.3, density 1000, dropped from 0.7 m), each body preprocessed by ``warpfem.prep.pipeline.prepare`` and
placed exactly as ``warpfem.build.add_prepared_body`` places it (x = scale * x @ R.T + t). Newton
then gets a ground plane (y up, gravity -9.81 m/s^2), every body as ``ModelBuilder.add_soft_mesh``
(Lame mu and lambda from E and nu), and ``SolverVBD`` with particle self-contact, 10 substeps x 10
iterations per 1/60 s frame. Time per frame is taken after 2 warm-up frames over ``--frames`` frames, the
substep loop replayed as a captured CUDA graph on GPUs (as Newton's examples do). Alongside it: the
lowest particle height at the end (below 0: into the ground), whether any position is NaN, and the dense
meshes carried by Newton's tets checked as ``scripts/bench.py`` checks ours (inside another body, below the
ground; over the run and at its end), in a second run of the same frames with its kernels launched one by one.

    python scripts/bench_newton.py --quick     # CPU, N=1 bunny, 3 frames: tests the harness itself
    python scripts/bench_newton.py --assets ../shared/assets --cache-dir .warpfem-cache   # GPU, all piles
    python scripts/bench_newton.py --piles 4,64 --frames 120 --out scripts/results

Writes ``bench-newton-<device>-<stamp>.json`` under ``--out`` with the environment block of bench.py.
Needs ``newton`` (PyPI, pure Python on top of warp-lang); warpfem's own bench does not.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import warp as wp

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "scripts"))

from bench import PILES, end_gap, environment, int_list, pile  # noqa: E402
from bench_check import CHECK_MAX_BODIES, FrameChecks, checked_frames  # noqa: E402

import warpfem  # noqa: E402
from warpfem.build import euler_rotation  # noqa: E402
from warpfem.prep.pipeline import prepare  # noqa: E402

FPS = 60.0


def lame(young: float, poisson: float) -> tuple[float, float]:
    """Lame (mu, lambda) in Pa of Young's modulus and Poisson's ratio."""
    mu = young / (2.0 * (1.0 + poisson))
    lam = young * poisson / ((1.0 + poisson) * (1.0 - 2.0 * poisson))
    return mu, lam


def prepared_bodies(objects, cache_dir: Path | None) -> list:
    """Each object's ``warpfem.prep.pipeline.PreparedBody`` (prepared once per mesh and settings)."""
    prepared = {}
    for obj in objects:
        key = (obj.mesh, obj.faces, obj.subdivide, obj.maxh)
        if key not in prepared:
            prepared[key] = prepare(
                obj.mesh, faces=obj.faces, subdivide=obj.subdivide, maxh=obj.maxh, cache_dir=cache_dir
            )
    return [prepared[(obj.mesh, obj.faces, obj.subdivide, obj.maxh)] for obj in objects]


def placed_meshes(objects, cache_dir: Path | None) -> list[tuple[np.ndarray, np.ndarray]]:
    """World tet vertices and tets of each object, placed as ``warpfem.build.add_prepared_body`` does."""
    meshes = []
    for obj, body in zip(objects, prepared_bodies(objects, cache_dir), strict=True):
        rot = euler_rotation(obj.rotate)
        x = obj.scale * body.tet_vertices @ rot.T + np.asarray(obj.translate, dtype=np.float64)
        meshes.append((x, np.asarray(body.tets, dtype=np.int32)))
    return meshes


class NewtonDenseCheck:
    """The dense meshes carried by Newton's tets, checked as ``scripts/bench.py`` checks ours.

    Each body's dense vertices follow its tets with the barycentric weights of warpfem's preprocessing (the tet
    meshes Newton runs are the same), so the check sees what a user rendering the dense meshes from Newton's run
    would. The frames are those ``scripts/bench.py`` checks in a run of as many frames.
    """

    def __init__(self, objects, cache_dir: Path | None, device, run_frames: int):
        from warpfem.io.penetration import PenetrationCheck

        bodies = prepared_bodies(objects, cache_dir)
        starts = np.cumsum([0] + [len(b.tet_vertices) for b in bodies])
        self.corners = [start + b.tets[b.embed_tet] for start, b in zip(starts, bodies, strict=False)]
        self.weights = [b.embed_bary for b in bodies]
        self.check = PenetrationCheck([b.dense_faces for b in bodies], [o.name for o in objects], device)
        self.frames = set(checked_frames(run_frames, 0) if len(objects) <= CHECK_MAX_BODIES else [run_frames])
        self.checks = FrameChecks(run_frames)

    def after(self, frame: int, particles) -> None:
        """Frame ``frame`` has run, its particles in ``particles``: check it if it is one of the checked frames."""
        if frame in self.frames:
            q = np.asarray(particles.numpy(), np.float64)
            points = [np.einsum("nk,nkj->nj", w, q[c]) for c, w in zip(self.corners, self.weights, strict=True)]
            self.checks.add(frame, self.check.measure(points, ground=(0.0, (0.0, 1.0, 0.0))))

    def result(self) -> dict:
        """The same JSON as ``bench_check.FrameChecks``."""
        return self.checks.result()


def build_model(objects, meshes, device, settings: dict):
    """Newton model of the pile: ground plane at y = 0, each body a soft tet mesh, colored for VBD."""
    import newton

    builder = newton.ModelBuilder(up_axis=newton.Axis.Y)  # gravity: -9.81 along y
    builder.add_ground_plane()
    for obj, (x, tets) in zip(objects, meshes, strict=True):
        mu, lam = lame(obj.young, obj.poisson)
        builder.add_soft_mesh(
            pos=(0.0, 0.0, 0.0),
            rot=wp.quat_identity(),
            scale=1.0,
            vel=tuple(float(v) for v in obj.velocity) if obj.velocity is not None else (0.0, 0.0, 0.0),
            vertices=x.tolist(),
            indices=tets.reshape(-1).tolist(),
            density=obj.density,
            k_mu=mu,
            k_lambda=lam,
            # VBD's damping is a viscosity (Pa s) on the rate of F^T F; ours is Rayleigh beta (s) times the
            # stiffness: beta * mu is the matching order of magnitude.
            k_damp=settings["k_damp_per_mu_s"] * mu,
            particle_radius=settings["particle_radius_m"],
            label=obj.name,
        )
    builder.color()
    model = builder.finalize(device=device)
    model.soft_contact_ke = settings["contact_ke"]
    model.soft_contact_kd = settings["contact_kd"]
    model.soft_contact_mu = settings["contact_mu"]
    return model


def pile_stepper(objects, device, cache_dir: Path | None, settings: dict):
    """The Newton model of a pile and a function advancing it one frame (a replayed CUDA graph on GPUs).

    Returns (model, frame, state, graph): ``state[0]`` holds the current particles after each frame, graph
    says whether frames replay a CUDA graph. The first frame is run here (it captures the graph, or compiles
    the kernels without one).
    """
    import newton

    meshes = placed_meshes(objects, cache_dir)
    model = build_model(objects, meshes, device, settings)
    expected_tets = sum(len(t) for _, t in meshes)
    if model.tet_count != expected_tets:  # Newton drops tets of non-positive volume with a warning
        raise RuntimeError(f"Newton kept {model.tet_count} of {expected_tets} tets")
    tile = settings["tile_solve"]
    solver = newton.solvers.SolverVBD(
        model,
        iterations=settings["iterations"],
        particle_enable_self_contact=settings["self_contact"],
        particle_self_contact_margin=settings["self_contact_margin_m"],
        particle_self_contact_gap=settings["self_contact_gap_m"],
        particle_enable_tile_solve=device.is_cuda if tile == "auto" else tile == "on",
    )
    pipeline = newton.CollisionPipeline(model)
    contacts = pipeline.contacts()
    state = [model.state(), model.state()]
    control = model.control()
    substeps = settings["substeps"]
    dt = 1.0 / (FPS * substeps)

    def simulate():
        for _ in range(substeps):
            state[0].clear_forces()
            pipeline.collide(state[0], contacts)
            solver.step(state[0], state[1], control, contacts, dt)
            state[0], state[1] = state[1], state[0]

    graph = None
    if device.is_cuda and settings["graph"]:
        if substeps % 2:  # the captured swaps must bring the states back to where they began
            raise ValueError("a CUDA graph needs an even substep count (or --no-graph)")
        with wp.ScopedCapture(device=device) as capture:
            simulate()
        graph = capture.graph
    frame = (lambda: wp.capture_launch(graph)) if graph is not None else simulate
    frame()  # with no graph: the first frame compiles and loads the kernels
    wp.synchronize_device(device)
    return model, frame, state, graph is not None


def time_pile(objects, device, cache_dir: Path | None, frames: int, settings: dict, warmup: int = 2) -> dict:
    """Per-frame time of N bodies under SolverVBD, sizes, lowest particle and NaN check."""
    t0 = time.perf_counter()
    model, frame, state, graph = pile_stepper(objects, device, cache_dir, settings)
    first_frame_s = time.perf_counter() - t0
    for _ in range(warmup - 1):
        frame()
    wp.synchronize_device(device)
    t0 = time.perf_counter()
    for _ in range(frames):
        frame()
    wp.synchronize_device(device)
    ms = 1000.0 * (time.perf_counter() - t0) / frames
    q = state[0].particle_q.numpy()
    finite = bool(np.isfinite(q).all())
    return {
        "ms_per_frame": ms,
        "fps": 1000.0 / ms,
        "frames_timed": frames,
        "warmup_frames": warmup,
        "substeps": settings["substeps"],
        "iterations": settings["iterations"],
        "cuda_graph": graph,
        "bodies": len(objects),
        "tets": int(model.tet_count),
        "particles": int(model.particle_count),
        "surface_triangles": int(model.tri_count),
        "lowest_point_m": float(np.nanmin(q[:, 1])) if finite else float("nan"),
        "nan": not finite,
        "build_and_first_frame_s": first_frame_s,
    }


def check_pile(objects, device, cache_dir: Path | None, frames: int, settings: dict) -> dict | None:
    """The dense meshes of a run of ``frames`` frames checked on the frames ``scripts/bench.py`` checks
    (:class:`NewtonDenseCheck`); None where the run went NaN.

    A run of its own, its kernels launched one by one: the timed run replays Newton's captured graph, whose
    replays fail once frames are read between them.
    """
    check = NewtonDenseCheck(objects, cache_dir, device, frames)
    _, frame, state, _ = pile_stepper(objects, device, cache_dir, {**settings, "graph": False})
    check.after(1, state[0].particle_q)
    for f in range(2, frames + 1):
        frame()
        check.after(f, state[0].particle_q)
    return check.result() if np.isfinite(state[0].particle_q.numpy()).all() else None


def settle_deviation(objects, device, cache_dir: Path | None, frames: int, settings: dict) -> dict:
    """How far the bench settings end from a converged run (4x substeps, 4x iterations) after ``frames`` frames."""
    converged = {**settings, "substeps": 4 * settings["substeps"], "iterations": 4 * settings["iterations"]}
    ends = []
    for s in (settings, converged):
        _, frame, state, _ = pile_stepper(objects, device, cache_dir, s)
        for _ in range(frames - 1):  # pile_stepper ran the first
            frame()
        ends.append(state[0].particle_q.numpy())
    return {
        "frames": frames,
        "converged_substeps": converged["substeps"],
        "converged_iterations": converged["iterations"],
        **end_gap(*ends),
    }


def _parser() -> argparse.ArgumentParser:
    """The command line: the run, the piles and Newton's settings."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="CPU, N=1 small bunny, 3 frames: test the harness")
    parser.add_argument("--device", default=None)
    parser.add_argument("--assets", type=Path, default=ROOT.parent / "shared" / "assets")
    parser.add_argument("--cache-dir", type=Path, default=ROOT / ".warpfem-cache")
    parser.add_argument("--out", type=Path, default=ROOT / "scripts" / "results")
    parser.add_argument("--frames", type=int, default=120)
    parser.add_argument("--warmup", type=int, default=2)
    parser.add_argument("--piles", type=int_list, default=",".join(map(str, PILES)))
    parser.add_argument("--substeps", type=int, default=10)
    parser.add_argument("--iterations", type=int, default=10)
    parser.add_argument("--no-self-contact", action="store_true")
    parser.add_argument("--self-contact-margin", type=float, default=0.01, help="m: VBD interaction distance")
    parser.add_argument("--self-contact-gap", type=float, default=0.01, help="m: extra detection distance")
    parser.add_argument("--particle-radius", type=float, default=0.01, help="m: particle-ground contact distance")
    parser.add_argument("--contact-ke", type=float, default=1e5, help="N/m: model.soft_contact_ke")
    parser.add_argument("--contact-kd", type=float, default=0.5, help="model.soft_contact_kd")
    parser.add_argument("--contact-mu", type=float, default=0.5, help="model.soft_contact_mu")
    parser.add_argument("--k-damp-per-mu", type=float, default=0.005, help="s: k_damp = this * mu (Pa s)")
    parser.add_argument("--tile-solve", choices=("auto", "on", "off"), default="auto", help="auto: on on CUDA")
    parser.add_argument("--no-graph", action="store_true", help="launch kernels instead of a CUDA graph")
    parser.add_argument(
        "--deviation",
        type=int_list,
        default="1,4",
        help="comma list of pile sizes compared with a converged run ('' for none)",
    )
    return parser


def _settings(args: argparse.Namespace) -> dict:
    """Newton's settings for the run, as the JSON records them."""
    return {
        "solver": "SolverVBD",
        "substeps": args.substeps,
        "iterations": args.iterations,
        "self_contact": not args.no_self_contact,
        "self_contact_margin_m": args.self_contact_margin,
        "self_contact_gap_m": args.self_contact_gap,
        "particle_radius_m": args.particle_radius,
        "contact_ke": args.contact_ke,
        "contact_kd": args.contact_kd,
        "contact_mu": args.contact_mu,
        "k_damp_per_mu_s": args.k_damp_per_mu,
        "tile_solve": args.tile_solve,
        "graph": not args.no_graph,
        "up_axis": "Y",
        "gravity": -9.81,
        "fps": FPS,
    }


def main(argv=None) -> int:
    args = _parser().parse_args(argv)

    import newton

    wp.config.log_level = wp.LOG_WARNING
    wp.config.quiet = True
    device = wp.get_device(args.device or ("cpu" if args.quick else ("cuda:0" if wp.is_cuda_available() else "cpu")))
    settings = _settings(args)
    env = environment(device)
    env["newton"] = getattr(newton, "__version__", "unknown")
    results = {"environment": env, "mode": "quick" if args.quick else "full", "settings": settings, "runs": []}

    defaults = warpfem.load_scene(ROOT / "scenes" / "default.toml")
    if args.quick:
        work = [(1, pile(defaults, 1, "builtin:bunny", 300, scale=0.5).objects)]
        frames = 3
    else:
        armadillo = str((args.assets / "armadillo.off").resolve())
        work = [(n, pile(defaults, n, armadillo, 500).objects) for n in args.piles]
        frames = args.frames

    args.out.mkdir(parents=True, exist_ok=True)
    stamp = datetime.now(UTC).strftime("%Y%m%dT%H%M%SZ")
    path = args.out / f"bench-newton-{device.alias.replace(':', '')}-{stamp}.json"
    for n, objs in work:
        t0 = time.perf_counter()
        run = time_pile(objs, device, args.cache_dir, frames, settings, warmup=args.warmup)
        run["dense_check"] = check_pile(objs, device, args.cache_dir, args.warmup + frames, settings)
        if n in args.deviation:
            run["settle_deviation"] = settle_deviation(objs, device, args.cache_dir, frames, settings)
        run.update(kind="pile", n=n, wall_s=time.perf_counter() - t0)
        results["runs"].append(run)
        low, worst = run["lowest_point_m"], (run["dense_check"] or {}).get("worst")
        dense = f"dense {100 * worst['relative']:.2f} / {100 * worst['below_relative']:.2f} %" if worst else "NaN!"
        print(
            f"newton pile N={n:5d} tets={run['tets']:8d} particles={run['particles']:8d} "
            f"{run['ms_per_frame']:9.2f} ms/frame  lowest {1e3 * low if math.isfinite(low) else low:7.1f} mm  {dense}",
            flush=True,
        )
        # after every pile, so a crash in a later one (Newton's VBD has hit illegal memory accesses on large
        # piles) keeps the figures measured so far
        tmp = path.with_suffix(".json.tmp")
        tmp.write_text(json.dumps(results, indent=1))
        tmp.replace(path)
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
