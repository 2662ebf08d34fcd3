"""PLY files of triangle strips (ascii and binary) load as the triangles they describe."""

import numpy as np
import pytest
import trimesh

from warpfem.prep.ply_strips import strip_triangles
from warpfem.prep.surface import load_surface


def _write_ply(path, vertices, strips, binary):
    flat = np.concatenate([np.append(s, -1) for s in strips]).astype(np.int32)
    header = (
        f"ply\nformat {'binary_little_endian' if binary else 'ascii'} 1.0\ncomment strips\n"
        f"element vertex {len(vertices)}\nproperty float x\nproperty float y\nproperty float z\n"
        "element tristrips 1\nproperty list int int vertex_indices\nend_header\n"
    )
    with open(path, "wb") as f:
        f.write(header.encode())
        if binary:
            f.write(np.asarray(vertices, "<f4").tobytes())
            f.write(np.array([len(flat)], "<i4").tobytes() + flat.astype("<i4").tobytes())
        else:
            f.write("".join(f"{x} {y} {z}\n" for x, y, z in vertices).encode())
            f.write((f"{len(flat)} " + " ".join(map(str, flat)) + "\n").encode())


def test_one_strip_alternates_its_winding():
    """A strip 0 1 2 3 4: triangles (0 1 2), (2 1 3), (2 3 4), every one wound the same way round."""
    np.testing.assert_array_equal(strip_triangles(np.array([0, 1, 2, 3, 4])), [[0, 1, 2], [2, 1, 3], [2, 3, 4]])
    np.testing.assert_array_equal(strip_triangles(np.array([0, 1, 2, -1, 3, 3, 4, -1, 5])), [[0, 1, 2]])


@pytest.mark.parametrize("binary", [False, True])
def test_a_sphere_stored_as_strips_loads_whole(tmp_path, binary):
    """An icosphere written as one strip per triangle comes back with the same triangles and volume."""
    sphere = trimesh.creation.icosphere(subdivisions=2, radius=0.5)
    path = tmp_path / "sphere.ply"
    _write_ply(path, sphere.vertices, list(sphere.faces), binary)
    surface = load_surface(path)
    assert len(surface.faces) == len(sphere.faces)
    volume = trimesh.Trimesh(surface.vertices, surface.faces).volume
    assert volume == pytest.approx(sphere.volume, rel=1e-5)


def test_a_tetrahedron_in_one_strip_is_closed_and_consistently_wound(tmp_path):
    vertices = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float)
    path = tmp_path / "tet.ply"
    _write_ply(path, vertices, [np.array([0, 1, 2, 3, 0, 1])], binary=True)
    surface = load_surface(path)
    mesh = trimesh.Trimesh(surface.vertices, surface.faces, process=False)
    assert len(surface.faces) == 4 and mesh.is_watertight and mesh.is_winding_consistent
    assert mesh.volume == pytest.approx(1 / 6)


def test_a_truncated_strip_file_is_a_one_line_error(tmp_path):
    from warpfem.errors import InputError

    path = tmp_path / "cut.ply"
    _write_ply(path, np.eye(3), [np.array([0, 1, 2])], binary=True)
    path.write_bytes(path.read_bytes()[:-6])  # the strip's indices cut short
    with pytest.raises(InputError, match="cut.ply: unreadable mesh file") as err:
        load_surface(path)
    assert "\n" not in str(err.value)
