"""Simplification, Netgen tetrahedralization and prepare() with its cache."""

import sys
import time
from collections import Counter

import igl
import numpy as np
import pytest
import trimesh
from mesh_kinds import cad_bracket, write_obj

from warpfem.errors import InputError
from warpfem.prep.pipeline import cached_surface_samples, prepare
from warpfem.prep.samples import surface_samples
from warpfem.prep.simplify import simplify
from warpfem.prep.tetmesh import tet_quality, tet_signed_volumes, tetrahedralize


def _once_used_faces(tets):
    """Faces of the tets used by exactly one tet, as sorted triples (an independent boundary extraction)."""
    counts = Counter(
        tuple(sorted(f)) for t in tets.tolist() for f in (t[:3], t[1:], [t[0], t[2], t[3]], [t[0], t[1], t[3]])
    )
    return {f for f, c in counts.items() if c == 1}


def _ellipsoid(subdivisions=3):
    mesh = trimesh.creation.icosphere(subdivisions=subdivisions)
    mesh.vertices *= [1.0, 0.6, 0.4]
    return mesh


def test_netgen_fills_the_sphere_and_keeps_its_surface():
    sphere = trimesh.creation.icosphere(subdivisions=2, radius=0.7)
    points, tets = tetrahedralize(sphere.vertices, sphere.faces, maxh=0.3)
    assert tets.dtype == np.int32 and tets.shape[1] == 4 and len(tets) > 0
    a, b, c, d = (points[tets[:, k]] for k in range(4))
    volumes = np.einsum("ij,ij->i", np.cross(b - a, c - a), d - a) / 6
    assert np.all(volumes > 0)
    assert volumes.sum() == pytest.approx(sphere.volume, rel=1e-9)
    np.testing.assert_array_equal(points[: len(sphere.vertices)], sphere.vertices)
    assert _once_used_faces(tets) == {tuple(sorted(f)) for f in sphere.faces.tolist()}
    assert len(points) > len(sphere.vertices)  # interior points were added


def test_netgen_rejects_inward_surface():
    sphere = trimesh.creation.icosphere(subdivisions=1)
    with pytest.raises(InputError, match="ball: Netgen made no tets"):
        tetrahedralize(sphere.vertices, sphere.faces[:, ::-1], maxh=0.5, name="ball")


def test_netgen_timeout():
    sphere = trimesh.creation.icosphere(subdivisions=2)
    with pytest.raises(InputError, match="did not finish within 0.01 s"):
        tetrahedralize(sphere.vertices, sphere.faces, maxh=0.3, timeout_s=0.01)


def test_netgen_crash_is_reported_with_its_signal(tmp_path, monkeypatch):
    fake = tmp_path / "crashing-python"
    fake.write_text("#!/bin/sh\necho 'Meshing volume'\nkill -SEGV $$\n")
    fake.chmod(0o755)
    monkeypatch.setattr("warpfem.prep.worker.sys.executable", str(fake))
    sphere = trimesh.creation.icosphere(subdivisions=1)
    with pytest.raises(InputError, match="ball: Netgen crashed \\(SIGSEGV\\); last output: Meshing volume"):
        tetrahedralize(sphere.vertices, sphere.faces, maxh=0.5, name="ball")


def test_simplify_keeps_a_closed_positive_surface_close_to_the_input():
    mesh = _ellipsoid(subdivisions=4)
    vertices, faces = simplify(mesh.vertices, mesh.faces, 300)
    assert vertices.dtype == np.float64 and faces.dtype == np.int32
    assert 200 < len(faces) <= 300
    coarse = trimesh.Trimesh(vertices, faces, process=False)
    assert coarse.is_watertight and coarse.is_winding_consistent
    assert coarse.volume == pytest.approx(mesh.volume, rel=0.05)
    # every coarse vertex stays near the ellipsoid the dense mesh approximates
    radius = np.linalg.norm(vertices / [1.0, 0.6, 0.4], axis=1)
    assert np.all((radius > 0.95) & (radius < 1.05))


