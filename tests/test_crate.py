"""The streamed crate layer (warpfem.io.crate) against usd-core: the same samples authored with the Sdf API and
exported by usd-core read back identically, and usd-core reads every value of ours as written."""

from __future__ import annotations

import numpy as np
import pytest

from warpfem.io.crate import CrateStream

pytest.importorskip("pxr")


def _samples(rng: np.random.Generator, frames: int, sizes: list[int], matrices: int) -> list[list[np.ndarray]]:
    """Per frame: a float3 array of each size, its 2-point box, then 4x4 matrices."""
    out = []
    for _ in range(frames):
        values = []
        for n in sizes:
            p = rng.normal(size=(n, 3)).astype(np.float32)
            values += [p, np.array([p.min(axis=0), p.max(axis=0)] if n else np.zeros((0, 3)), np.float32)]
        values += [rng.normal(size=(4, 4)) for _ in range(matrices)]
        out.append(values)
    return out


def _reference(attributes: list[tuple[str, str]], times: list[float], samples: list[list[np.ndarray]]) -> object:
    """The same samples authored with usd-core's Sdf API and exported by it, opened again."""
    from pxr import Gf, Sdf, Vt

    layer = Sdf.Layer.CreateAnonymous("reference.usdc")
    types = {"point3f[]": Sdf.ValueTypeNames.Point3fArray, "float3[]": Sdf.ValueTypeNames.Float3Array}
    types["matrix4d"] = Sdf.ValueTypeNames.Matrix4d
    for path, type_name in attributes:
        prim_path = Sdf.Path(path).GetPrimPath()
        parent = layer.pseudoRoot
        for name in prim_path.pathString.strip("/").split("/"):
            parent = parent.nameChildren.get(name) or Sdf.PrimSpec(parent, name, Sdf.SpecifierOver)
        Sdf.AttributeSpec(parent, Sdf.Path(path).name, types[type_name])
    for t, values in zip(times, samples, strict=True):
        for (path, type_name), v in zip(attributes, values, strict=True):
            value = Gf.Matrix4d(v.tolist()) if type_name == "matrix4d" else Vt.Vec3fArray.FromNumpy(v)
            layer.SetTimeSample(path, t, value)
    return layer


def _attributes(bodies: list[str], props: list[str]) -> list[tuple[str, str]]:
    out = [(f"/World/{b}.{a}", t) for b in bodies for a, t in (("points", "point3f[]"), ("extent", "float3[]"))]
    return out + [(f"/World/{p}.xformOp:transform", "matrix4d") for p in props]


@pytest.mark.parametrize("bodies", [1, 40], ids=["one body", "40 bodies"])
def test_a_stream_reads_back_as_usd_cores_own_export_of_the_same_samples(tmp_path, bodies):
    """Prims, attributes, types and every sample equal what usd-core makes of the same authoring (its text form);
    40 bodies make the token, field and path tables long (LZ4 literal runs of several 255-byte steps)."""
    from pxr import Sdf

    rng = np.random.default_rng(bodies)
    names = [f"body_with_a_long_name_{i:03d}" for i in range(bodies)]
    props = ["obstacles/ramp", "handles/left/grip"]
    attributes = _attributes(names, props)
    sizes = [int(rng.integers(1, 50)) for _ in names]
    times = [0.0, 1.0, 2.0, 7.0, 7.5]
    samples = _samples(rng, len(times), sizes, len(props))
    stream = CrateStream(tmp_path / "ours.usdc", attributes)
    for t, values in zip(times, samples, strict=True):
        stream.add(t, values)
    stream.close()

    ours = Sdf.Layer.OpenAsAnonymous(str(tmp_path / "ours.usdc"))
    assert ours is not None and ours.GetFileFormat().formatId == "usdc"
    reference = _reference(attributes, times, samples)
    reference.Export(str(tmp_path / "theirs.usdc"))
    theirs = Sdf.Layer.OpenAsAnonymous(str(tmp_path / "theirs.usdc"))
    assert ours.ExportToString() == theirs.ExportToString()


