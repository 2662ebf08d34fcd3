"""The fused block-Jacobi PCG against NumPy's dense solver."""

import numpy as np
import pytest
import warp as wp
from warpfem.kernels.cg import HELD_WIDE_BLOCK, cg_solve_held_wide
from warpfem.kernels.product import PAIR_LANES, SHARED_SLOTS

from warpfem.prep.shapes import box_tet_mesh
from warpfem.sim import cg as cg_module
from warpfem.sim.cg import BLOCK, CGSolver
from warpfem.sim.contacts import Coupling
from warpfem.sim.model import block_pattern


@pytest.fixture(
    params=[
        dict(mode="grid"),
        dict(mode="grid", grid_blocks=4),
        dict(mode="grid", grid_blocks=4, hold_chunks=False),
        dict(mode="launches"),
        dict(mode="grid", grid_blocks=4, product="scatter"),
        dict(mode="launches", product="scatter"),
    ],
    ids=["grid", "grid-4-blocks", "grid-4-blocks-unheld", "per-iteration-launches", "grid-scatter", "launches-scatter"],
)
def path(request):
    """Both CG paths: the whole solve in one persistent launch (on CUDA also forced onto 4 blocks, so that
    even these tiny systems meet at real grid barriers, each thread holding its chunk of the product in
    registers or, unheld, reading it every iteration), and two launches per iteration; each with the product
    that gathers (the default at these sizes) and with the one that scatters."""
    return request.param


def _system(device, seed=0, pinned=(), cells=(2, 2, 2)):
    """A random SPD 3x3-block system on a tet mesh's sparsity pattern; returns solver inputs and dense A."""
    rng = np.random.default_rng(seed)
    V, T = box_tet_mesh((0, 0, 0), (1, 1, 1), cells)
    n = len(V)
    row_start, cols, diag_slot, tet_slots = block_pattern(T, n)
    A = np.zeros((3 * n, 3 * n))
    for t in T:  # each tet adds a random SPD 12x12 coupling its corners
        B = rng.normal(size=(12, 12))
        idx = np.concatenate([np.arange(3 * v, 3 * v + 3) for v in t])
        A[np.ix_(idx, idx)] += B @ B.T
    A += 0.5 * np.eye(3 * n)
    values = np.stack(
        [A[3 * i : 3 * i + 3, 3 * c : 3 * c + 3] for i in range(n) for c in cols[row_start[i] : row_start[i + 1]]]
    )
    free = np.ones(n, np.int32)
    free[list(pinned)] = 0
    diag_inv = np.stack([np.linalg.inv(A[3 * i : 3 * i + 3, 3 * i : 3 * i + 3]) for i in range(n)])
    diag_inv[free == 0] = 0
    arrays = dict(
        row_start=wp.array(row_start, dtype=wp.int32, device=device),
        cols=wp.array(cols, dtype=wp.int32, device=device),
        free=wp.array(free, dtype=wp.int32, device=device),
        values=wp.array(values.astype(np.float32), dtype=wp.mat33, device=device),
        diag_inv=wp.array(diag_inv.astype(np.float32), dtype=wp.mat33, device=device),
    )
    return arrays, A, free, rng


def test_cg_solves_spd_system_to_tolerance(device, path):
    a, A, _, rng = _system(device)
    n = A.shape[0] // 3
    b = rng.normal(size=(n, 3))
    cg = CGSolver(a["row_start"], a["cols"], a["free"], 500, device, **path)
    cg.configure(500, 1e-6)
    x = wp.zeros(n, dtype=wp.vec3, device=device)
    cg.solve(a["values"], a["diag_inv"], wp.array(b.astype(np.float32), dtype=wp.vec3, device=device), x)
    stats = cg.read_stats()
    reference = np.linalg.solve(A, b.ravel())
    assert stats.solves == 1 and 0 < stats.iterations < 500
    assert stats.residual_max <= 1e-6
    np.testing.assert_allclose(x.numpy().ravel(), reference, atol=1e-4 * np.abs(reference).max())
    assert np.linalg.norm(A @ x.numpy().ravel() - b.ravel()) < 1e-4 * np.linalg.norm(b)


