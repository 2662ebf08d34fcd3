"""Friction between bodies: the Coulomb law against the analytic incline, and solves that converge where a soft
body rests on a stiff one.

References are independent of the simulator: the analytic acceleration of a block on an incline, and each
linear system the step solves rebuilt with SciPy from the solver's inputs (its stored blocks and contact pairs)
and the residual of the answer measured there.
"""

import numpy as np
import pytest
import scipy.sparse as sp
from scipy.spatial.transform import Rotation

import warpfem
from warpfem.prep.shapes import box_tet_mesh
from warpfem.sim.collision import CollisionSettings
from warpfem.sim.solver import Solver

G = 9.81


def _incline(device, theta_deg, mu, stiffness=1e7):
    """A block of 10 cm resting on a pinned slab tilted by ``theta_deg`` (about z, downhill towards +x)."""
    rot = Rotation.from_euler("z", -np.radians(theta_deg)).as_matrix()
    down, normal = rot @ [1.0, 0.0, 0.0], rot @ [0.0, 1.0, 0.0]
    sv, st = box_tet_mesh((-1.0, -0.1, -0.3), (1.0, 0.0, 0.3), (10, 1, 3))
    bv, bt = box_tet_mesh((-0.05, 0.0, -0.05), (0.05, 0.05, 0.05), (2, 1, 2))
    builder = warpfem.ModelBuilder()
    warpfem.add_body(builder, "slab", sv @ rot.T, st, 1e7, 0.3, 1000.0, pinned=np.ones(len(sv), bool))
    warpfem.add_body(builder, "block", (bv + [0.0, 0.001, 0.0]) @ rot.T - 0.5 * down, bt, 1e7, 0.3, 1000.0)
    model = builder.finalize(device)
    solver = Solver(model, ground=None, collision=CollisionSettings(stiffness=stiffness, friction=mu))
    return warpfem.Simulation.from_model(model, solver, substeps=4, fps=60.0), down, normal


def _slide(sim, down, frames=45, start=10):
    """Times (s) and the block's centre along ``down`` (m) from frame ``start`` (landed) on."""
    times, along = [], []
    for frame in range(1, frames + 1):
        sim.step_frame()
        if frame >= start:
            times.append(frame / 60.0)
            along.append(sim.tet_points("block").mean(axis=0) @ down)
    return np.array(times), np.array(along)


def test_a_block_slides_down_a_body_at_the_acceleration_friction_predicts(device):
    theta, mu = 25.0, 0.2
    sim, down, normal = _incline(device, theta, mu)
    times, along = _slide(sim, down)
    accel = 2.0 * np.polyfit(times, along, 2)[0]
    t = np.radians(theta)
    assert accel == pytest.approx(G * (np.sin(t) - mu * np.cos(t)), rel=0.03)
    gap = (sim.tet_points("block") @ normal).min()
    assert abs(gap) < 1e-3  # on the slab's face (within 1 mm), not through it


@pytest.mark.parametrize("stiffness", [1e7, 1e6])
def test_a_block_sticks_on_a_body_below_the_friction_angle(device, stiffness):
    """Below the friction angle (tan 25 deg = 0.47 < mu = 0.8) the block stays put, also where a softer penalty
    holds it deeper (the contact's depth sets how far friction may creep)."""
    sim, down, _ = _incline(device, 25.0, 0.8, stiffness)
    _, along = _slide(sim, down)
    assert abs(along[-1] - along[0]) < 1e-3  # under 1 mm in 0.6 s


def _bunny_stack(youngs):
    """Half-size bunnies stacked on the ground, one per Young's modulus (Pa), bottom first; scene defaults
    otherwise (CG to 1e-4, at most 100 iterations)."""
    objects = [
        {
            "name": f"b{k}",
            "mesh": "builtin:bunny",
            "subdivide": 0,
            "faces": 400,
            "scale": 0.5,
            "translate": [0.05 * k, 0.25 + 0.42 * k, 0.0],
            "young": young,
        }
        for k, young in enumerate(youngs)
    ]
    doc = {"scene": {"frames": 45, "substeps": 4}, "object": objects}
    return warpfem.Scene.from_dict(doc, name="contrast")


