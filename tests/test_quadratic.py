"""Quadratic (10-node) tets against NGSolve's order-2 elements on the same mesh, and their mass and motion."""

import numpy as np
import pytest

from warpfem.build import add_body
from warpfem.errors import InputError
from warpfem.prep.shapes import box_tet_mesh
from warpfem.sim.model import EDGES, ModelBuilder, quadratic_nodes
from warpfem.sim.solver import Solver
from warpfem.study.reference import Cantilever, sag_on_tets

BOX = ((0, 0, 0), (1.0, 0.1, 0.1), (20, 2, 2))
"""The cantilever two tets across: linear tets lock (half the sag), quadratic ones do not."""


def _model(device, beam, vertices, tets, quadratic=True):
    b = ModelBuilder()
    add_body(b, "beam", vertices, tets, beam.young, beam.poisson, beam.density, pinned=vertices[:, 0] < 1e-9,
             quadratic=quadratic)  # fmt: skip
    return b.finalize(device)


def _sag(device, beam, vertices, tets, steps, dt, quadratic=True, **solver):
    model = _model(device, beam, vertices, tets, quadratic)
    solver = Solver(model, gravity=(0, -beam.gravity, 0), ground=None, cg_iterations=5000, cg_tolerance=1e-7, **solver)
    s0, s1 = model.state(), model.state()
    tip = np.isclose(vertices[:, 0], beam.length)  # the corners on the tip face
    sags = []
    for _ in range(steps):  # backward Euler with a long step relaxes to the static equilibrium
        solver.step(s0, s1, dt)
        s0, s1 = s1, s0
        sags.append(vertices[tip, 1].mean() - s0.x.numpy()[: len(vertices)][tip, 1].mean())
    return np.array(sags)


def test_settles_at_ngsolve_order_2_linear_elasticity_on_the_same_tets(device):
    beam = Cantilever(young=1e8)  # a small deflection (1.5 % of the length): linear elasticity's answer
    V, T = box_tet_mesh(*BOX)
    order2, order1 = sag_on_tets(beam, V, T, order=2), sag_on_tets(beam, V, T)
    assert order1 < 0.7 * order2  # the mesh locks with linear tets
    # long steps relax to the equilibrium of the elastic force (one solve from rest would carry the float32
    # rounding of a stiffness this ill-conditioned, about 1 %)
    sags = _sag(device, beam, V, T, 10, 100.0, rotation_updates=0)
    assert sags[-1] == pytest.approx(order2, rel=3e-3)
    assert sags[-2] == pytest.approx(sags[-1], rel=1e-3)


def test_large_deflection_settles_at_ngsolve_order_2_nonlinear(device):
    beam = Cantilever(young=1e6)  # sags 75 % of its length
    V, T = box_tet_mesh(*BOX)
    nonlinear = sag_on_tets(beam, V, T, nonlinear=True, load_steps=8, order=2)
    b = ModelBuilder()
    add_body(b, "beam", V, T, beam.young, beam.poisson, beam.density, pinned=V[:, 0] < 1e-9, quadratic=True,
             damping_mass=8.0)  # fmt: skip
    model = b.finalize(device)
    solver = Solver(model, gravity=(0, -beam.gravity, 0), ground=None, cg_iterations=2000, cg_tolerance=1e-6)
    s0, s1 = model.state(), model.state()
    tip = np.isclose(V[:, 0], beam.length)
    for _ in range(240):  # 4 s at 60 Hz, damped to rest
        solver.step(s0, s1, 1.0 / 60.0)
        s0, s1 = s1, s0
    corotational = V[tip, 1].mean() - s0.x.numpy()[: len(V)][tip, 1].mean()
    # corotational linear elasticity is not Saint Venant-Kirchhoff: they part by about 1.4 % at this sag
    assert corotational == pytest.approx(nonlinear, rel=0.02)
    assert corotational > 1.3 * sag_on_tets(beam, V, T, nonlinear=True, load_steps=8)  # linear tets lock


def test_lumped_mass_is_positive_and_sums_to_the_body(device):
    beam = Cantilever()
    V, T = box_tet_mesh(*BOX)
    mass = _model(device, beam, V, T).mass.numpy()
    nodes, edges = quadratic_nodes(V, T)
    assert len(mass) == len(nodes) == len(V) + len({tuple(sorted(e)) for e in T[:, np.array(EDGES)].reshape(-1, 2)})
    assert (mass > 0).all()
    assert mass.sum() == pytest.approx(beam.density * 0.01, rel=1e-5)
    for k, (i, j) in enumerate(EDGES):
        assert np.allclose(nodes[edges[:, k]], 0.5 * (V[T[:, i]] + V[T[:, j]]))