def test_start_moves_along_a_smooth_direction_only(device, path):
    """The start x + theta d: theta minimises the A-norm error along d (d = the answer: converged at once),
    clamped to [0, 1] (d = -answer: not moved); a direction stiffer than SMOOTH d.M d is not used."""
    a, A, _, rng = _system(device, seed=3)
    n = A.shape[0] // 3
    b = rng.normal(size=(n, 3))
    answer = np.linalg.solve(A, b.ravel()).reshape(n, 3)
    vec = lambda v: wp.array(np.asarray(v, dtype=np.float32), dtype=wp.vec3, device=device)  # noqa: E731
    cg = CGSolver(a["row_start"], a["cols"], a["free"], 500, device, **path)
    cg.configure(500, 1e-5)
    heavy = wp.array(np.full(n, 1e3, np.float32), device=device)  # d.A d well under 2 d.M d
    light = wp.array(np.full(n, 1e-3, np.float32), device=device)  # d.A d far above it
    runs = {}
    for name, direction, mass in [
        ("none", None, None),
        ("answer", answer, heavy),
        ("twice", 2.0 * answer, heavy),
        ("backwards", -answer, heavy),
        ("stiff", answer, light),
    ]:
        x = vec(np.zeros((n, 3)))
        cg.solve(a["values"], a["diag_inv"], vec(b), x, None if direction is None else vec(direction), mass)
        runs[name] = (cg.read_stats().iterations, x.numpy())
    assert runs["none"][0] > 5
    assert runs["answer"][0] == 0 and runs["twice"][0] == 0  # theta = 1 and 1/2: the start is the answer
    np.testing.assert_allclose(runs["twice"][1], answer, atol=1e-3 * np.abs(answer).max())
    for name in ("backwards", "stiff"):  # not moved: the same solve as without a direction
        assert runs[name][0] == runs["none"][0]
        np.testing.assert_allclose(runs[name][1], runs["none"][1], atol=1e-6 * np.abs(answer).max())
    with pytest.raises(ValueError, match="mass"):
        cg.solve(a["values"], a["diag_inv"], vec(b), vec(np.zeros((n, 3))), vec(answer))


def test_fixed_iteration_count_is_exact(device, path):
    a, A, _, rng = _system(device, seed=1)
    n = A.shape[0] // 3
    b = wp.array(rng.normal(size=(n, 3)).astype(np.float32), dtype=wp.vec3, device=device)
    cg = CGSolver(a["row_start"], a["cols"], a["free"], 50, device, **path)
    residuals = []
    for iters in (3, 7):
        cg.configure(iters, 0.0)
        cg.solve(a["values"], a["diag_inv"], b, wp.zeros(n, dtype=wp.vec3, device=device))
        stats = cg.read_stats()
        assert stats.iterations == iters
        residuals.append(stats.residual_max)
    assert residuals[1] < residuals[0]


def test_pinned_rows_keep_their_start_value(device, path):
    pinned = (0, 5, 11)
    a, A, free, rng = _system(device, seed=2, pinned=pinned)
    n = A.shape[0] // 3
    b = rng.normal(size=(n, 3))
    b[list(pinned)] = 0.0
    cg = CGSolver(a["row_start"], a["cols"], a["free"], 500, device, **path)
    cg.configure(500, 1e-7)
    x = wp.zeros(n, dtype=wp.vec3, device=device)
    cg.solve(a["values"], a["diag_inv"], wp.array(b.astype(np.float32), dtype=wp.vec3, device=device), x)
    dofs = np.repeat(free == 1, 3)
    reference = np.zeros(3 * n)
    reference[dofs] = np.linalg.solve(A[np.ix_(dofs, dofs)], b.ravel()[dofs])
    np.testing.assert_allclose(x.numpy().ravel(), reference, atol=1e-4 * np.abs(reference).max())
    assert np.all(x.numpy()[list(pinned)] == 0.0)


