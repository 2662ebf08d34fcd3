"""PLY files whose faces are triangle strips (``element tristrips``), which trimesh and meshio do not read.

Old scanner output (the Cyberware scans, for example) stores its surface as strips: one list of vertex
indices per strip, strips separated by -1, each index after the second making a triangle with the two
before it, every other one turned so that the strip keeps one winding.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}  # fmt: skip


def has_strips(path: Path) -> bool:
    """Whether a PLY file's header declares triangle strips."""
    with open(path, "rb") as stream:
        for raw in stream:
            line = raw.decode("ascii", "replace").strip()
            if line.startswith("element tristrips"):
                return True
            if line == "end_header":
                return False
    return False


def read_strip_ply(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """The vertices (n, 3) and the triangles (m, 3) of a PLY file with ``element tristrips``.

    Raises:
        ValueError: A header or body this reader does not understand (the caller reports the file).
    """
    data = Path(path).read_bytes()
    end = data.find(b"end_header")
    if end < 0:
        raise ValueError("no end_header")
    body = data[data.index(b"\n", end) + 1 :]
    fmt, elements = _header(data[:end].decode("ascii", "replace").splitlines())
    if fmt == "ascii":
        words = iter(body.split())
        read = _ascii_reader(words)
    else:
        read = _binary_reader(body, "<" if fmt == "binary_little_endian" else ">")
    vertices, strips = None, []
    for name, count, props in elements:
        values = [read(props) for _ in range(count)] if any(p[0] == "list" for p in props) else read(props, count)
        if name == "vertex":
            names = [p[2] for p in props]
            vertices = np.stack([np.asarray(values[names.index(axis)], np.float64) for axis in "xyz"], axis=1)
        elif name == "tristrips":
            column = next(k for k, p in enumerate(props) if p[0] == "list")
            strips += [np.append(row[column], -1) for row in values]
    if vertices is None:
        raise ValueError("no vertex element")
    return vertices, strip_triangles(np.concatenate(strips) if strips else np.zeros(0, np.int64))


def strip_triangles(indices: np.ndarray) -> np.ndarray:
    """Triangles of strips given as one index list with -1 between strips, degenerate ones dropped."""
    triangles = []
    for strip in np.split(indices, np.flatnonzero(indices < 0)):
        strip = strip[strip >= 0]
        if len(strip) < 3:
            continue
        a, b, c = strip[:-2], strip[1:-1], strip[2:]
        odd = np.arange(len(a)) % 2 == 1
        tri = np.stack([np.where(odd, b, a), np.where(odd, a, b), c], axis=1)
        keep = (tri[:, 0] != tri[:, 1]) & (tri[:, 1] != tri[:, 2]) & (tri[:, 0] != tri[:, 2])
        triangles.append(tri[keep])
    return np.concatenate(triangles).astype(np.int64) if triangles else np.zeros((0, 3), np.int64)


def _header(lines: list[str]) -> tuple[str, list[tuple[str, int, list[tuple[str, ...]]]]]:
    fmt, elements = "", []
    for line in lines:
        parts = line.split()
        if not parts:
            continue
        if parts[0] == "format":
            fmt = parts[1]
        elif parts[0] == "element":
            elements.append((parts[1], int(parts[2]), []))
        elif parts[0] == "property":
            if parts[1] == "list":
                elements[-1][2].append(("list", _TYPES[parts[2]], parts[4], _TYPES[parts[3]]))
            else:
                elements[-1][2].append(("scalar", _TYPES[parts[1]], parts[2]))
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise ValueError(f"unknown PLY format {fmt!r}")
    return fmt, elements


def _ascii_reader(words):
    def read(props, count=None):
        if count is not None:  # scalars only: one column per property
            rows = np.array([[float(next(words)) for _ in props] for _ in range(count)]).reshape(count, len(props))
            return [rows[:, k] for k in range(len(props))]
        row = []
        for prop in props:
            if prop[0] == "list":
                n = int(next(words))
                row.append(np.array([int(next(words)) for _ in range(n)], np.int64))
            else:
                row.append(float(next(words)))
        return row

    return read


def _binary_reader(body: bytes, order: str):
    offset = 0

    def read(props, count=None):
        nonlocal offset
        if count is not None:  # scalars only: one structured read
            dtype = np.dtype([(f"p{k}", order + p[1]) for k, p in enumerate(props)])
            rows = np.frombuffer(body, dtype, count, offset)
            offset += dtype.itemsize * count
            return [rows[f"p{k}"] for k in range(len(props))]
        row = []
        for prop in props:
            if prop[0] == "list":
                n = int(np.frombuffer(body, order + prop[1], 1, offset)[0])
                offset += np.dtype(prop[1]).itemsize
                row.append(np.frombuffer(body, order + prop[3], n, offset).astype(np.int64))
                offset += np.dtype(prop[3]).itemsize * n
            else:
                row.append(np.frombuffer(body, order + prop[1], 1, offset)[0])
                offset += np.dtype(prop[1]).itemsize
        return row

    return read