def test_free_body_falls_and_spins_rigidly(device):
    V, T = box_tet_mesh((0, 0, 0), (0.3, 0.2, 0.1), (3, 2, 1))
    centre = V.mean(axis=0)
    spin = np.array([0.0, 0.0, 3.0])
    velocity = np.cross(spin, V - centre)
    b = ModelBuilder()
    add_body(b, "box", V, T, 1e7, 0.3, 1000.0, velocity=velocity, quadratic=True)
    model = b.finalize(device)
    solver = Solver(model, gravity=(0, -9.81, 0), ground=None, cg_iterations=2000, cg_tolerance=1e-8)
    s0, s1 = model.state(), model.state()
    dt, steps = 1.0 / 240.0, 48
    for _ in range(steps):
        solver.step(s0, s1, dt)
        s0, s1 = s1, s0
    x, rest, mass = s0.x.numpy().astype(np.float64), model.rest_x.numpy().astype(np.float64), model.mass.numpy()
    t = dt * steps
    # the centre of mass falls as a point does (implicit Euler: g dt^2 n (n + 1) / 2)
    drop = (mass[:, None] * (rest - x)).sum(axis=0) / mass.sum()
    assert drop[1] == pytest.approx(9.81 * dt * dt * steps * (steps + 1) / 2, rel=1e-3)
    # and keeps its shape: the distances between its corners stay within 0.5 % of their rest lengths
    d0 = np.linalg.norm(rest[T[:, 0]] - rest[T[:, 3]], axis=1)
    d = np.linalg.norm(x[T[:, 0]] - x[T[:, 3]], axis=1)
    assert np.abs(d / d0 - 1).max() < 5e-3
    # having turned about its axis as it was set spinning, less what implicit Euler damps
    first = rest[T[0, 1]] - rest[T[0, 0]]
    now = x[T[0, 1]] - x[T[0, 0]]
    angle = np.arctan2(first[0] * now[1] - first[1] * now[0], first[:2] @ now[:2])
    assert angle == pytest.approx(3.0 * t, rel=0.05)


def test_mixed_linear_and_quadratic_bodies_are_an_input_error():
    V, T = box_tet_mesh((0, 0, 0), (0.3, 0.2, 0.1), (3, 2, 1))
    b = ModelBuilder()
    add_body(b, "a", V, T, 1e7, 0.3, 1000.0, quadratic=True)
    add_body(b, "b", V + 1.0, T, 1e7, 0.3, 1000.0)
    with pytest.raises(InputError, match="all have linear tets or all quadratic"):
        b.finalize("cpu")


def test_edge_nodes_that_do_not_match_the_tets_are_an_input_error():
    V, T = box_tet_mesh((0, 0, 0), (0.3, 0.2, 0.1), (3, 2, 1))
    nodes, edges = quadratic_nodes(V, T)
    from warpfem.prep.geometry import body_geometry

    geometry = body_geometry(V, T, 0.0)
    b = ModelBuilder()
    with pytest.raises(InputError, match="tet_edges"):
        b.add_body("a", nodes, T, geometry, 1e7, 0.3, 1000.0, tet_edges=edges[:, ::-1])


def _quadratic_energy(x, v, mass, vertices, tets, edges, young, poisson):
    """Kinetic plus corotated elastic energy (J) of quadratic tets: at each of four points per tet, from the
    singular values of that point's deformation gradient (NumPy, float64)."""
    from warpfem.sim.model import lame

    mu, lam = lame(young, poisson)
    a, b = 0.5854101966249685, 0.1381966011250105
    d = vertices[tets[:, 1:]] - vertices[tets[:, :1]]
    volume = np.linalg.det(d) / 6.0
    g = np.linalg.inv(np.transpose(d, (0, 2, 1)))  # rows: gradients of barycentrics 1..3
    g = np.concatenate([-g.sum(axis=1, keepdims=True), g], axis=1)  # (q, 4, 3)
    nodes = np.concatenate([tets, edges], axis=1)
    elastic = 0.0
    for q in range(4):
        lam_q = np.full(4, b)
        lam_q[q] = a
        grads = [(4 * lam_q[c] - 1) * g[:, c] for c in range(4)]
        grads += [4 * (lam_q[i] * g[:, j] + lam_q[j] * g[:, i]) for i, j in EDGES]
        F = sum(np.einsum("qi,qj->qij", x[nodes[:, n]], grads[n]) for n in range(10))
        s = np.linalg.svd(F, compute_uv=False)
        s[:, 2] *= np.sign(np.linalg.det(F))
        e = s - 1.0
        elastic += np.sum(0.25 * volume * (mu * np.sum(e * e, axis=1) + 0.5 * lam * np.sum(e, axis=1) ** 2))
    return 0.5 * np.sum(mass * np.sum(v * v, axis=1)) + elastic


