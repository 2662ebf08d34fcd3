"""What a viewer sees: the written (dense) surface against the ground, measured on the dense points alone."""

import numpy as np
import pytest
import warp as wp

import warpfem
from warpfem.presets import CONTACT_OFFSET
from warpfem.sim.collision import LIFT_SHARE


def _thrown(speed: float, obstacle: dict | None = None) -> dict:
    """A tilted bunny (0.8 m, 2e5 Pa) thrown down at ``speed`` (m/s) onto the ground or, with the ground off,
    onto ``obstacle`` below it (the scene's ``[[obstacle]]`` table)."""
    bunny = {
        "name": "bunny",
        "mesh": "builtin:bunny",
        "subdivide": 0,
        "faces": 400,
        "scale": 0.5,
        "rotate": [15.0, 30.0, 0.0],
        "translate": [0.0, 0.3, 0.0],
        "velocity": [0.0, -speed, 0.0],
        "young": 2e5,
    }
    doc = {"scene": {"frames": 40, "substeps": 4}, "object": [bunny]}
    if obstacle is not None:
        doc["ground"] = {"enabled": False}
        doc["obstacle"] = [obstacle]
    return doc


def _deepest_over_run(device: str, doc: dict, depth, **solver) -> float:
    """The deepest the bunny's dense surface goes into its collider over the run (``depth(points)``: m, of the
    dense points alone), relative to its size (bounding-box diagonal); ``solver``: the scene's ``[solver]``
    keys to set."""
    doc = {**doc, "solver": {**doc.get("solver", {}), **solver}}
    sim = warpfem.Simulation(warpfem.Scene.from_dict(doc, name="throw"), device=device)
    size = float(np.linalg.norm(np.ptp(sim.dense_points("bunny"), axis=0)))
    deepest = 0.0
    for _ in range(doc["scene"]["frames"]):
        sim.step_frame()
        deepest = max(deepest, depth(sim.dense_points("bunny")))
    return deepest / size


def _below_ground(points: np.ndarray) -> float:
    return -float(points[:, 1].min())


def _lowest_over_run(device: str, speed: float, contact_passes: int) -> float:
    """The penalties alone (no lift): the deepest below the ground over the thrown bunny's run."""
    return _deepest_over_run(device, _thrown(speed), _below_ground, contact_passes=contact_passes, static_lift=False)


@pytest.mark.parametrize("speed", [3.0, 10.0])
def test_late_contacts_catch_a_body_thrown_at_the_ground(device, speed):
    """With the ground's penalty alone, points the step's own motion carries through the ground (a tilted
    body pivots about its first contact and swings its other side down faster than it fell) are caught
    within the step: the dense surface stays within 0.2 % of the size of the ground, and at 10 m/s sinks
    several times deeper without those late contacts."""
    caught = _lowest_over_run(device, speed, contact_passes=2)
    assert caught < 0.002
    if speed == 10.0:
        assert _lowest_over_run(device, speed, contact_passes=0) > 3 * caught


@pytest.mark.parametrize("speed", [3.0, 10.0, 30.0])
def test_a_thrown_body_never_sinks_into_the_ground(device, speed):
    """Scene defaults: a body thrown at the ground at up to 30 m/s (a step's travel 16 % of its size) never
    shows its dense surface below it by more than its skin points' tolerance (0.02 % of its size), landing
    included, since the visible surface is lifted out of the ground (``[solver] static_lift``; with the penalty
    alone it goes deeper: docs/decisions.md)."""
    deepest = _deepest_over_run(device, _thrown(speed), _below_ground)
    assert deepest < 0.0002, deepest


@pytest.mark.parametrize("obstacle", [None, "rising box"])
def test_late_passes_leave_out_only_skin_points_that_cannot_reach_a_collider(device, obstacle):
    """A late pass reads only the skin points that their body's fastest vertex could carry onto a collider within
    the step (their clearance at its start, less the collider's own travel, is smaller): a bunny thrown at 30
    m/s onto the ground, and at 10 m/s onto a box rising and turning to meet it, land exactly where the same
    runs reading every skin point land (float32 summation order aside on CUDA)."""
    moving = {"kind": "box", "center": [0.0, -0.5, 0.0], "half_extents": [2.0, 0.5, 2.0],
              "keys": [[0.0, 0, 0, 0, 0, 0, 0], [0.5, 0, 0.3, 0, 0, 20, 0]]}  # fmt: skip
    doc = _thrown(30.0) if obstacle is None else _thrown(10.0, moving)
    landed = []
    for gated in (True, False):
        sim = warpfem.Simulation(warpfem.Scene.from_dict(doc, name="throw"), device=device)
        if not gated:
            sim.solver.skin_clear = wp.zeros(0, dtype=float, device=sim.solver.model.device)
        for _ in range(doc["scene"]["frames"]):
            sim.step_frame()
        landed.append(sim.dense_points("bunny"))
    atol = 0.0 if device == "cpu" else 1e-5
    np.testing.assert_allclose(landed[0], landed[1], rtol=0.0, atol=atol)


def _every_pass(solver) -> list[int]:
    """Make ``solver`` run every late pass, whether or not the one before it solved; returns a list that counts
    the later passes run."""
    nested, later = solver._late_passes, []

    def every(state_in, state_out, dt, k=0):
        passes = solver.contact_passes
        if k >= passes:
            return
        later.extend([k] if k else [])
        solver.contact_passes = k + 1  # this pass alone: its solve does not start the next
        nested(state_in, state_out, dt, k)
        solver.contact_passes = passes
        every(state_in, state_out, dt, k + 1)

    solver._late_passes = every
    return later