@pytest.mark.parametrize("unroll", [1, 3])
def test_coupling_pairs_enter_every_product(device, unroll, path, monkeypatch):
    """Contacts as a matrix-free term: the solve equals the dense solve of A + sum J^T C J."""
    monkeypatch.setattr(cg_module, "PAIR_THREADS", 2)  # fewer pair threads than pairs: each strides
    _check_coupled_solve(device, 5, 8, dict(unroll=unroll, **path))


def test_pairs_beyond_one_per_thread(device):
    """More pairs than the held solve's pair lanes take at once (``HELD_PAIR_BLOCKS`` blocks, ``PAIR_LANES``
    lanes a pair, on CUDA) or than one block has threads (256, with grid_blocks=1): the group's held first
    pair and the ones it reads past it both enter the product."""
    on_cuda = wp.get_device(device).is_cuda
    cg = _check_coupled_solve(device, 300, 320, dict(mode="grid"))
    assert cg.held == on_cuda
    if on_cuda:
        assert cg.pair_lanes // PAIR_LANES < 300 <= cg.grid_threads
    assert not _check_coupled_solve(device, 300, 320, dict(mode="grid", grid_blocks=1)).held  # no room for pairs


def test_more_chunks_than_a_block_of_256_held_in_wider_blocks(device):
    """Where the grid's blocks of 256 threads cannot give every chunk a thread (here one or two blocks for 294
    chunks), blocks of ``HELD_WIDE_BLOCK`` threads hold them (``cg_solve_held_wide``, registers spilling to
    shared memory on CUDA); the answer is NumPy's dense solve, with and without coupling pairs."""
    on_cuda = wp.get_device(device).is_cuda
    a, A, _, rng = _system(device, seed=4, cells=(3, 4, 4))
    cg = CGSolver(a["row_start"], a["cols"], a["free"], 500, device, mode="grid", grid_blocks=1)
    assert cg.held == on_cuda
    if on_cuda:
        assert BLOCK < cg.chunk_row.shape[0] <= HELD_WIDE_BLOCK == cg.grid_threads
        assert cg.held_kernel is cg_solve_held_wide
    _check_random_solve(device, cg, a, A, rng, 500)
    coupled = _check_coupled_solve(device, 5, 8, dict(mode="grid", grid_blocks=2), cells=(3, 4, 4))
    assert coupled.held == on_cuda
    if on_cuda:  # one block of chunks, one of pairs
        assert coupled.held_kernel is cg_solve_held_wide and coupled.pair_lanes == HELD_WIDE_BLOCK


@pytest.mark.parametrize("blocks", [1, 2])
def test_more_chunks_than_threads_held_in_shared_memory(device, blocks):
    """Where even blocks of ``HELD_WIDE_BLOCK`` threads are too few for the chunks but ``SHARED_SLOTS`` chunks a
    thread are not (here about 1,100 chunks on one or two blocks of 256), each thread keeps its chunks, their
    blocks in shared memory (``cg_solve_shared``, CUDA only); the answer is NumPy's dense solve, with and
    without coupling pairs."""
    on_cuda = wp.get_device(device).is_cuda
    a, A, _, rng = _system(device, seed=5, cells=(6, 6, 6))
    cg = CGSolver(a["row_start"], a["cols"], a["free"], 800, device, mode="grid", grid_blocks=blocks)
    assert not cg.held and cg.shared == on_cuda
    if on_cuda:
        assert HELD_WIDE_BLOCK * blocks < cg.chunk_row.shape[0] <= SHARED_SLOTS * cg.grid_threads
    _check_random_solve(device, cg, a, A, rng, 800)
    coupled = _check_coupled_solve(device, 40, 64, dict(mode="grid", grid_blocks=blocks), cells=(6, 6, 6))
    assert coupled.shared == on_cuda