@pytest.mark.parametrize("young", (1e3, 1e9))
@pytest.mark.parametrize("poisson", (0.0, 0.49))
@pytest.mark.parametrize("dt", (1 / 1000, 1 / 24))
def test_material_and_time_step_extremes(device, young, poisson, dt):
    """A cube released stretched 30 % and squeezed 20 %, in free flight, gains no energy in any step and keeps
    its shape. The CG statistics are read after every step, as a run reads them after each frame."""
    V, T = box_tet_mesh((0, 0, 0), (0.2, 0.2, 0.2), (2, 2, 2))
    b = ModelBuilder()
    add_body(b, "cube", V, T, young, poisson, 1000.0, quadratic=True)
    model = b.finalize(device)
    rest = model.rest_x.numpy().astype(np.float64)
    edges = model.tet_edges.numpy()
    mass = model.mass.numpy().astype(np.float64)
    solver = Solver(model, gravity=(0, 0, 0), ground=None, cg_iterations=500, cg_tolerance=1e-5)
    s0, s1 = model.state(), model.state()
    s0.x.assign((rest * np.array([1.3, 0.8, 1.0])).astype(np.float32))
    energies = []
    for _ in range(30):
        x, v = s0.x.numpy().astype(np.float64), s0.v.numpy().astype(np.float64)
        energies.append(_quadratic_energy(x, v, mass, rest, T, edges, young, poisson))
        solver.step(s0, s1, dt)
        solver.read_cg_stats()
        s0, s1 = s1, s0
    assert solver.first_bad_vertex() is None
    assert np.isfinite(energies).all()
    allowed = 1e-2 * energies[0] + 1e-6
    assert max(energies) <= energies[0] + allowed, energies
    assert np.diff(energies).max() <= allowed, energies
    assert np.ptp(s0.x.numpy(), axis=0).max() < 2.0  # nothing flew apart


def test_sub_tets_tile_the_tet_and_hold_each_point_with_weights_that_reproduce_it():
    """The eight sub-tets of a quadratic tet fill it (positive volumes, an eighth each); a point inside gets
    non-negative weights in its sub-tet, and they give back its position."""
    from warpfem.sim.cells import SUB_TETS, shortest_diagonals, sub_cells

    rng = np.random.default_rng(5)
    corners = np.array([[0.0, 0.0, 0.0], [1.0, 0.1, 0.0], [0.2, 0.9, 0.1], [0.1, 0.2, 1.2]])
    nodes = np.vstack([corners, [(corners[a] + corners[b]) / 2 for a, b in EDGES]])
    edges_of = nodes[SUB_TETS[:, :, 1:]] - nodes[SUB_TETS[:, :, :1]]
    volumes = np.linalg.det(edges_of) / 6
    whole = np.linalg.det(corners[1:] - corners[0]) / 6
    np.testing.assert_allclose(volumes, whole / 8, rtol=1e-12)
    assert shortest_diagonals(corners, np.array([[0, 1, 2, 3]]))[0] == 1  # the midpoints of edges 0-2 and 1-3
    bary = rng.dirichlet(np.ones(4), size=2000)
    for diagonal in range(3):
        cell, weights = sub_cells(np.zeros(2000, np.int32), bary, np.array([diagonal]))
        assert weights.min() > -1e-12 and cell.min() >= 0 and cell.max() < 8
        back = np.einsum("nk,nkd->nd", weights, nodes[SUB_TETS[diagonal][cell]])
        np.testing.assert_allclose(back, bary @ corners, atol=1e-12)