def test_a_late_pass_after_one_that_found_nothing_would_find_nothing(device):
    """A late pass runs only after the pass before it solved: a bunny dropped at 6 m/s onto another on the
    ground lands exactly where the same run with every pass run every step lands (float32 summation order
    aside on CUDA), while that run ran more of the later passes."""
    doc = _thrown(6.0)
    doc["scene"]["frames"] = 30
    lower = {**doc["object"][0], "name": "lower", "translate": [0.05, -0.15, 0.0], "velocity": [0.0, 0.0, 0.0]}
    doc["object"] = [{**doc["object"][0], "translate": [0.0, 0.5, 0.0]}, lower]
    landed, later = [], []
    for every in (False, True):
        sim = warpfem.Simulation(warpfem.Scene.from_dict(doc, name="drop"), device=device)
        runs = _every_pass(sim.solver) if every else []
        for _ in range(doc["scene"]["frames"]):
            sim.step_frame()
        landed.append(np.concatenate([sim.dense_points("bunny"), sim.dense_points("lower")]))
        later.append(len(runs))
    assert later[1] >= 4 * doc["scene"]["frames"]
    atol = 0.0 if device == "cpu" else 1e-5
    np.testing.assert_allclose(landed[0], landed[1], rtol=0.0, atol=atol)


def _inside_box(points: np.ndarray) -> float:
    """How deep the deepest point lies inside the box of centre (0, -0.5, 0) and half extents (2, 0.5, 2) (m)."""
    q = np.abs(points - [0.0, -0.5, 0.0]) - [2.0, 0.5, 2.0]
    return max(0.0, float(-q.max(axis=1).min()))


def _inside_ball(points: np.ndarray) -> float:
    """How deep the deepest point lies inside the ball of centre (0, -1, 0) and radius 1 (m)."""
    return max(0.0, float(1.0 - np.linalg.norm(points - [0.0, -1.0, 0.0], axis=1).min()))


@pytest.mark.parametrize("kind", ["box", "sphere"])
def test_a_body_thrown_at_a_still_obstacle_never_sinks_into_it(device, kind):
    """Thrown at 10 m/s onto a box or a ball (the ground off): the dense surface is never inside it by more than
    the skin points' tolerance (0.02 % of the size; measured against the obstacle's own shape), and deeper
    with the penalty alone."""
    obstacle = (
        {"kind": "box", "center": [0.0, -0.5, 0.0], "half_extents": [2.0, 0.5, 2.0]}
        if kind == "box"
        else {"kind": "sphere", "center": [0.0, -1.0, 0.0], "radius": 1.0}
    )
    depth = _inside_box if kind == "box" else _inside_ball
    lifted = _deepest_over_run(device, _thrown(10.0, obstacle), depth)
    alone = _deepest_over_run(device, _thrown(10.0, obstacle), depth, static_lift=False)
    assert lifted < 0.0002, lifted
    assert alone > 2 * lifted + 0.0002, (alone, lifted)


