"""Fuzzed scene files and mesh files: a clean one-line error (exit 2) or a valid result, never a traceback."""

import pytest
import trimesh
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from warpfem.cli import main
from warpfem.errors import InputError
from warpfem.prep.surface import load_surface
from warpfem.scene import load_scene

FUZZ = settings(max_examples=60, deadline=None, suppress_health_check=list(HealthCheck))

KEYS = {
    "scene": ["frames", "fps", "substeps", "up_axis", "gravity"],
    "solver": ["cg_mode", "cg_iterations", "cg_tolerance"],
    "ground": ["enabled", "height", "stiffness", "friction"],
    "collision": ["enabled", "stiffness", "friction"],
    "object": ["name", "mesh", "faces", "scale", "young", "poisson", "density", "translate", "rotate", "maxh"],
    "bogus": ["x"],
}
scalars = st.one_of(
    st.integers(-(2**63), 2**63 - 1),
    st.floats(allow_nan=True, allow_infinity=True),
    st.booleans(),
    st.text(max_size=12),
    st.sampled_from(["ball.obj", "builtin:bunny", "Y", "Z", "fixed", "tolerance", "../x.obj", ""]),
)
values = st.one_of(scalars, st.lists(scalars, max_size=4), st.dictionaries(st.text(max_size=5), scalars, max_size=2))
tables = st.dictionaries(
    st.sampled_from(sorted(KEYS)),
    st.sampled_from(sorted(KEYS)).flatmap(lambda t: st.dictionaries(st.sampled_from(KEYS[t]), values, max_size=5)),
    max_size=5,
)


def _toml(doc):
    """A TOML text of ``doc`` (object tables as [[object]]); values TOML cannot hold are written as junk."""
    lines = []
    for table, keys in doc.items():
        lines.append(f"[[{table}]]" if table == "object" else f"[{table}]")
        for key, value in keys.items():
            lines.append(f"{key} = {_value(value)}")
    return "\n".join(lines) + "\n"


def _value(v):
    if isinstance(v, bool):
        return str(v).lower()
    if isinstance(v, float):
        return {"nan": "nan", "inf": "inf", "-inf": "-inf"}.get(str(v), repr(v))
    if isinstance(v, int):
        return str(v)
    if isinstance(v, str):
        return '"' + v.encode("unicode_escape").decode().replace('"', '\\"') + '"'
    if isinstance(v, list):
        return "[" + ", ".join(_value(x) for x in v) + "]"
    return "{" + ", ".join(f'"{k.encode("unicode_escape").decode()}" = {_value(x)}' for k, x in v.items()) + "}"


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    path = tmp_path_factory.mktemp("fuzz")
    trimesh.creation.icosphere(subdivisions=2).export(path / "ball.obj")
    return path


@FUZZ
@given(doc=tables, raw=st.one_of(st.none(), st.binary(max_size=64)))
def test_random_scene_files_load_or_fail_in_one_line(folder, doc, raw):
    path = folder / "fuzz.toml"
    path.write_bytes(raw if raw is not None else _toml(doc).encode())
    try:
        load_scene(path)
    except InputError as err:
        assert "\n" not in str(err) and str(err).startswith(str(path))


@settings(max_examples=8, deadline=None, suppress_health_check=list(HealthCheck))
@given(doc=tables)
def test_random_scene_files_through_the_cli_exit_0_or_2(folder, doc, capsys):
    doc = {k: v for k, v in doc.items() if k != "object"} | {"object": {"mesh": "ball.obj", "faces": 100}}
    (folder / "cli.toml").write_text(_toml(doc))
    out = folder / "cli.usdc"
    out.unlink(missing_ok=True)
    args = ["run", str(folder / "cli.toml"), "--frames", "1", "--device", "cpu", "--out", str(out), "--quiet"]
    code = main(args + ["--cache-dir", str(folder / "cache")])
    err = [line for line in capsys.readouterr().err.splitlines() if line.startswith("warpfem")]
    assert code in (0, 1, 2), err
    if code == 2:
        assert len(err) == 1 and err[0].startswith("warpfem: error: ") and not out.exists()


@FUZZ
@given(
    suffix=st.sampled_from([".obj", ".ply", ".stl", ".off"]),
    cut=st.floats(0.0, 1.0),
    flips=st.lists(st.tuples(st.floats(0.0, 1.0), st.integers(0, 255)), max_size=4),
)
def test_truncated_or_damaged_meshes_load_or_fail_in_one_line(folder, suffix, cut, flips):
    source = folder / f"source{suffix}"
    if not source.exists():
        trimesh.creation.icosphere(subdivisions=1).export(source)
    data = bytearray(source.read_bytes()[: int(cut * source.stat().st_size)])
    for where, byte in flips:
        if data:
            data[int(where * (len(data) - 1))] = byte
    path = folder / f"damaged{suffix}"
    path.write_bytes(bytes(data))
    try:
        surface = load_surface(path)
    except InputError as err:
        assert "\n" not in str(err) and str(path) in str(err)
    else:
        assert len(surface.faces) > 0 and len(surface.vertices) >= 4


def test_a_ply_cut_inside_its_header_is_a_one_line_error(tmp_path):
    """A PLY file that ends before its header does (a truncated download) is refused in one line, at once:
    meshio, the fallback reader, would wait forever for the header's last line."""
    path = tmp_path / "cut.ply"
    path.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\n")
    with pytest.raises(InputError, match="end_header") as err:
        load_surface(path)
    assert "\n" not in str(err.value) and str(path) in str(err.value)