def test_dense_points_follow_the_quadratic_field_four_times_closer_than_the_corners(device):
    """Tet nodes moved by a quadratic field u(X), which quadratic tets represent exactly: the dense points the
    model maps (its own kernel) lie within a quarter of the error of the corners' linear interpolation
    (NumPy) of the analytic u at the points' rest positions, nearly every one closer than the corners put it."""
    import warp as wp

    from warpfem.prep.embedding import embed
    from warpfem.prep.tetmesh import boundary_faces
    from warpfem.sim.embedding import map_dense

    V, T = box_tet_mesh((0, 0, 0), (1.0, 0.2, 0.2), (6, 2, 2))
    rng = np.random.default_rng(6)
    dense = rng.uniform((0.0, 0.0, 0.0), (1.0, 0.2, 0.2), size=(3000, 3))
    tet, bary = embed(dense, V, T, boundary_faces(T))
    b = ModelBuilder()
    add_body(b, "bar", V, T, 1e6, 0.3, 1000.0, quadratic=True, embed_tet=tet, embed_bary=bary)
    model = b.finalize(device)

    def bent(x):
        return x + np.column_stack([0.1 * x[:, 1] * x[:, 0], -0.4 * x[:, 0] ** 2, 0.3 * x[:, 1] * x[:, 2]])

    nodes = bent(model.rest_x.numpy().astype(np.float64))
    out = wp.zeros(len(dense), dtype=wp.vec3, device=device)
    map_dense(model.cells, wp.array(nodes, dtype=wp.vec3, device=device), model.dense_cell, model.dense_bary, out)
    exact = bent(dense)
    corners = np.einsum("nk,nkd->nd", bary, nodes[T[tet]])
    ours, linear = np.linalg.norm(out.numpy() - exact, axis=1), np.linalg.norm(corners - exact, axis=1)
    assert ours.max() < 0.26 * linear.max()
    assert (ours <= linear + 1e-6).mean() > 0.95


def test_each_sub_tet_adds_its_blocks_where_the_matrix_stores_them(device):
    """A skin point's term in a quadratic tet goes to its sub-tet's 4 x 4 node blocks: each cell slot is the
    stored block (row <= column) of its two nodes in the CSR pattern, -1 below the diagonal, and the cells'
    nodes are their tets' nodes."""
    V, T = box_tet_mesh((0, 0, 0), (1.0, 0.2, 0.2), (3, 1, 1))
    b = ModelBuilder()
    add_body(b, "bar", V, T, 1e6, 0.3, 1000.0, quadratic=True)
    model = b.finalize(device)
    row_start, cols = model.row_start.numpy(), model.cols.numpy()
    cells, slots = model.cells.numpy(), model.cell_slots.numpy().reshape(-1, 4, 4)
    nodes = np.hstack([model.tets.numpy(), model.tet_edges.numpy()])
    assert len(cells) == 8 * len(nodes)
    for c, cell in enumerate(cells):
        assert set(cell) <= set(nodes[c // 8])
        for a in range(4):
            for k in range(4):
                i, j = cell[a], cell[k]
                if i > j:
                    assert slots[c, a, k] == -1
                else:
                    assert cols[slots[c, a, k]] == j and row_start[i] <= slots[c, a, k] < row_start[i + 1]


def test_a_quadratic_scene_draws_its_dense_meshes_where_a_linear_one_does_at_rest(device, tmp_path):
    """Two bunnies, placed apart: before any step, the dense meshes that quadratic tets map through their
    sub-tets are the same points the corners of linear tets give (each body's cells offset in the flat arrays)."""
    import warpfem

    def scene(elements):
        bunny = {"mesh": "builtin:bunny", "subdivide": 0, "faces": 300, "scale": 0.5}
        doc = {
            "scene": {"frames": 1},
            "solver": {"elements": elements},
            "object": [
                {**bunny, "name": "left", "translate": [-0.6, 0.4, 0.0], "rotate": [0.0, 30.0, 10.0]},
                {**bunny, "name": "right", "translate": [0.6, 0.4, 0.0]},
            ],
        }
        return warpfem.Simulation(warpfem.Scene.from_dict(doc, name=elements), device=device, cache_dir=tmp_path)

    linear, quadratic = scene("linear"), scene("quadratic")
    assert quadratic.model.cells.shape[0] == 8 * quadratic.model.tet_count
    for a, b in zip(linear.dense_points(), quadratic.dense_points(), strict=True):
        np.testing.assert_allclose(b, a, atol=1e-5)