def _check_random_solve(device, cg: CGSolver, a: dict, A: np.ndarray, rng, cap: int) -> None:
    """Solve ``A x = b`` for a random b to 1e-6 within ``cap`` iterations; check x against NumPy's dense solve."""
    n = A.shape[0] // 3
    b = rng.normal(size=(n, 3))
    cg.configure(cap, 1e-6)
    x = wp.zeros(n, dtype=wp.vec3, device=device)
    cg.solve(a["values"], a["diag_inv"], wp.array(b.astype(np.float32), dtype=wp.vec3, device=device), x)
    reference = np.linalg.solve(A, b.ravel())
    assert cg.read_stats().residual_max <= 1e-6
    np.testing.assert_allclose(x.numpy().ravel(), reference, atol=1e-4 * np.abs(reference).max())


def _check_coupled_solve(device, pairs: int, capacity: int, options: dict, cells=(2, 2, 2)) -> CGSolver:
    """Solve a random system with ``pairs`` coupling pairs; check it against NumPy's dense solve."""
    a, A, _, rng = _system(device, seed=3, cells=cells)
    n = A.shape[0] // 3
    verts = np.stack([rng.permutation(n)[:8] for _ in range(pairs)]).astype(np.int32)  # distinct per pair
    weights = rng.dirichlet(np.ones(4), size=(pairs, 2))
    C = []
    A_full = A.copy()
    values = a["values"].numpy()
    row_start, cols = a["row_start"].numpy(), a["cols"].numpy()
    for c in range(pairs):
        B = rng.normal(size=(3, 3))
        C.append(B @ B.T + np.eye(3))
        J = np.zeros((3, 3 * n))
        for k in range(4):
            J[:, 3 * verts[c, k] : 3 * verts[c, k] + 3] += weights[c, 0, k] * np.eye(3)
            J[:, 3 * verts[c, 4 + k] : 3 * verts[c, 4 + k] + 3] -= weights[c, 1, k] * np.eye(3)
        A_full += J.T @ C[c] @ J
        for k in range(8):  # the diagonal blocks go into the assembled matrix
            v, wk = verts[c, k], weights[c, k // 4, k % 4]
            slot = row_start[v] + np.flatnonzero(cols[row_start[v] : row_start[v + 1]] == v)[0]
            values[slot] += wk * wk * C[c]
    diag_inv = np.stack([np.linalg.inv(A_full[3 * i : 3 * i + 3, 3 * i : 3 * i + 3]) for i in range(n)])

    def pad(x, dtype):
        full = np.zeros((capacity, *x.shape[1:]), x.dtype)
        full[: len(x)] = x
        return wp.array(full.astype(np.float32 if dtype is not wp.vec4i else np.int32), dtype=dtype, device=device)

    coupling = Coupling(
        wp.array([pairs], dtype=wp.int32, device=device),
        pad(verts[:, :4], wp.vec4i),
        pad(weights[:, 0], wp.vec4),
        pad(verts[:, 4:], wp.vec4i),
        pad(weights[:, 1], wp.vec4),
        pad(np.array(C), wp.mat33),
    )
    b = rng.normal(size=(n, 3))
    cg = CGSolver(a["row_start"], a["cols"], a["free"], 500, device, coupling=coupling, **options)
    cg.configure(500, 1e-6)
    x0 = rng.normal(size=(n, 3))  # a nonzero start: the coupling enters the initial residual too
    x = wp.array(x0.astype(np.float32), dtype=wp.vec3, device=device)
    values_wp = wp.array(values.astype(np.float32), dtype=wp.mat33, device=device)
    diag_wp = wp.array(diag_inv.astype(np.float32), dtype=wp.mat33, device=device)
    cg.solve(values_wp, diag_wp, wp.array(b.astype(np.float32), dtype=wp.vec3, device=device), x)
    reference = np.linalg.solve(A_full, b.ravel())
    assert cg.read_stats().residual_max <= 1e-6
    np.testing.assert_allclose(x.numpy().ravel(), reference, atol=1e-4 * np.abs(reference).max())
    return cg


def test_product_is_chosen_by_size_and_checked(device, monkeypatch):
    a = _system(device)[0]
    args = (a["row_start"], a["cols"], a["free"], 10, device)
    assert CGSolver(*args).product == ("gather" if wp.get_device(device).is_cuda else "scatter")  # 27 rows
    assert CGSolver(*args, product="gather").product == "gather"
    monkeypatch.setattr(cg_module, "GATHER_MAX_ROWS", 20)
    assert CGSolver(*args).product == "scatter"
    with pytest.raises(ValueError, match="product"):
        CGSolver(*args, product="dense")


def test_configure_rejects_out_of_range(device, path):
    a, _, _, _ = _system(device)
    cg = CGSolver(a["row_start"], a["cols"], a["free"], 10, device, **path)
    with pytest.raises(ValueError):
        cg.configure(11, 1e-3)
    with pytest.raises(ValueError):
        cg.configure(5, 1.5)


def test_default_path_is_one_persistent_launch(device):
    """The grid path unless told otherwise (measured ahead at every size, see ``DEFAULT_MODE``)."""
    a, _, _, _ = _system(device)
    assert CGSolver(a["row_start"], a["cols"], a["free"], 10, device).mode == "grid"
    assert CGSolver(a["row_start"], a["cols"], a["free"], 10, device, mode="launches").mode == "launches"
    with pytest.raises(ValueError, match="mode"):
        CGSolver(a["row_start"], a["cols"], a["free"], 10, device, mode="fast")


def test_chunks_held_only_where_each_has_a_thread(device):
    """A grid solve with a gathered product holds each thread's chunk in registers when every chunk has a
    thread of its own (CUDA, small systems); never on the CPU (one thread), with the scatter, per-iteration
    launches, or when told not to."""
    a = _system(device)[0]
    args = (a["row_start"], a["cols"], a["free"], 10, device)
    on_cuda = wp.get_device(device).is_cuda
    assert CGSolver(*args, mode="grid", product="gather").held == on_cuda
    assert CGSolver(*args, mode="grid", grid_blocks=1, product="gather").held == on_cuda  # 256 threads, ~100 chunks
    assert not CGSolver(*args, mode="grid", product="gather", hold_chunks=False).held
    assert not CGSolver(*args, mode="grid", product="scatter").held
    assert not CGSolver(*args, mode="launches", product="gather").held


def test_a_stiff_body_on_the_ground_converges_with_scene_defaults():
    """The bunny (2.6 m across) of 1e8 Pa landing and resting on the ground, nothing set but its modulus: the
    default cap leaves CG room for a stiff body's conditioning, so every solve reaches the default tolerance,
    measured on the system rebuilt with SciPy (a cap of 100 stopped a third of them short)."""
    from solves import record_solves, worst_residual

    import warpfem

    body = {"name": "b", "mesh": "builtin:bunny", "subdivide": 0, "faces": 400, "rotate": [15.0, 30.0, 0.0]}
    doc = {"scene": {"frames": 30}, "object": [{**body, "translate": [0.0, 0.3, 0.0], "young": 1e8}]}
    sim = warpfem.Simulation(warpfem.Scene.from_dict(doc, name="stiff"), device="cpu")
    solves = record_solves(sim)
    for _ in range(30):
        sim.step_frame()
    assert len(solves) > 100
    assert worst_residual(sim, solves) < 2.0 * sim.scene.solver.cg_tolerance  # float32 rounding aside


@pytest.mark.parametrize("young", [1e7, 1e9])
def test_a_run_says_when_float32_cannot_resolve_the_tolerance(young):
    """The bunny (2.6 m across) landing on the ground. At 1e9 Pa CG's recurrence reaches the tolerance while the
    system's residual (float64, with SciPy, from the stored blocks and float32 answers) stays several times
    above it: the run warns once, and its float32 floor estimate is within a factor 3 of that residual. At
    1e7 Pa the system's residual meets the tolerance, and nothing is said."""
    from solves import record_solves, worst_residual

    import warpfem

    body = {"name": "b", "mesh": "builtin:bunny", "subdivide": 0, "faces": 400, "rotate": [15.0, 30.0, 0.0]}
    doc = {"scene": {"frames": 30}, "object": [{**body, "translate": [0.0, 0.3, 0.0], "young": young}]}
    said = []
    sim = warpfem.Simulation(warpfem.Scene.from_dict(doc, name="stiff"), device="cpu", warn=said.append)
    solves = record_solves(sim)
    for _ in range(30):
        sim.step_frame()
    measured, tolerance = worst_residual(sim, solves), sim.scene.solver.cg_tolerance
    floor = sim.totals.cg_float32_floor
    warned = [w for w in said if "float32" in w]
    if young > 1e8:
        assert measured > 3.0 * tolerance and sim.totals.cg_residual_max <= tolerance * 1.01  # CG's own: met
        assert len(warned) == 1 and "'b'" in warned[0]
        assert measured / 3.0 < floor < 3.0 * measured
    else:
        assert measured < 2.0 * tolerance and floor < tolerance and warned == []


def test_the_float32_floor_is_said_on_every_device(device):
    """The floor's estimate and its warning come from the solver's blocks read between frames, on any device: the
    bunny (2.6 m across) of 1e9 Pa is warned about once, of 1e7 Pa not (the CPU test above checks the estimate)."""
    import warpfem

    body = {"name": "b", "mesh": "builtin:bunny", "subdivide": 0, "faces": 400, "translate": [0.0, 0.3, 0.0]}
    floors = []
    for young in (1e7, 1e9):
        said = []
        doc = {"scene": {"frames": 3}, "object": [{**body, "young": young}]}
        sim = warpfem.Simulation(warpfem.Scene.from_dict(doc, name="stiff"), device=device, warn=said.append)
        for _ in range(3):
            sim.step_frame()
        floors.append((sim.totals.cg_float32_floor, len([w for w in said if "float32" in w])))
    tolerance = sim.scene.solver.cg_tolerance
    (soft, soft_said), (stiff, stiff_said) = floors
    assert soft < tolerance and soft_said == 0
    assert stiff > tolerance and stiff_said == 1
    assert stiff / soft == pytest.approx(100.0, rel=0.2)  # the elastic diagonal scales with Young's modulus


def test_the_float32_floor_script_reports_each_modulus(capsys):
    """scripts/float32_floor.py: one line per modulus. In flight (4 frames) at 1e9 Pa the bunny's residual
    measured with SciPy is already several times what CG reports, at 1e7 Pa the two agree; R, the run's estimate
    (0.25 u R in flight, where no contact adds to the diagonal) and the iterations grow with the modulus."""
    import importlib.util
    import re
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "scripts" / "float32_floor.py"
    spec = importlib.util.spec_from_file_location("float32_floor", path)
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    assert script.main(["1e7,1e9", "--frames", "4"]) == 0
    lines = [line for line in capsys.readouterr().out.splitlines() if line.startswith("E ")]
    assert [line.split()[1] for line in lines] == ["1e+07", "1e+09"]
    keys = ("Pa: R", "estimate", "reported", "measured")
    (soft, stiff) = [{k: float(re.search(rf"{k} ([0-9.e+-]+)", line).group(1)) for k in keys} for line in lines]
    for run in (soft, stiff):
        assert run["estimate"] == pytest.approx(0.25 * 2.0**-24 * run["Pa: R"], rel=0.02)
    assert stiff["Pa: R"] == pytest.approx(100.0 * soft["Pa: R"], rel=0.05)
    assert soft["measured"] == pytest.approx(soft["reported"], rel=0.05)
    assert stiff["measured"] > 5.0 * stiff["reported"]


def test_no_warning_where_the_shared_tile_does_not_fit():
    """On a GPU whose blocks get less shared memory than ``cg_solve_shared``'s tile, Warp says at each load of the
    CG module that it could not size that kernel (its message, emitted here as Warp's loader does, in a process of
    its own: pytest replaces the warning filters); the solver never launches it there, so the warning is filtered,
    and other kernels' warnings still show."""
    import subprocess
    import sys

    code = (
        "import warpfem.sim.cg\n"
        "from warp._src.logger import log_warning\n"
        "for k in ('cg_solve_shared', 'another'):\n"
        "    log_warning(f\"Failed to configure dynamic shared memory for kernel '{k}' (forward) on cuda:0: x\")\n"
    )
    err = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stderr
    assert "cg_solve_shared" not in err and "'another'" in err
