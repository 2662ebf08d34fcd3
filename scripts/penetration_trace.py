"""How deep the visible surfaces of a scene sink, frame by frame: the figures of docs/decisions.md's contact entries.

    .venv/bin/python scripts/penetration_trace.py scenes/paper_a_armadillo_stack.toml --every 3
    .venv/bin/python scripts/penetration_trace.py scenes/paper_c_two_bodies.toml --set ground.stiffness=1e8
    .venv/bin/python scripts/penetration_trace.py scenes/default.toml --contact-passes 0 --frames 60
    .venv/bin/python scripts/penetration_trace.py --pile 16 --set object.faces=1000
    .venv/bin/python scripts/penetration_trace.py --pile 256 --device cuda:0 --dissect 0.5

``--dissect P`` adds, on each checked frame where a body's dense vertex lies more than P % of the other body's
size inside it, how many of that body's dense vertices and of its collision points lie inside the other, by
libigl's winding number, and of those points how many lie in none of the other body's tets, how many lie in
them but outside its dense surface at rest (where its own parts overlap), how many have no contact with it
in the last step, how many a detection run afresh on the frame's positions finds none for, and how many
both (a point with none in the last step but one afresh came in during the step's last solve); then how far
the deepest dense vertex lies from the body's nearest collision point, and how many of the other body's
collision points lie inside this one and how many of those have no contact: whether a deep frame is a few
points or a wide overlap, seen or missed, or the dense surface between collision points. The fresh detection
rewrites the contact buffers, which the next step fills again.

``--pile N`` runs scripts/bench.py's pile of N armadillos (``--assets``) instead of a scene file.

Runs the scene through the public API and checks the dense meshes alone (``warpfem.io.penetration``: a
vertex inside another body's dense surface by winding number, the lowest point against the ground and the
obstacles) every ``--every`` frames; prints one line per check and a summary with the solver's work.
``--set section.key=value`` overrides a scene key before validation (the value read as TOML).
"""

from __future__ import annotations

import argparse
import sys
import time
import tomllib
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import numpy as np


def load(args):
    """The scene of ``args``: its file with ``--set`` applied, or bench.py's pile of ``--pile`` armadillos."""
    import warpfem

    sys.path.insert(0, str(ROOT / "scripts"))
    from bench import override, pile, replaced

    if args.pile:
        defaults = warpfem.load_scene(ROOT / "scenes" / "default.toml")
        scene = pile(defaults, args.pile, str((args.assets / "armadillo.off").resolve()), 500)
        for setting in args.set:
            scene = replaced(scene, setting)
        scene.validate()
        return scene
    doc = tomllib.loads(args.scene.read_text())
    for setting in args.set:
        override(doc, setting)
    return warpfem.Scene.from_dict(doc, base_dir=args.scene.parent, name=args.scene.stem)


ROOT = Path(__file__).resolve().parents[1]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scene", type=Path, nargs="?")
    parser.add_argument("--pile", type=int, default=0, help="bench.py's pile of this many armadillos instead")
    parser.add_argument("--assets", type=Path, default=ROOT.parent / "shared" / "assets")
    parser.add_argument("--frames", type=int, help="frames to run (default: the scene's)")
    parser.add_argument("--every", type=int, default=1, help="check every Nth frame (and the last)")
    parser.add_argument("--device", default="cpu")
    parser.add_argument(
        "--contact-passes", type=int, help="the solver's late-contact passes (default: its own; only fewer)"
    )
    parser.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE")
    parser.add_argument("--dissect", type=float, metavar="P", help="dissect frames deeper than P %% (see above)")
    args = parser.parse_args(argv)
    if (args.scene is None) == (args.pile <= 0):
        parser.error("give a scene file or --pile N (N > 0), not both")
    if args.dissect is not None and not args.dissect >= 0.0:  # NaN too
        parser.error(f"--dissect: expected a depth in % >= 0, got {args.dissect}")

    import warpfem
    from warpfem.io.penetration import frame_penetration

    try:
        scene = load(args)
    except (warpfem.InputError, TypeError) as err:  # a bad value, or a key the section does not have
        raise SystemExit(f"penetration_trace: {err}") from None
    sim = warpfem.Simulation(scene, device=args.device, cache_dir=ROOT / ".warpfem-cache" if args.pile else None)
    if args.contact_passes is not None:
        try:
            sim.solver.contact_passes = args.contact_passes
        except ValueError as err:
            raise SystemExit(f"penetration_trace: --contact-passes: {err}") from None
    frames = args.frames or scene.frames
    inside = below = 0.0
    clock = time.perf_counter()
    for frame in range(1, frames + 1):
        sim.step_frame()
        if frame % max(args.every, 1) and frame != frames:
            continue
        r = frame_penetration(sim)
        inside, below = max(inside, r.relative), max(below, r.below_relative)
        print(
            f"{frame:5d}  inside {100 * r.relative:6.2f} % {r.inside:24s} below {100 * r.below_relative:6.3f} % "
            f"({1000 * r.below_ground:.2f} mm)"
        )
        if args.dissect is not None and 100 * r.relative > args.dissect:
            print("       " + dissect(sim, *r.inside.split(" in ")))
    t = sim.totals
    print(
        f"worst inside {100 * inside:.2f} %, below {100 * below:.3f} %; at the end {100 * r.relative:.2f} % and "
        f"{100 * r.below_relative:.3f} %, the lowest point {lowest_point(sim)}; "
        f"CG {t.cg_iterations / t.steps:.1f} iterations and "
        f"{t.cg_solves / t.steps:.2f} solves a step, at its cap in {t.cg_capped_frames} frames; "
        f"{time.perf_counter() - clock:.0f} s"
    )
    return 0