def test_every_value_reads_back_bitwise_with_empty_and_single_point_arrays(tmp_path):
    from pxr import Usd

    rng = np.random.default_rng(3)
    attributes = _attributes(["a", "b", "c"], ["obstacles/o"])
    samples = _samples(rng, 4, [0, 1, 1000], 1)
    stream = CrateStream(tmp_path / "x.usdc", attributes)
    for f, values in enumerate(samples):
        stream.add(float(f), values)
    stream.close()
    stage = Usd.Stage.Open(str(tmp_path / "x.usdc"))
    for (path, type_name), column in zip(attributes, zip(*samples, strict=True), strict=True):
        attr = stage.GetAttributeAtPath(path)
        assert attr.GetTypeName() == type_name and attr.GetTimeSamples() == [0.0, 1.0, 2.0, 3.0]
        for f, expected in enumerate(column):
            got = np.array(attr.Get(float(f)), dtype=np.float64 if type_name == "matrix4d" else np.float32)
            np.testing.assert_array_equal(got.reshape(expected.shape), expected)


def test_a_stream_checks_its_attributes_and_times(tmp_path):
    with pytest.raises(ValueError, match="type 'int\\[\\]'"):
        CrateStream(tmp_path / "x.usdc", [("/World/a.points", "int[]")])
    stream = CrateStream(tmp_path / "y.usdc", [("/World/a.points", "point3f[]")])
    stream.add(1.0, [np.zeros((2, 3), np.float32)])
    with pytest.raises(ValueError, match="times must increase"):
        stream.add(1.0, [np.zeros((2, 3), np.float32)])
    with pytest.raises(ValueError, match="expected 1 values, got 2"):
        stream.add(2.0, [np.zeros((2, 3), np.float32)] * 2)
    with pytest.raises(ValueError, match="cannot reshape"):  # a float3 array of another width
        stream.add(2.0, [np.zeros((2, 2), np.float32)])
    with pytest.raises(ValueError, match="type 'float\\[\\]' is not one of"):
        stream.set_default("/World/a.mass", "float[]", np.zeros(2))
    with pytest.raises(ValueError, match="/World/a.points is sampled"):
        stream.set_default("/World/a.points", "point3f[]", np.zeros((2, 3)))
    stream.discard()
    assert not (tmp_path / "y.usdc").exists()


def test_short_writes_and_one_system_call_per_frame(tmp_path, monkeypatch):
    """Where ``pwritev`` writes less than asked (at most 1,000 bytes a call, cutting through values), the file
    still reads back bitwise; where it writes everything, each frame costs one call and closing two."""
    import os

    from pxr import Usd

    attributes = _attributes(["a", "b"], ["obstacles/o"])
    samples = _samples(np.random.default_rng(4), 3, [1, 700], 1)
    calls, pwritev = [], os.pwritev

    def short(fd, buffers, offset):
        calls.append(offset)
        return pwritev(fd, [memoryview(b"".join(bytes(b) for b in buffers)[:limit])], offset)

    for limit, name in ((1000, "short.usdc"), (1 << 30, "whole.usdc")):
        calls.clear()
        monkeypatch.setattr(os, "pwritev", short)
        stream = CrateStream(tmp_path / name, attributes)
        for f, values in enumerate(samples):
            stream.add(float(f), values)
        stream.close()
        monkeypatch.setattr(os, "pwritev", pwritev)
        if limit > 1000:
            assert len(calls) == len(samples) + 2
        stage = Usd.Stage.Open(str(tmp_path / name))
        for (path, _), column in zip(attributes, zip(*samples, strict=True), strict=True):
            for f, expected in enumerate(column):
                got = np.array(stage.GetAttributeAtPath(path).Get(float(f)))
                np.testing.assert_array_equal(got.reshape(expected.shape).astype(expected.dtype), expected)