def test_a_large_surface_is_first_reduced_by_a_fast_qem_and_still_simplifies_well(monkeypatch):
    """Above twice ``FIRST_FACES`` the child first reduces the surface fast; the result holds as QEM's alone does."""
    from warpfem.prep import simplify as S

    assert S.first_faces(195_200, 1000) == 0  # the default scene's bunny goes to the blocked QEM whole
    assert S.first_faces(3_123_200, 1000) == S.FIRST_FACES and S.first_faces(3_123_200, 30_000) == 600_000
    monkeypatch.setattr(S, "FIRST_FACES", 2000)
    sent = {}
    run = S.run_in_child

    def spy(task, inputs, *args):
        sent.update(inputs)
        return run(task, inputs, *args)

    monkeypatch.setattr(S, "run_in_child", spy)
    mesh = _ellipsoid(subdivisions=4)  # 5,120 faces, more than twice 2,000
    vertices, faces = simplify(mesh.vertices, mesh.faces, 80)
    assert int(sent["first"]) == 2000
    assert 60 < len(faces) <= 80
    coarse = trimesh.Trimesh(vertices, faces, process=False)
    assert coarse.is_watertight and coarse.is_winding_consistent
    assert coarse.volume == pytest.approx(mesh.volume, rel=0.1)
    radius = np.linalg.norm(vertices / [1.0, 0.6, 0.4], axis=1)  # near the ellipsoid the dense mesh approximates
    assert np.all((radius > 0.9) & (radius < 1.1))


def test_simplify_leaves_small_meshes_alone():
    mesh = trimesh.creation.icosphere(subdivisions=1)
    vertices, faces = simplify(mesh.vertices, mesh.faces, 1000)
    np.testing.assert_array_equal(vertices, mesh.vertices)
    np.testing.assert_array_equal(faces, mesh.faces)


@pytest.fixture
def ellipsoid_file(tmp_path):
    path = tmp_path / "ellipsoid.off"
    _ellipsoid().export(path)
    return path


def test_prepare_builds_a_consistent_body(ellipsoid_file):
    messages = []
    body = prepare(ellipsoid_file, faces=200, maxh=0.3, progress=messages.append)
    assert body.stats["cache"] == "off" and len(messages) >= 4
    assert len(body.coarse_faces) <= 200 and body.stats["tets"] == len(body.tets)
    np.testing.assert_array_equal(body.tet_vertices[body.boundary_faces], body.coarse_vertices[body.coarse_faces])
    rebuilt = np.einsum("nk,nkj->nj", body.embed_bary, body.tet_vertices[body.tets[body.embed_tet]])
    np.testing.assert_allclose(rebuilt, body.dense_vertices, atol=1e-9)
    # QEM leaves the convex dense surface partly outside; the cage pushed out of it holds every dense vertex
    assert body.stats["embedding_coverage"] == 1.0 and body.stats["cage_outside"] == 0.0
    assert body.stats["cage_volume_ratio"] > body.stats["volume_ratio"]
    winding = igl.fast_winding_number(body.coarse_vertices, body.coarse_faces.astype(np.int64), body.dense_vertices)
    assert winding.min() > 0.5
    # the distance field is the signed depth below the dense surface (reference: libigl's exact distance,
    # the side from its winding number)
    faces = body.dense_faces.astype(np.int64)
    squared, _, _ = igl.point_mesh_squared_distance(body.tet_vertices, body.dense_vertices, faces)
    inside = igl.fast_winding_number(body.dense_vertices, faces, body.tet_vertices) > 0.5
    np.testing.assert_allclose(body.vertex_depth, np.where(inside, 1, -1) * np.sqrt(squared), atol=1e-6)
    assert body.vertex_depth[: len(body.coarse_vertices)].max() <= 1e-6 < -body.vertex_depth.min()
    np.testing.assert_allclose(np.linalg.norm(body.vertex_grad, axis=1), 1.0, atol=1e-9)