def dissect(sim, name: str, other: str) -> str:
    """How much of body ``name`` lies inside body ``other``: its dense vertices and its collision points (on its
    dense surface, where the model embeds them; detection tests them lifted off it, deeper still) inside
    the other's dense surface (libigl's fast winding number), the deepest of each (% of the other's size), and of
    those collision points how many lie in none of the other body's tets (which detection needs), how many lie
    in them but outside its dense surface at rest (its own parts overlapping there), how many have no contact
    with it in the last step's contact buffers, how many a detection afresh finds none for, and how many both;
    then :func:`_between`'s figures."""
    import numpy as np

    mine, theirs = sim.body_names.index(name), sim.body_names.index(other)
    dense = sim.dense_points()  # one mapping of every body
    faces = np.asarray(sim.model.bodies[theirs].dense_faces, np.int64)
    surface = np.asarray(dense[theirs], np.float64)
    size = float(np.linalg.norm(np.ptp(surface, axis=0)))
    m = sim.model
    cells, cell, bary, body, cell_body = (
        a.numpy() for a in (m.cells, m.point_cell, m.point_bary, m.point_body, m.cell_body)
    )
    x = sim.states[0].x.numpy().astype(np.float64)

    def collision_points(b: int) -> tuple[np.ndarray, np.ndarray]:  # body b's: indices and world positions
        idx = np.flatnonzero(body == b)
        return idx, np.einsum("nk,nkj->nj", bary[idx].astype(np.float64), x[cells[cell[idx]]])

    own, points = collision_points(mine)
    dense_depth = _depth_inside(np.asarray(dense[mine], np.float64), surface, faces)
    point_depth = _depth_inside(points, surface, faces)
    parts = [
        f"{int((d > 0).sum())} of {len(d)} {what} inside (deepest {100 * d.max() / size:.2f} %)"
        for what, d in (("dense vertices", dense_depth), ("collision points", point_depth))
    ]
    inside = point_depth > 0
    their_cells = cells[cell_body == theirs]
    corner = x[their_cells[:, 0]]
    edges = np.stack([x[their_cells[:, k]] - corner for k in (1, 2, 3)], axis=2)
    w = np.einsum("cij,ncj->nci", np.linalg.inv(edges), points[inside][:, None, :] - corner[None])
    lowest = np.minimum(w.min(axis=2), 1.0 - w.sum(axis=2))  # per point and cell of theirs
    held = lowest.max(axis=1) >= 0.0
    rest_depth = _rest_depths(sim, theirs, cells, their_cells, lowest, w, faces)
    collider = sim.solver.collider
    contact_point, contact_cell = collider.contacts()
    without = ~np.isin(own[inside], contact_point[cell_body[contact_cell] == theirs])
    state = sim.states[0]
    fresh_point, fresh_cell = collider.contacts_at(state.x, state.v, sim.dt)
    unseen = ~np.isin(own[inside], fresh_point[cell_body[fresh_cell] == theirs])
    overlap = int((held & (rest_depth <= 0.0)).sum())
    parts.append(
        f"{int((~held).sum())} of those outside its tets, {overlap} in them but outside its dense surface at rest "
        f"(where its own parts overlap), {int(without.sum())} with no contact, {int(unseen.sum())} with none "
        f"afresh ({int((without & unseen).sum())} both)"
    )
    their, their_points = collision_points(theirs)
    own_faces = np.asarray(m.bodies[mine].dense_faces, np.int64)
    in_mine = contact_point[cell_body[contact_cell] == mine]  # the points with a contact with body mine
    parts.append(
        _between(np.asarray(dense[mine], np.float64), own_faces, dense_depth, points, their, their_points, in_mine)
    )
    return f"{name} in {other}: " + ", ".join(parts)