def test_skin_samples_hold_the_surface_up_in_every_direction():
    """On a sphere and on a bumpy one, for any direction, the lowest chosen skin point lies within the
    tolerance (twice it: the rule works along vertex normals) of the lowest surface vertex: what the ground
    holds up is where the visible surface is; the plain grid of collision samples does not."""
    import trimesh

    from warpfem.prep.samples import surface_samples

    rng = np.random.default_rng(3)
    directions = rng.normal(size=(400, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    sphere = trimesh.creation.icosphere(subdivisions=5, radius=0.5)
    bumpy = sphere.vertices * (1.0 + 0.02 * np.sin(12 * sphere.vertices[:, :1]) * np.cos(9 * sphere.vertices[:, 1:2]))
    for vertices in (np.asarray(sphere.vertices), bumpy):
        size = float(np.linalg.norm(np.ptp(vertices, axis=0)))
        tolerance = 2e-4 * size
        samples = surface_samples(vertices, np.asarray(sphere.faces), 0.05 * size, tolerance)
        support = (vertices @ directions.T).max(axis=0)
        gap_skin = support - (vertices[samples.skin] @ directions.T).max(axis=0)
        gap_grid = support - (vertices[samples.collision] @ directions.T).max(axis=0)
        assert gap_skin.max() < 2 * tolerance and gap_grid.max() > 5 * tolerance


def test_stick_out_in_chunks_is_the_whole_formula(monkeypatch):
    """``stick_out`` over chunks of rows gives exactly the one-array formula (the samples do not depend on it)."""
    from warpfem.prep import samples as S

    rng = np.random.default_rng(3)
    x, chosen = rng.normal(size=(1000, 3)), rng.normal(size=(40, 3))
    normal = rng.normal(size=(1000, 3))
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    near = rng.integers(0, 40, size=(1000, 8))
    whole = np.einsum("vkj,vj->vk", x[:, None, :] - chosen[near], normal).min(axis=1)
    monkeypatch.setattr(S, "STICK_OUT_ROWS", 96)  # 1000 rows: ten full chunks and a short one
    np.testing.assert_array_equal(S.stick_out(x, normal, chosen, near), whole)


def test_collision_samples_cover_the_dense_surface(prep_cache):
    """On the builtin bunny, with the default spacing: every dense vertex lies within half the spacing of a
    collision sample (brute-force distances, NumPy), where a grid of that spacing picking one vertex per cell
    leaves vertices nearly twice as far; the cover's picks lie at least that far apart, and refinement only
    adds to them."""
    from warpfem.prep.samples import DEFAULT_SPACING, SKIN_SPACING, covering_picks, grid_picks, surface_samples

    body = warpfem.prepare("builtin:bunny", faces=400, cache_dir=prep_cache)
    x = np.asarray(body.dense_vertices, np.float64)
    size = float(np.linalg.norm(np.ptp(x, axis=0)))
    spacing = DEFAULT_SPACING * size

    def nearest(picks):  # each dense vertex's distance to its nearest pick
        return np.concatenate(
            [np.sqrt(((x[i : i + 2048, None] - x[picks][None]) ** 2).sum(-1)).min(1) for i in range(0, len(x), 2048)]
        )

    samples = surface_samples(x, body.dense_faces, spacing, 2e-4 * size, SKIN_SPACING * size)
    assert nearest(samples.collision).max() <= 0.5 * spacing * (1 + 1e-9)
    assert nearest(grid_picks(x, spacing)).max() > 0.9 * spacing
    picks = covering_picks(x, 0.5 * spacing)
    assert np.isin(picks, samples.collision).all()
    apart = np.sqrt(((x[picks][:, None] - x[picks][None]) ** 2).sum(-1)) + np.eye(len(picks)) * size
    assert apart.min() >= 0.5 * spacing


def test_large_triangles_carry_collision_points_of_their_own():
    """Where a mesh's triangles are larger than the collision spacing, points on them fill the gaps its vertices
    leave: every point of a low-poly box's surface (sampled by trimesh, measured by SciPy) lies within 1.2
    times the spacing of a collision point (a dense vertex picked, or a point on a triangle; the corners alone
    leave 29 times), each point once; a mesh finer than the spacing gets none."""
    import trimesh
    from scipy.spatial import cKDTree

    from warpfem.prep.samples import surface_samples

    spacing = 0.02
    box = trimesh.creation.box(extents=(0.4, 0.2, 0.4))
    samples = surface_samples(box.vertices, box.faces, spacing, 1e-4)
    bary = samples.face_bary
    assert np.allclose(bary.sum(axis=1), 1.0) and (bary >= 0).all()
    points = np.einsum("kj,kjd->kd", bary, box.vertices[box.faces[samples.face]])
    gap, _ = cKDTree(np.vstack([points, box.vertices[samples.collision]])).query(box.sample(20000, seed=1))
    assert gap.max() <= 1.2 * spacing, gap.max() / spacing
    assert len(np.unique(np.round(points, 9), axis=0)) == len(points)
    fine = trimesh.creation.icosphere(subdivisions=4, radius=0.1)  # edges of about 1 cm
    assert len(surface_samples(fine.vertices, fine.faces, spacing, 1e-4).face) == 0


def _head_on(
    device: str,
    speed: float,
    contact_passes: int | None = None,
    rotation_updates: int | None = None,
    elements: str = "linear",
    offset: float | None = None,
    damping: float | None = None,
) -> float:
    """Two bunnies (0.8 m) thrown at each other at ``speed`` each, no gravity: the deepest a dense vertex of
    one gets inside the other's dense surface over 30 frames (libigl's winding number on the dense meshes
    alone), relative to the size of the body it is inside."""

    def thrown(name, x, vx, turn):
        return {
            "name": name,
            "mesh": "builtin:bunny",
            "subdivide": 0,
            "faces": 400,
            "scale": 0.5,
            "rotate": [0.0, turn, 0.0],
            "translate": [x, 0.5, 0.0],
            "velocity": [vx, 0.0, 0.0],
            "young": 2e5,
        }

    doc = {
        "scene": {"frames": 30, "substeps": 4, "gravity": [0.0, 0.0, 0.0]},
        "solver": {"elements": elements}
        | ({"contact_passes": contact_passes} if contact_passes is not None else {})
        | ({"rotation_updates": rotation_updates} if rotation_updates is not None else {}),
        "ground": {"enabled": False},
        "collision": ({} if offset is None else {"offset": offset}) | ({} if damping is None else {"damping": damping}),
        "object": [thrown("left", -0.55, speed, 90.0), thrown("right", 0.55, -speed, -90.0)],
    }
    sim = warpfem.Simulation(warpfem.Scene.from_dict(doc, name="head_on"), device=device)
    return _worst_inside(sim, 30)


def test_bodies_meeting_head_on_do_not_sink_into_each_other(device):
    """Closing at 10 m/s (a step's travel is 3.5 % of the size) with scene defaults, the dense surfaces
    overlap by less than 1 % of the size. At 30 m/s too in this meeting (turned otherwise, such an impact
    can overlap more: docs/decisions.md), since contacts the step's own motion makes are answered within the
    step; found only at the start of the next step, and with each step linearised about the rotations at its
    start (which stretches the deforming surfaces along their tangents), they overlap by more than 1.5 % when
    contacts start at the surface and close undamped (no ``[collision] offset``, whose gap absorbs part of that
    overlap, nor ``damping``, which stops the closing nearer the surface)."""
    assert _head_on(device, 5.0) < 0.01
    assert _head_on(device, 15.0, contact_passes=2) < 0.01
    assert _head_on(device, 15.0, contact_passes=0, rotation_updates=0, offset=0.0, damping=0.0) > 0.015


def test_quadratic_bodies_meeting_head_on_do_not_sink_into_each_other(device):
    """The same meeting at 10 m/s with quadratic tets, whose dense surfaces follow their tets' sub-tets: the
    contacts find each point in the sub-tet of the other body that holds it, so the visible surfaces overlap
    by less than 1 % of the size too."""
    assert _head_on(device, 5.0, elements="quadratic") < 0.01


@pytest.mark.parametrize("look", ["full", "carried"])
def test_a_pile_of_armadillos_keeps_its_surfaces_apart(device, asset, prep_cache, look, monkeypatch):
    """Four 1 m armadillos (500 coarse faces each) dropped in a 2 x 2 grid from 0.7 m with scene defaults, every
    frame checked on the dense meshes alone: no dense vertex gets deeper than 1 % of the size inside another
    body (the goal) and the dense surfaces stay within 0.15 % of the size of the ground. ``carried``: stepped as
    a scene of many bodies is, every step starting from the step before's contacts (its late look the only
    look at every point)."""
    if look == "carried":
        monkeypatch.setattr("warpfem.sim.collision.DIRECT_BODIES", 0)
        monkeypatch.setattr("warpfem.sim.collision.CARRY_BODIES", 0)
    rng = np.random.default_rng(4)
    objects = [
        {
            "name": f"body_{i}",
            "mesh": str(asset("armadillo.off")),
            "faces": 500,
            "scale": 0.0066,
            "rotate": [0.0, float(rng.uniform(0, 360)), 0.0],
            "translate": [1.1 * (i % 2 - 0.5), 0.7, 1.1 * (i // 2 - 0.5)],
            "young": 1e6,
            "poisson": 0.3,
            "damping_stiffness": 0.005,
        }
        for i in range(4)
    ]
    scene = warpfem.Scene.from_dict({"scene": {"frames": 90}, "object": objects}, name="pile")
    sim = warpfem.Simulation(scene, device=device, cache_dir=prep_cache)
    assert sim.solver.collider.carries == (look == "carried")
    inside = below = 0.0
    for _ in range(90):
        sim.step_frame()
        r = warpfem.frame_penetration(sim)
        inside, below = max(inside, r.relative), max(below, r.below_relative)
    assert inside < 0.01 and below < 0.0015


def test_the_penetration_trace_script_checks_the_frames_asked(capsys):
    """scripts/penetration_trace.py: one line per checked frame (every 10th and the last) and a summary; a
    malformed override is a one-line error."""
    import importlib.util
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    spec = importlib.util.spec_from_file_location("penetration_trace", root / "scripts" / "penetration_trace.py")
    trace = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(trace)
    scene = root / "tests" / "data" / "golden" / "two_balls.toml"
    assert trace.main([str(scene), "--frames", "12", "--every", "10", "--set", "object.young=3e5"]) == 0
    out = capsys.readouterr().out.splitlines()  # Warp may print its banner first
    lines = [line for line in out if line.split() and (line.split()[0].isdigit() or line.startswith("worst"))]
    assert [line.split()[0] for line in lines[:2]] == ["10", "12"] and lines[2].startswith("worst inside")
    # --dissect: the bodies of a deep frame counted by libigl's winding number; its deepest dense vertex is the
    # one warpfem.io.penetration found (a soft penalty lets the top ball sink into the lower one)
    assert (
        trace.main(
            [str(scene), "--frames", "20", "--every", "20", "--dissect", "0", "--set", "collision.stiffness=1e3"]
            + ["--set", "collision.approach_limit=0.02"]  # the landing this was written for (refined twice)
        )
        == 0
    )
    out = [line.strip() for line in capsys.readouterr().out.splitlines()]
    frame = next(line for line in out if line.startswith("20 "))
    pair = out[out.index(frame) + 1]
    assert frame.split()[4:7] == ["top", "in", "ball"] and pair.startswith("top in ball: ")
    dense = pair.split(": ")[1].split(", ")[0]
    assert int(dense.split()[0]) > 0 and dense.endswith(f"(deepest {frame.split()[2]} %)")
    counts = pair.split(": ")[1].split(", ")[1:]
    inside, outside, overlap, missing, unseen = (int(part.split()[0]) for part in counts[:5])
    assert 0 < inside and 0 <= outside <= inside and 0 <= missing <= inside
    # the deepest dense vertex lies within the sampling's cover of a collision point (every dense vertex within
    # 0.8 % of the size of one at rest), and the lower ball's points pressed into the top ball are counted too
    gap = counts[5].split()[4]
    assert counts[5].startswith("its deepest dense vertex ") and 0.0 <= float(gap) <= 1.0
    reverse, reverse_missing = int(counts[6].split()[0]), int(counts[6].split("(")[1].split()[0])
    assert counts[6].endswith("with no contact)") and 0 < reverse and 0 <= reverse_missing <= reverse
    assert overlap == 0  # a ball's parts never overlap: a point in its tets inside it is inside it at rest too
    # a detection afresh at the frame's positions finds every point inside the other ball by winding number
    # (none lies outside its tets past their slack, nor where its parts overlap)
    assert counts[4] == "0 with none afresh (0 both)"
    with pytest.raises(SystemExit, match="expected section.key=value"):
        trace.main([str(scene), "--set", "young"])
    for bad in ("abc", "nan", "-1"):  # a depth in % >= 0, or argparse's one line and exit 2, before any run
        with pytest.raises(SystemExit) as stop:
            trace.main([str(scene), "--dissect", bad])
        assert stop.value.code == 2 and "--dissect" in capsys.readouterr().err
    with pytest.raises(SystemExit):  # a scene file or --pile, not both
        trace.main([str(scene), "--pile", "4"])
    # --pile's overrides (scripts/bench.py's, as its own --set) reach the scene's dataclasses as the file's
    # reach its document
    import bench  # scripts/, on the path once the trace has run

    loaded = warpfem.load_scene(scene)
    changed = bench.replaced(bench.replaced(loaded, "object.young=3e5"), "collision.stiffness=1e8")
    assert [o.young for o in changed.objects] == [3e5, 3e5] and changed.collision.stiffness == 1e8
    assert bench.replaced(loaded, "scene.substeps=3").substeps == 3


def _dense_obj(path, vertices, faces):
    """Write a dense surface mesh (m) as an OBJ file for a scene to read."""
    import trimesh

    trimesh.Trimesh(vertices, faces, process=False).export(path)
    return str(path)


def test_crossing_thin_bars_keep_their_dense_surfaces_apart(device, tmp_path, prep_cache):
    """A 1 m bar of 4 cm square section (31k dense faces, scene defaults otherwise) dropped at 3 m/s across a
    pinned one: it bounces twice and comes to lie across it, its corners pressed on the other's edges. Checked
    every frame on the dense meshes alone (winding numbers): no dense vertex gets deeper than 1 % of the size
    inside the other bar, and it ends on top of the crossing, not tipped into it."""
    import trimesh

    box = trimesh.creation.box(extents=(1.0, 0.04, 0.04))
    bar = _dense_obj(tmp_path / "bar.obj", *trimesh.remesh.subdivide_to_size(box.vertices, box.faces, max_edge=0.01))
    doc = {
        "scene": {"frames": 70},
        "ground": {"enabled": False},
        "object": [
            {"name": "lower", "mesh": bar, "young": 1e7, "pin_min": [-1, -1, -1], "pin_max": [1, 1, 1]},
            {
                "name": "upper",
                "mesh": bar,
                "young": 1e7,
                "rotate": [0, 90, 0],
                "translate": [0, 0.08, 0],
                "velocity": [0, -3.0, 0],
            },
        ],
    }
    sim = warpfem.Simulation(warpfem.Scene.from_dict(doc, name="bars"), device=device, cache_dir=prep_cache)
    worst, lowest = 0.0, []
    for _ in range(70):
        sim.step_frame()
        worst = max(worst, warpfem.frame_penetration(sim).relative)
        upper = sim.dense_points("upper")
        lowest.append(float(upper[np.abs(upper[:, 2]) < 0.02, 1].min()))  # over the crossing
    assert worst < 0.01, worst
    assert all(0.02 - 0.002 < y < 0.022 for y in lowest[-10:])  # the lower bar's top is at 0.02 m


def test_a_stack_comes_to_rest_with_its_dense_surfaces_apart(device, tmp_path, prep_cache):
    """Two rounded boxes (superellipsoids, 0.4 x 0.2 x 0.4 m, 20k dense faces: their dense surfaces bulge
    out of the coarse ones at every edge) stacked on a third whose base is pinned, scene defaults otherwise:
    after 2 s the stack stands where it was put, at rest, and no dense vertex is deeper than 0.3 % of the size
    inside another body (winding numbers on the dense meshes). Each body rests on the one below: its dense
    surface within 0.1 % of the size plus twice the contacts' offset of the other's, and no nearer than the
    collision points' lift (libigl's signed distance)."""
    import igl
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=5)
    rounded = sphere.vertices / (np.abs(sphere.vertices) ** 6).sum(axis=1, keepdims=True) ** (1 / 6)
    mesh = _dense_obj(tmp_path / "cushion.obj", rounded * [0.2, 0.1, 0.2], sphere.faces)
    common = {"mesh": mesh, "faces": 300, "young": 3e5, "damping_stiffness": 0.005}
    doc = {
        "scene": {"frames": 120},
        "ground": {"enabled": False},
        "object": [
            {"name": "lower", "translate": [0, 0.1, 0], "pin_min": [-1, -1, -1], "pin_max": [1, 0.11, 1], **common},
            {"name": "middle", "rotate": [0, 30, 0], "translate": [0.03, 0.31, 0], **common},
            {"name": "top", "rotate": [0, 60, 0], "translate": [-0.03, 0.52, 0.02], **common},
        ],
    }
    sim = warpfem.Simulation(warpfem.Scene.from_dict(doc, name="stack"), device=device, cache_dir=prep_cache)
    for _ in range(118):
        sim.step_frame()
    before = sim.dense_points()
    sim.step_frame()
    sim.step_frame()
    after = sim.dense_points()
    assert max(float(np.abs(a - b).max()) for a, b in zip(after, before, strict=True)) < 0.001  # at rest
    centres = np.array([p.mean(axis=0) for p in after])
    assert np.allclose(centres[1:, [0, 2]], [[0.03, 0.0], [-0.03, 0.02]], atol=0.01)  # not slid off
    assert np.all(np.diff(centres[:, 1]) > 0.19)  # each on the one below
    assert warpfem.frame_penetration(sim).relative < 0.003
    faces = [np.asarray(b.dense_faces, np.int64).reshape(-1, 3) for b in sim.model.bodies]
    size = float(np.linalg.norm(np.ptp(after[0], axis=0)))
    points = [p.astype(np.float64) for p in after]
    for upper in (1, 2):
        gap = float(igl.signed_distance(points[upper], points[upper - 1], faces[upper - 1])[0].min())
        assert gap < (0.001 + 2.0 * CONTACT_OFFSET) * size, gap / size
        # its contacts start at least the collision points' lift outside the other's surface, where the cage
        # touches it too (the rounded boxes' cages hug their edges): it rests at least that far above
        assert gap > LIFT_SHARE * CONTACT_OFFSET * size, gap / size


@pytest.mark.parametrize("elements", ["linear", "quadratic"])
def test_an_armadillo_rests_on_the_ground_with_its_visible_surface(device, asset, prep_cache, elements):
    """A 1 m armadillo (500 coarse faces, scene defaults otherwise) dropped from 0.24 m onto the ground: its
    lowest dense point is never more than 0.1 % of its size below the ground, landing included (measured
    on the dense mesh alone), with linear or quadratic tets (softer without locking, they dent where they
    land and topple: 0.11 % below with the ground's penalty at its surface, none with its default offset)."""
    doc = {
        "scene": {"frames": 60},
        "solver": {"elements": elements},
        "object": [
            {
                "name": "armadillo",
                "mesh": str(asset("armadillo.off")),
                "faces": 500,
                "scale": 0.0066,
                "rotate": [0.0, 40.0, 0.0],
                "translate": [0.0, 0.6, 0.0],
                "young": 1e6,
                "damping_stiffness": 0.005,
            }
        ],
    }
    sim = warpfem.Simulation(warpfem.Scene.from_dict(doc, name="armadillo"), device=device, cache_dir=prep_cache)
    below = 0.0
    for _ in range(60):
        sim.step_frame()
        below = max(below, warpfem.frame_penetration(sim).below_relative)
    assert below < 0.001, below


def _rest_height(device: str, collider: str, offset: float) -> tuple[float, float]:
    """A bunny (0.8 m, 400 coarse faces) set down on the ground or on a box obstacle (the ground off) with the
    collider's ``offset``: the lowest dense point above the collider's top after it has settled (m), and the
    body's size (its tet mesh's rest diagonal, which the offset is a share of)."""
    bunny = {
        "name": "bunny",
        "mesh": "builtin:bunny",
        "faces": 400,
        "scale": 0.5,
        "translate": [0.0, 0.0, 0.0],
        "young": 2e5,
        "damping_mass": 20.0,
    }
    doc = {"scene": {"frames": 45}, "object": [bunny]}
    top = 0.0
    if collider == "ground":
        doc["ground"] = {"offset": offset}
    else:
        top = -0.2
        doc["ground"] = {"enabled": False}
        doc["obstacle"] = [
            {"kind": "box", "center": [0.0, top - 0.5, 0.0], "half_extents": [2.0, 0.5, 2.0], "offset": offset}
        ]
    sim = warpfem.Simulation(warpfem.Scene.from_dict(doc, name="rest"), device=device)
    for _ in range(45):
        sim.step_frame()
    return float(sim.dense_points("bunny")[:, 1].min()) - top, sim.model.bodies[0].size


@pytest.mark.parametrize("collider", ["ground", "box"])
def test_a_resting_body_floats_by_the_offset_and_never_below(device, collider):
    """A static collider's penalty starts its ``offset`` (a share of the body's size) above its surface, so the
    give it needs to hold the body is spent in that gap: a resting body's visible surface lies above the
    surface and at most the offset above it; raising the offset by 0.002 of the size lifts the resting body
    by that much (the same load, the same give), to within a tenth."""
    base, size = _rest_height(device, collider, 0.001)
    raised, _ = _rest_height(device, collider, 0.003)
    assert 0.0 <= base <= 0.001 * size, (base, size)
    assert 0.0 <= raised <= 0.003 * size, (raised, size)
    assert raised - base == pytest.approx(0.002 * size, rel=0.1), (base, raised, size)


def test_collision_points_stand_the_lift_off_their_own_dense_surface(tmp_path, prep_cache):
    """Two spheres of 0.2 m (20k dense faces, a 300-face cage): at rest every collision point of each lies
    ``LIFT_SHARE`` of the contact offset outside its own dense surface (libigl's signed distance), and the
    points the model embeds lie on it."""
    import igl
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=5, radius=0.2)
    mesh = _dense_obj(tmp_path / "sphere.obj", sphere.vertices, sphere.faces)
    common = {"mesh": mesh, "faces": 300, "young": 1e6}
    doc = {
        "scene": {"frames": 1},
        "ground": {"enabled": False},
        "object": [{"name": "a", **common}, {"name": "b", "translate": [1.0, 0, 0], **common}],
    }
    sim = warpfem.Simulation(warpfem.Scene.from_dict(doc, name="spheres"), device="cpu", cache_dir=prep_cache)
    m = sim.model
    rest, cells = m.rest_x.numpy().astype(np.float64), m.cells.numpy()[m.point_cell.numpy()]
    body = m.point_body.numpy()
    lift = LIFT_SHARE * CONTACT_OFFSET * min(b.size for b in m.bodies)
    dense = sim.dense_points()
    for k, b in enumerate(m.bodies):
        faces = np.asarray(b.dense_faces, np.int64).reshape(-1, 3)
        own = body == k
        for bary, expected in ((m.point_bary.numpy(), 0.0), (sim.solver.collider.point_bary.numpy(), lift)):
            points = np.einsum("nk,nkj->nj", bary[own].astype(np.float64), rest[cells[own]])
            distance = igl.signed_distance(points, dense[k].astype(np.float64), faces)[0]
            np.testing.assert_allclose(distance, expected, atol=0.02 * lift + 1e-6)


def test_low_poly_boxes_crossing_edge_first_do_not_pass_through(device, tmp_path, prep_cache):
    """Two boxes of twelve triangles each (0.4 x 0.2 x 0.4 m, scene defaults otherwise), the upper turned 45
    degrees about the vertical and dropped at 3 m/s onto the pinned lower one: no corner of either lies inside
    the other, so a collision point at every dense vertex alone let it fall straight through. It lands and
    stays on top: its lowest point never gets deeper than 1 % of its size below the lower box's top face, at
    0.2 m (the meshes' own geometry), and ends on it."""
    import trimesh

    box = trimesh.creation.box(extents=(0.4, 0.2, 0.4))
    mesh = _dense_obj(tmp_path / "box.obj", box.vertices + [0.0, 0.1, 0.0], box.faces)
    doc = {
        "scene": {"frames": 40},
        "ground": {"enabled": False},
        "object": [
            {"name": "lower", "mesh": mesh, "young": 1e7, "pin_min": [-1, -1, -1], "pin_max": [1, 1, 1]},
            {
                "name": "upper",
                "mesh": mesh,
                "young": 1e7,
                "rotate": [0, 45, 0],
                "translate": [0, 0.25, 0],
                "velocity": [0, -3.0, 0],
            },
        ],
    }
    sim = warpfem.Simulation(warpfem.Scene.from_dict(doc, name="boxes"), device=device, cache_dir=prep_cache)
    size = float(np.linalg.norm([0.4, 0.2, 0.4]))
    lowest = []
    for _ in range(40):
        sim.step_frame()
        lowest.append(float(sim.dense_points("upper")[:, 1].min()))
    assert min(lowest) > 0.2 - 0.01 * size, min(lowest)
    assert all(0.2 - 0.002 < y < 0.2 + 0.002 for y in lowest[-10:]), lowest[-10:]


@pytest.mark.parametrize("height", [0.75, 0.95])
def test_stiff_low_poly_boxes_landing_on_each_other_come_to_rest(device, tmp_path, prep_cache, height):
    """Two boxes of twelve triangles (12 tets each), 1 GPa, nu 0.49, 24 steps a second, scene defaults
    otherwise: the lower resting on the ground, the upper turned 45 degrees and dropped from ``height`` (its
    bottom 0.55 or 0.75 m above the lower's top; 3.3 or 3.8 m/s at contact, 0.14 or 0.16 m a step). Float32
    loses such bodies' rigid motions in CG, and where they meet only their solve together holds them. The
    upper lands on the lower box's top face (0.2 m) and rests there: its lowest point within 1 % of its size
    of the face over the last second, moving less than 0.1 % of its size a frame."""
    import trimesh

    box = trimesh.creation.box(extents=(0.4, 0.2, 0.4))
    mesh = _dense_obj(tmp_path / "box.obj", box.vertices + [0.0, 0.1, 0.0], box.faces)
    stiff = {"mesh": mesh, "young": 1e9, "poisson": 0.49}
    doc = {
        "scene": {"frames": 48, "fps": 24.0, "substeps": 1},
        "object": [
            {"name": "lower", **stiff, "translate": [0, 0.05, 0]},
            {"name": "upper", **stiff, "rotate": [0, 45, 0], "translate": [0.05, height, 0.02]},
        ],
    }
    sim = warpfem.Simulation(warpfem.Scene.from_dict(doc, name="stiff_boxes"), device=device, cache_dir=prep_cache)
    size = float(np.linalg.norm([0.4, 0.2, 0.4]))
    lowest, moved, previous = [], [], None
    for _ in range(48):
        sim.step_frame()
        points = sim.dense_points("upper")
        lowest.append(float(points[:, 1].min()))
        if previous is not None:
            moved.append(float(np.abs(points - previous).max()))
        previous = points
    assert all(abs(y - 0.2) < 0.01 * size for y in lowest[-24:]), lowest[-24:]
    assert max(moved[-24:]) < 0.001 * size, max(moved[-24:])


def _horse_drop(device: str, asset, prep_cache, drop: float, **collision) -> tuple[float, warpfem.Simulation]:
    """A 1 m horse (3.9e6 Pa) dropped upright from ``drop`` m onto another's back (1.9e6 Pa, standing on the
    ground), legs first, for 72 frames with scene defaults but ``collision``: the deepest a dense vertex of one
    gets inside the other's dense surface, checked on the dense meshes alone every frame, relative to the size
    of the body it is inside; and the simulation."""
    horse = {"mesh": str(asset("horse.ply")), "faces": 500, "scale": 3.952, "poisson": 0.3, "damping_stiffness": 0.005}
    objects = [
        {**horse, "name": "below", "translate": [0.0, 0.363, 0.0], "young": 1.9e6},
        {**horse, "name": "above", "rotate": [0.0, 30.0, 0.0], "translate": [0.05, 1.087 + drop, 0.02], "young": 3.9e6},
    ]
    doc = {"scene": {"frames": 72}, "collision": collision, "object": objects}
    sim = warpfem.Simulation(warpfem.Scene.from_dict(doc, name="horses"), device=device, cache_dir=prep_cache)
    return _worst_inside(sim, 72), sim


def _worst_inside(sim: warpfem.Simulation, frames: int) -> float:
    """Run ``frames`` frames: the deepest a dense vertex gets inside another body over them, checked on the
    written dense meshes every frame, relative to that body's size."""
    inside = 0.0
    for _ in range(frames):
        sim.step_frame()
        inside = max(inside, warpfem.frame_penetration(sim).relative)
    return inside


def test_a_horse_dropped_onto_another_lands_within_one_percent(device, asset, prep_cache):
    """Dropped from 3.5, 4 and 4.5 m, the horse lands legs first at 8.3-9.4 m/s (a step's travel is 3.5 % of its
    size, more than its legs are thick): no dense vertex gets deeper than 1 % of the size inside the other body.
    The frames of the impact run more substeps (``[collision] approach_limit``)."""
    assert max(_horse_drop(device, asset, prep_cache, drop)[0] for drop in (3.5, 4.0, 4.5)) < 0.01


def test_only_the_frames_of_a_fast_impact_run_more_substeps(device, asset, prep_cache):
    """Of the 72 frames of the 3.5 m drop, those in which the horses close fast on each other run 1.25, 1.5 or 2
    times the substeps, not the fall before them nor the rest after; with ``approach_limit = 0`` none do, and the legs,
    which a step then carries deeper than they are thick, sink past 1 % of the size into the other horse where
    contacts start at its surface and close undamped (``offset = 0``, ``damping = 0``: the default offset's gap
    or the damper of contacts closing fast holds this drop without the other two)."""
    inside, sim = _horse_drop(device, asset, prep_cache, 3.5)
    refined, s = sim.totals.refined_frames, sim.substeps
    assert 1 <= refined <= 12, refined
    assert s * 72 + refined * s // 4 <= sim.totals.steps <= s * (72 + refined)
    assert inside < 0.01
    inside, sim = _horse_drop(device, asset, prep_cache, 3.5, approach_limit=0.0, offset=0.0, damping=0.0)
    assert sim.approach is None and sim.totals.steps == sim.substeps * 72
    assert inside > 0.01


def _landing(device: str, asset, prep_cache, speed: float, **collision) -> float:
    """A 1 m armadillo of the piles (1e6 Pa) thrown down at ``speed`` m/s onto another falling from the piles'
    first layer, turned so that its feet meet the other's ears, 40 frames: the deepest a dense vertex of one gets
    inside the other's dense surface, checked on the dense meshes alone every frame, relative to its size."""
    body = {"mesh": str(asset("armadillo.off")), "faces": 500, "scale": 0.0066, "young": 1e6, "poisson": 0.3,
            "density": 1000.0, "damping_stiffness": 0.005}  # fmt: skip
    objects = [
        {**body, "name": "below", "translate": [0.0, 0.7, 0.0], "rotate": [0.0, 40.0, 0.0]},
        {**body, "name": "above", "translate": [0.05, 2.0, 0.03], "rotate": [0.0, 120.0, 0.0],
         "velocity": [0.0, -speed, 0.0]},
    ]  # fmt: skip
    doc = {"scene": {"frames": 40}, "collision": collision, "object": objects}
    sim = warpfem.Simulation(warpfem.Scene.from_dict(doc, name="landing"), device=device, cache_dir=prep_cache)
    return _worst_inside(sim, 40)


def test_a_fast_landing_on_thin_parts_stops_near_the_surface(device, asset, prep_cache):
    """Landing feet first on the other's ears at 22 m/s (a refined step's travel 3 % of the size, more than an
    ear is thick), the dense surfaces overlap by less than 0.5 % of the size with scene defaults, where contacts
    that start at the surface and close undamped (``offset = 0``, ``damping = 0``: the default offset's gap and
    the damper of contacts closing fast each hold part of it) let the feet 0.8 % and more into the other's head."""
    assert _landing(device, asset, prep_cache, 22.0) < 0.005
    assert _landing(device, asset, prep_cache, 22.0, damping=0.0, offset=0.0) > 0.008


def _vertex_normals(points: np.ndarray, faces: np.ndarray) -> np.ndarray:
    import trimesh

    return trimesh.Trimesh(points, faces, process=False).vertex_normals


def _tips_pressed(device, asset, prep_cache, press: float) -> warpfem.Simulation | None:
    """Two of the piles' armadillos (500 faces, 1 m; gravity and ground off), the second turned half a turn so
    that a vertex where the dense surface stands out of the tets meets its own copy, ``press`` (m) deep; of the
    eight such vertices farthest out, the first where that overlaps the bodies by less than 0.3 % of their size
    (where the surface around it is not hollow). None if none does."""
    from scipy.spatial.transform import Rotation

    arm = {"name": "a", "mesh": str(asset("armadillo.off")), "faces": 500, "scale": 0.0066, "young": 1e6}
    arm |= {"poisson": 0.3, "damping_stiffness": 0.005}

    def scene(objects):
        doc = {"scene": {"frames": 8, "gravity": [0, 0, 0]}, "ground": {"enabled": False}, "object": objects}
        return warpfem.Simulation(warpfem.Scene.from_dict(doc, name="tips"), device=device, cache_dir=prep_cache)

    alone = scene([arm])
    points = alone.dense_points("a")
    normals = _vertex_normals(points, alone.model.bodies[0].dense_faces)
    for v in np.argsort(alone.model.dense_bary.numpy().min(axis=1))[:8]:
        n = normals[v]
        axis = np.cross(n, [0.3, 0.5, 0.8])
        turn = Rotation.from_rotvec(np.pi * axis / np.linalg.norm(axis))
        shift = points[v] - press * n - turn.apply(points[v])
        b = arm | {"name": "b", "rotate": list(turn.as_euler("xyz", degrees=True)), "translate": list(shift)}
        sim = scene([arm, b])
        if 0.0 < warpfem.frame_penetration(sim).relative < 0.003:
            return sim
    return None


def test_bodies_pressed_where_their_surfaces_stand_out_of_the_tets_part(device, asset, prep_cache):
    """Two armadillos pressed 2 mm into each other where each one's dense surface stands out of its tets (the
    piles' armadillo has such parts up to 1.1 % of its size): neither body's tets hold the other's points there,
    and without contacts for points just outside a tet they stayed 1.5-1.8 mm inside each other. Within six
    frames no dense vertex of either lies inside the other (winding numbers on the dense meshes)."""
    sim = _tips_pressed(device, asset, prep_cache, 0.002)
    assert sim is not None, "no vertex out of the tets where a 2 mm press overlaps the bodies by less than 0.3 %"
    for _ in range(6):
        sim.step_frame()
    assert warpfem.frame_penetration(sim).relative == 0.0