def test_cache_hit_and_rebuild_of_a_damaged_file(ellipsoid_file, tmp_path):
    cache = tmp_path / "cache"
    first = prepare(ellipsoid_file, faces=200, maxh=0.3, cache_dir=cache)
    files = sorted(cache.iterdir(), key=lambda p: p.suffix)  # the entry, and the index naming it by file bytes
    assert first.stats["cache"] == "miss" and [p.suffix for p in files] == [".npz", ".txt"]

    second = prepare(ellipsoid_file, faces=200, maxh=0.3, cache_dir=cache)
    assert second.stats["cache"] == "hit"
    for name in ("dense_vertices", "dense_faces", "tet_vertices", "tets", "embed_tet", "embed_bary", "vertex_depth"):
        np.testing.assert_array_equal(getattr(first, name), getattr(second, name))
        assert getattr(first, name).dtype == getattr(second, name).dtype
    assert second.stats["tets"] == first.stats["tets"]

    files[0].write_bytes(files[0].read_bytes()[:500])  # truncate it
    third = prepare(ellipsoid_file, faces=200, maxh=0.3, cache_dir=cache)
    assert third.stats["cache"] == "miss"
    np.testing.assert_array_equal(third.tets, first.tets)
    assert prepare(ellipsoid_file, faces=200, maxh=0.3, cache_dir=cache).stats["cache"] == "hit"

    other = prepare(ellipsoid_file, faces=150, maxh=0.3, cache_dir=cache)  # other parameters, other entry
    assert other.stats["cache"] == "miss"
    assert sorted(p.suffix for p in cache.iterdir()) == [".npz", ".npz", ".txt", ".txt"]  # no temporary files left


def test_what_other_preprocessing_code_prepared_is_not_read(ellipsoid_file, tmp_path, monkeypatch):
    """Entries are keyed by the preprocessing code: code that changed (here, one more kernel module counted
    as its own) prepares the mesh again instead of reading what the older code made, through the entry and
    through the index naming it by the file's bytes; the code as it was still reads its own."""
    from warpfem.prep import pipeline

    cache = tmp_path / "cache"
    assert prepare(ellipsoid_file, faces=200, maxh=0.3, cache_dir=cache).stats["cache"] == "miss"
    with monkeypatch.context() as patch:
        patch.setattr(pipeline, "PREP_KERNELS", (*pipeline.PREP_KERNELS, "fem"))
        pipeline.code_digest.cache_clear()
        assert prepare(ellipsoid_file, faces=200, maxh=0.3, cache_dir=cache).stats["cache"] == "miss"
    pipeline.code_digest.cache_clear()
    assert prepare(ellipsoid_file, faces=200, maxh=0.3, cache_dir=cache).stats["cache"] == "hit"
    assert sorted(p.suffix for p in cache.iterdir()) == [".npz", ".npz", ".txt", ".txt"]


def test_a_cached_mesh_file_is_found_by_its_bytes_without_loading_it(ellipsoid_file, tmp_path, monkeypatch):
    """The second prepare of the same file and parameters reads the cache without loading and repairing the
    mesh; a file whose bytes changed is loaded again; the index never outlives a damaged entry."""
    cache = tmp_path / "cache"
    first = prepare(ellipsoid_file, faces=200, maxh=0.3, cache_dir=cache)

    def no_load(*args, **kwargs):
        raise AssertionError("the mesh was loaded")

    with monkeypatch.context() as patch:
        patch.setattr("warpfem.prep.pipeline.load_surface", no_load)
        again = prepare(ellipsoid_file, faces=200, maxh=0.3, cache_dir=cache)
        assert again.stats["cache"] == "hit"
        np.testing.assert_array_equal(again.embed_bary, first.embed_bary)
        with pytest.raises(AssertionError, match="was loaded"):  # other parameters: not in the index
            prepare(ellipsoid_file, faces=150, maxh=0.3, cache_dir=cache)

    moved = _ellipsoid()
    moved.vertices *= 1.5
    moved.export(ellipsoid_file)  # new bytes at the same path
    changed = prepare(ellipsoid_file, faces=200, maxh=0.3, cache_dir=cache)
    assert changed.stats["cache"] == "miss"
    np.testing.assert_allclose(changed.dense_vertices, 1.5 * first.dense_vertices)

    for npz in cache.glob("*.npz"):
        npz.write_bytes(npz.read_bytes()[:300])  # every entry damaged: the index leads nowhere
    assert prepare(ellipsoid_file, faces=200, maxh=0.3, cache_dir=cache).stats["cache"] == "miss"