def _between(dense, faces, dense_depth, points, their, their_points, in_contact) -> str:
    """How far a body's deepest dense vertex (``dense``: its dense surface, with ``faces``; ``dense_depth``: each
    vertex's depth in the other body) lies from its nearest collision point (``points``), as % of the body's
    size: a vertex between collision points sinks unseen by any contact. Then how many of the other body's
    collision points (indices ``their`` at ``their_points``) lie inside this body's dense surface, and of those
    how many are not among the points ``in_contact`` with it in the last step: the other way round, which holds
    the two apart there as well."""
    import numpy as np

    size = float(np.linalg.norm(np.ptp(dense, axis=0)))
    gap = float(np.linalg.norm(points - dense[int(np.argmax(dense_depth))], axis=1).min())
    inside = their[_depth_inside(their_points, dense, faces) > 0.0]
    without = ~np.isin(inside, in_contact)
    return (
        f"its deepest dense vertex {100 * gap / size:.2f} % of its size from its nearest collision point, "
        f"{len(inside)} of the other's collision points inside it ({int(without.sum())} with no contact)"
    )


def _depth_inside(points: np.ndarray, surface: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Each point's depth (m) inside the closed dense ``surface`` (``faces``) by libigl's fast winding number:
    positive inside, negative outside."""
    import igl
    import numpy as np

    if len(points) == 0:
        return np.zeros(0)
    kind = igl.SignedDistanceType.SIGNED_DISTANCE_TYPE_FAST_WINDING_NUMBER
    return -igl.signed_distance(points, surface, faces, kind)[0]


def _rest_depths(sim, body: int, cells: np.ndarray, their_cells: np.ndarray, lowest: np.ndarray, w: np.ndarray, faces):
    """Per point, its depth (m, positive inside) below body ``body``'s dense surface at rest, at its weights in
    the cell of ``their_cells`` (the body's) it lies least outside of (``lowest``: per point and such cell, its
    lowest weight; ``w``: the weights of corners 1-3; ``cells``: every cell's nodes): where that body's parts
    do not overlap, the same side as in the world."""
    import numpy as np

    m = sim.model
    rest = m.rest_x.numpy().astype(np.float64)
    b = m.bodies[body]
    span = slice(b.dense_start, b.dense_start + b.dense_count)  # the body's dense vertices alone
    dense_cell, dense_bary = m.dense_cell[span].numpy(), m.dense_bary[span].numpy().astype(np.float64)
    surface = np.einsum("nk,nkj->nj", dense_bary, rest[cells[dense_cell]])
    best = lowest.argmax(axis=1)
    w3 = w[np.arange(len(best)), best]
    weights = np.concatenate([1.0 - w3.sum(axis=1, keepdims=True), w3], axis=1)
    points = np.einsum("nk,nkj->nj", weights, rest[their_cells[best]])
    return _depth_inside(points, surface, faces)


def lowest_point(sim) -> str:
    """The lowest dense point above the ground (mm, and % of its body's size): how far a resting body floats."""
    import numpy as np

    scene = sim.scene
    axis = 1 if scene.up_axis == "Y" else 2
    heights = []
    for points in sim.dense_points():  # every body's in one copy (a copy a body is the whole pile's each time)
        p = np.asarray(points, np.float64)
        size = float(np.linalg.norm(np.ptp(p, axis=0)))
        heights.append((float(p[:, axis].min()) - scene.ground.height, size))
    height, size = min(heights)
    return f"{1000 * height:+.2f} mm ({100 * height / size:+.3f} %)"


if __name__ == "__main__":
    sys.exit(main())