def _system(model, values, pairs):
    """The solve's matrix with SciPy: stored upper-triangle blocks mirrored, plus each contact pair's coupling
    between distinct nodes (``J^T C J`` off the diagonal; the diagonal blocks already hold ``w^2 C``)."""
    n = model.vertex_count
    starts, cols = model.row_start.numpy(), model.cols.numpy()
    rows = np.repeat(np.arange(n), np.diff(starts))
    a, b = np.meshgrid(np.arange(3), np.arange(3), indexing="ij")
    r = (3 * rows[:, None, None] + a).ravel()
    c = (3 * cols[:, None, None] + b).ravel()
    upper = sp.coo_matrix((values.reshape(-1), (r, c)), shape=(3 * n, 3 * n)).tocsr()
    strict = upper - sp.block_diag([values[s] for s in model.diag_slot.numpy()]).tocsr()
    A = upper + strict.T
    va, wa, vb, wb, C = pairs
    if len(va):
        idx = np.concatenate([va, vb], axis=1)  # (k, 8) nodes
        w = np.concatenate([wa, -wb], axis=1)  # (k, 8) weights
        p, q = np.meshgrid(np.arange(8), np.arange(8), indexing="ij")
        keep = p != q
        p, q = p[keep], q[keep]
        blk = (w[:, p] * w[:, q])[:, :, None, None] * C[:, None]  # (k, 56, 3, 3)
        r = (3 * idx[:, p][:, :, None, None] + a).ravel()
        c = (3 * idx[:, q][:, :, None, None] + b).ravel()
        A = A + sp.coo_matrix((blk.ravel(), (r, c)), shape=A.shape).tocsr()
    return A.tocsr()


def _record_solves(sim):
    """Wrap the solver's CG (on the CPU, not captured) so that every solve keeps its inputs, its start
    (``x0``) and its answer (``x``)."""
    cg, solves = sim.solver.cg, []
    solve = cg.solve

    def recording(values, diag_inv, b, x, *args, **kwargs):
        pairs = [np.zeros((0, 4), int), np.zeros((0, 4)), np.zeros((0, 4), int), np.zeros((0, 4)), np.zeros((0, 3, 3))]
        if sim.solver.collider is not None:
            c = sim.solver.collider.coupling
            k = int(c.count.numpy()[0])
            pairs = [arr.numpy()[:k].copy() for arr in (c.verts_a, c.weights_a, c.verts_b, c.weights_b, c.matrix)]
        entry = dict(values=values.numpy().copy(), b=b.numpy().copy(), x0=x.numpy().copy(), pairs=pairs)
        out = solve(values, diag_inv, b, x, *args, **kwargs)
        entry["x"] = x.numpy().copy()
        solves.append(entry)
        return out

    cg.solve = recording
    return solves


@pytest.mark.slow
@pytest.mark.parametrize("youngs", [(3e5, 1e7), (1e7, 3e5)], ids=["soft-under-stiff", "stiff-under-soft"])
def test_solves_converge_where_a_soft_body_rests_on_a_stiff_one(youngs):
    """Bodies 30x apart in stiffness, resting on each other with friction: every solve reaches CG's tolerance,
    measured on the system rebuilt with SciPy (block-Jacobi norm, as CG's stopping rule)."""
    sim = warpfem.Simulation(_bunny_stack(youngs), device="cpu")
    solves = _record_solves(sim)
    for _ in range(45):
        sim.step_frame()
    free = np.repeat(sim.model.free.numpy() != 0, 3)
    tol = sim.scene.solver.cg_tolerance
    worst = 0.0
    for s in solves:
        A = _system(sim.model, s["values"], s["pairs"])[free][:, free]
        b, x = s["b"].reshape(-1)[free].astype(float), s["x"].reshape(-1)[free].astype(float)
        blocks = [A[i : i + 3, i : i + 3].toarray() for i in range(0, A.shape[0], 3)]
        m_inv = sp.block_diag([np.linalg.inv(blk) for blk in blocks]).tocsr()
        r = b - A @ x
        worst = max(worst, np.sqrt((r @ (m_inv @ r)) / (b @ (m_inv @ b))))
    assert len(solves) > 100
    assert worst < 2.0 * tol  # float32 rounding aside