def test_collision_samples_are_cached_beside_the_body(ellipsoid_file, tmp_path, monkeypatch):
    cache = tmp_path / "cache"
    body = prepare(ellipsoid_file, faces=200, maxh=0.3, cache_dir=cache)
    expected = surface_samples(body.dense_vertices, body.dense_faces, 0.1, 1e-3)
    first = cached_surface_samples(body, 0.1, 1e-3, cache)
    (entry,) = cache.glob("samples-*.npz")

    def no_samples(*args, **kwargs):
        raise AssertionError("the samples were computed")

    with monkeypatch.context() as patch:
        patch.setattr("warpfem.prep.pipeline.surface_samples", no_samples)
        second = cached_surface_samples(body, 0.1, 1e-3, cache)
        with pytest.raises(AssertionError, match="computed"):  # another spacing is another entry
            cached_surface_samples(body, 0.05, 1e-3, cache)
    entry.write_bytes(entry.read_bytes()[:200])  # damaged: computed again
    third = cached_surface_samples(body, 0.1, 1e-3, cache)
    stale = dict(collision=expected.collision, skin=expected.skin, face=[len(body.dense_faces)], face_bary=[[1, 0, 0]])
    with entry.open("wb") as stream:  # a point on a triangle the mesh does not have: computed again
        np.savez(stream, **stale)
    fourth = cached_surface_samples(body, 0.1, 1e-3, cache)
    for got in (first, second, third, fourth):
        np.testing.assert_array_equal(got.collision, expected.collision)
        np.testing.assert_array_equal(got.skin, expected.skin)
        np.testing.assert_array_equal(got.face, expected.face)
        np.testing.assert_array_equal(got.face_bary, expected.face_bary)


def test_prepare_reports_bad_input(tmp_path):
    with pytest.raises(InputError, match="missing.obj.*not found"):
        prepare(tmp_path / "missing.obj", faces=100)


def test_killed_netgen_child_goes_to_the_next_rung(tmp_path, monkeypatch, ellipsoid_file):
    # the first Netgen child is killed (SIGKILL, as the OOM killer or a 'double free' abort would end it);
    # the parent survives and the ladder's next rung runs the real worker
    marker = tmp_path / "killed-once"
    fake = tmp_path / "python"
    fake.write_text(
        f'#!/bin/sh\nif [ "$3" = netgen ] && [ ! -e {marker} ]; then\n'
        f'  touch {marker}; echo "Meshing"; kill -KILL $$\nfi\n'
        f'exec {sys.executable} "$@"\n'
    )
    fake.chmod(0o755)
    monkeypatch.setattr("warpfem.prep.worker.sys.executable", str(fake))
    body = prepare(ellipsoid_file, faces=200, maxh=0.3)
    assert marker.exists()
    assert body.stats["failed_rungs"].startswith("1) Netgen crashed (SIGKILL); last output: Meshing")
    assert body.stats["rung"].startswith("2 ")
    assert np.all(tet_signed_volumes(body.tet_vertices, body.tets) > 0)


def test_every_stage_has_a_time_limit(ellipsoid_file):
    with pytest.raises(
        InputError, match="every rung failed: 1\\) QEM simplification did not finish within 0.01 s"
    ) as err:
        prepare(ellipsoid_file, faces=200, timeout_s=0.01)
    assert "outer surface did not finish within 0.01 s" in str(err.value) and "\n" not in str(err.value)


def test_a_corrupted_cache_entry_is_rebuilt(ellipsoid_file, tmp_path):
    cache = tmp_path / "cache"
    first = prepare(ellipsoid_file, faces=200, maxh=0.3, cache_dir=cache)
    (entry,) = cache.glob("*.npz")
    data = bytearray(entry.read_bytes())
    data[len(data) // 2] ^= 0xFF  # one flipped byte in the middle, same length
    entry.write_bytes(bytes(data))
    again = prepare(ellipsoid_file, faces=200, maxh=0.3, cache_dir=cache)
    assert again.stats["cache"] == "miss"
    np.testing.assert_array_equal(again.embed_bary, first.embed_bary)


def test_stats_report_quality_volume_and_hausdorff(ellipsoid_file):
    import igl

    body = prepare(ellipsoid_file, faces=200, maxh=0.3)
    dihedral, ratio = tet_quality(body.tet_vertices, body.tets)
    assert body.stats["tet_min_dihedral_deg"] == pytest.approx(dihedral.min(), rel=1e-9)
    assert dihedral.min() >= 0.5
    assert body.stats["tet_min_radius_ratio"] == pytest.approx(ratio.min(), rel=1e-6)
    assert 0 < ratio.min() <= 1
    dense = trimesh.Trimesh(body.dense_vertices, body.dense_faces, process=False)
    assert body.stats["cage_volume_ratio"] == pytest.approx(
        tet_signed_volumes(body.tet_vertices, body.tets).sum() / dense.volume, rel=1e-9
    )
    assert body.stats["volume_ratio"] == pytest.approx(0.98, abs=0.02)  # QEM's surface, before the cage
    # libigl's Hausdorff distance (vertex-based) as the independent reference
    reference = igl.hausdorff(
        body.dense_vertices, body.dense_faces.astype(np.int64), body.coarse_vertices, body.coarse_faces.astype(np.int64)
    )
    assert body.stats["hausdorff"] == pytest.approx(reference, rel=0.05)


def _min_dihedral_deg(points, tets):
    """Smallest dihedral angle of any tet, from the angle between each pair of face normals (degrees)."""
    x = points[tets]
    smallest = 180.0
    for i, j in [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]:
        # the edge shared by faces opposite corners i and j joins the other two corners
        k, m = (c for c in range(4) if c not in (i, j))
        edge = x[:, m] - x[:, k]
        # the two faces' directions perpendicular to the edge, towards corners i and j
        u = x[:, i] - x[:, k] - edge * (np.einsum("ij,ij->i", x[:, i] - x[:, k], edge) / (edge**2).sum(1))[:, None]
        w = x[:, j] - x[:, k] - edge * (np.einsum("ij,ij->i", x[:, j] - x[:, k], edge) / (edge**2).sum(1))[:, None]
        cos = np.einsum("ij,ij->i", u, w) / np.linalg.norm(u, axis=1) / np.linalg.norm(w, axis=1)
        smallest = min(smallest, float(np.degrees(np.arccos(np.clip(cos, -1, 1))).min()))
    return smallest


def test_a_cad_part_is_remeshed_before_netgen(tmp_path):
    """An angle bracket of long thin CAD triangles: QEM keeps needles (Netgen made 0.006 deg slivers on them
    for 40 s and more); the remeshing rung gives well-shaped tets of the part's volume within seconds."""
    from manifold3d import Manifold  # noqa: F401 - the reference volume below comes from the same booleans

    vertices, faces = cad_bracket()
    volume = trimesh.Trimesh(vertices, faces, process=False).volume
    clock = time.perf_counter()
    body = prepare(write_obj(tmp_path / "bracket.obj", vertices, faces), faces=400)
    assert time.perf_counter() - clock < 30
    assert body.stats["failed_rungs"].startswith("1) the simplified surface has needle triangles")
    assert body.stats["rung"].startswith("5 (qslim, remeshed")
    assert np.all(tet_signed_volumes(body.tet_vertices, body.tets) > 0)
    assert _min_dihedral_deg(body.tet_vertices, body.tets) > 5.0
    assert body.stats["tet_min_dihedral_deg"] == pytest.approx(_min_dihedral_deg(body.tet_vertices, body.tets))
    # the cage holds the part: its volume is the part's, a little more
    assert 1.0 <= tet_signed_volumes(body.tet_vertices, body.tets).sum() / volume < 1.05
    assert body.stats["hausdorff_relative"] < 0.02


def test_the_time_budget_ends_a_preparation_in_one_line(ellipsoid_file):
    clock = time.perf_counter()
    with pytest.raises(InputError, match="no valid tet mesh at 200 faces within the time budget") as err:
        prepare(ellipsoid_file, faces=200, budget_s=0.05)
    assert time.perf_counter() - clock < 10
    assert "1) QEM simplification did not finish within" in str(err.value) and "\n" not in str(err.value)


def test_tet_quality_measures_every_dihedral_angle():
    """Against the angle between the two faces' directions perpendicular to each edge, on random tets of
    both orientations of their corner order (turned positive) and the regular tet (70.53 deg, ratio 1)."""
    rng = np.random.default_rng(0)
    points = rng.normal(size=(400, 3))
    tets = np.arange(400).reshape(-1, 4)
    negative = tet_signed_volumes(points, tets) < 0
    tets[negative] = tets[negative][:, [0, 2, 1, 3]]
    dihedral, _ = tet_quality(points, tets)
    np.testing.assert_allclose(dihedral, [_min_dihedral_deg(points, t[None]) for t in tets], rtol=1e-9)
    regular = np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], dtype=float)
    dihedral, ratio = tet_quality(regular, np.array([[0, 1, 2, 3]]))
    assert dihedral[0] == pytest.approx(np.degrees(np.arccos(1 / 3))) and ratio[0] == pytest.approx(1.0)
