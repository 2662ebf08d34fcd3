"""A USD crate (``.usdc``) layer of time samples streamed to disk: each frame's values are written as they come.

usd-core builds a layer in memory and exports it whole, holding the interpreter lock while it copies, hashes
and writes every array; beside a simulation's threads that cost several times a plain write of the same
bytes. A chunk of a run is one simple kind of layer: ``over`` prims whose attributes hold time samples of
float3 arrays or 4x4 matrices. :class:`CrateStream` writes exactly that in crate version 0.8.0 (the version
usd-core writes by default): the values go to the file with plain writes frame by frame, and closing adds
the small tables that index them (the time-sample records, then the structural sections: tokens, fields,
field sets, paths, specs, and the table of contents the header points to). The layout follows OpenUSD's
``pxr/usd/usd/crateFile.cpp``; the integer lists are written in its integer coding with every value as a
32-bit difference, and each compressed block as one literal run of LZ4, which every LZ4 decoder reads.
"""

from __future__ import annotations

import os
import struct
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

VERSION = (0, 8, 0)
"""The crate version written."""

_BOOTSTRAP_BYTES = 88  # "PXR-USDC", 8 version bytes, the table of contents' offset, 8 reserved int64

# TypeEnum values and ValueRep bits (crateDataTypes.h, crateFile.h)
_BOOL, _INT, _DOUBLE, _TOKEN, _MATRIX4D, _VEC3F = 1, 3, 9, 11, 15, 24
_TOKEN_VECTOR, _SPECIFIER, _VARIABILITY, _TIME_SAMPLES, _DOUBLE_VECTOR = 41, 42, 44, 46, 48
_ARRAY_BIT, _INLINED_BIT = 1 << 63, 1 << 62

_SPEC_ATTRIBUTE, _SPEC_PRIM, _SPEC_PSEUDO_ROOT = 1, 6, 7  # SdfSpecType
_SPECIFIER_DEF, _SPECIFIER_OVER, _VARIABILITY_VARYING, _VARIABILITY_UNIFORM = 0, 1, 0, 1

_IOV_MAX = 1024  # buffers per pwritev call (POSIX requires at least 16; Linux has 1024)
_PADS = [bytes(n) for n in range(8)]
_FLOAT32, _FLOAT64 = np.dtype("<f4"), np.dtype("<f8")

TYPES = {"point3f[]": _VEC3F, "float3[]": _VEC3F, "matrix4d": _MATRIX4D}
"""The attribute types a stream samples, by USD type name: float3 arrays as (n, 3) float32, matrices as 4x4
float64 in USD's row-vector convention."""

DEFAULT_TYPES = ("point3f[]", "float3[]", "int[]", "token[]", "token", "matrix4d")
"""The attribute types a stream can give a default value (:meth:`CrateStream.set_default`): float3 arrays as
(n, 3) float32, int arrays as int32, token arrays as a list of str, a token as a str, a matrix as :data:`TYPES`."""


def _rep(kind: int, payload: int, inlined: bool = False, array: bool = False) -> int:
    """A ValueRep: the type in bits 48-55, flags in the top bits, an offset or inlined value below."""
    return (_ARRAY_BIT if array else 0) | (_INLINED_BIT if inlined else 0) | (kind << 48) | payload


_VEC3F_ARRAY = _rep(_VEC3F, 0, array=True)  # a float3 array's ValueRep, less its offset


def lz4_literal_block(data: bytes) -> bytes:
    """``data`` as TfFastCompression writes a single chunk: a zero byte, then an LZ4 block of one literal run."""
    n = len(data)
    if n < 15:
        return bytes((0, n << 4)) + data
    rest, extra = n - 15, bytearray()
    while rest >= 255:
        extra.append(255)
        rest -= 255
    extra.append(rest)
    return b"\x00\xf0" + bytes(extra) + data


def compressed_ints(values: Sequence[int]) -> bytes:
    """A list of 32-bit integers as Usd_IntegerCompression stores it, preceded by its byte count.

    Coded as differences from the previous value, each as a 32-bit integer (code 3), with 0 as the
    common value, then compressed as one LZ4 literal run.
    """
    signed = np.asarray(values, dtype=np.int64).astype(np.uint32).view(np.int32)
    deltas = np.diff(signed, prepend=np.int32(0)).astype(np.int32)  # wraps like the C++ int32 arithmetic
    codes = b"\xff" * ((2 * len(signed) + 7) // 8)
    block = lz4_literal_block(struct.pack("<i", 0) + codes + deltas.tobytes())
    return struct.pack("<Q", len(block)) + block


@dataclass
class _Node:
    """A path in the layer: the pseudo-root, a prim or an attribute."""

    name: str
    attribute: str | None = None  # the type name of an attribute; None for a prim
    children: list[_Node] = field(default_factory=list)
    samples: int = -1  # an attribute's time-sample record offset
    default: object = None  # an attribute's default value, if it has one
    uniform: bool = False  # an attribute's variability
    type_name: str = ""  # a defined prim's type ("": an ``over``)

    def child(self, name: str, attribute: str | None = None) -> _Node:
        """The prim (or, with its type name ``attribute``, attribute) child ``name``, made if new."""
        for c in self.children:
            if c.name == name and (c.attribute is None) == (attribute is None):
                return c
        node = _Node(name, attribute)
        self.children.append(node)
        return node

    def find(self, path: str) -> _Node:
        """The prim at absolute ``path`` under this (pseudo-root) node, made with its parents where new."""
        node = self
        for part in path.strip("/").split("/"):
            node = node.child(part)
        return node


class CrateStream:
    """One ``.usdc`` layer of ``over`` prims whose attributes hold time samples, written frame by frame.

    Args:
        path: The file written (created or truncated now; complete only once :meth:`close` returns).
        attributes: ``(path, type name)`` per attribute, e.g. ``("/World/bunny.points", "point3f[]")``: an
            absolute prim path and a property name; type names from :data:`TYPES`.

    Every :meth:`add` samples every attribute at one time code, in increasing order. Before :meth:`close`, prims
    can be defined (:meth:`define`), attributes given default values (:meth:`set_default`) and the layer given
    metadata (:meth:`set_metadata`), so that the file is self-contained.
    """

    def __init__(self, path: str | Path, attributes: Sequence[tuple[str, str]]) -> None:
        self.path = Path(path)
        self._root = _Node("")
        self._attributes: list[_Node] = []
        for attribute, type_name in attributes:
            if type_name not in TYPES:
                raise ValueError(f"attribute {attribute}: type {type_name!r} is not one of {sorted(TYPES)}")
            prim, _, name = attribute.rpartition(".")
            leaf = _Node(name, type_name)
            self._root.find(prim).children.append(leaf)
            self._attributes.append(leaf)
        self._metadata: dict[str, str | float] = {}
        self._kinds = [TYPES[node.attribute] for node in self._attributes]
        self._sizes: list[int] | None = None  # the value lengths the frame layout is for (:meth:`_lay_out`)
        self._starts: list[int] = []  # where each frame in the current layout starts
        self._rep_blocks: list[np.ndarray] = []  # the ValueReps of the frames of earlier layouts, (frames, attributes)
        self._times: list[float] = []
        self._fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        self._offset = _BOOTSTRAP_BYTES  # the header's room, written on closing (zeros until then)
        self._tail: list[bytes | np.ndarray] = []  # what closing adds, written together

    @property
    def last_time(self) -> float:
        """The last time code sampled (raises IndexError before the first :meth:`add`)."""
        return self._times[-1]

    def add(self, time: float, values: Sequence[np.ndarray]) -> None:
        """Sample every attribute at time code ``time``: one value per attribute, in the constructor's order.

        A float3 array is an (n, 3) float32 array (C-contiguous), a matrix a 4x4 float64 array. Values are
        written before this returns; the arrays may be reused after it.
        """
        if len(values) != len(self._attributes):
            raise ValueError(f"expected {len(self._attributes)} values, got {len(values)}")
        if self._times and not time > self._times[-1]:
            raise ValueError(f"time {time} after {self._times[-1]}: times must increase")
        sizes = [len(value) for value in values]
        if sizes != self._sizes:
            self._lay_out(sizes)
        parts = self._parts.copy()
        for slot, dtype, shape, i in self._values:
            parts[slot] = np.ascontiguousarray(values[i], dtype).reshape(shape)  # no copy of one already so
        _pwrite_all(self._fd, parts, self._offset, self._frame_bytes)  # one system call per frame
        self._starts.append(self._offset)
        self._offset += self._frame_bytes
        self._times.append(float(time))

    def _lay_out(self, sizes: list[int]) -> None:
        """Where each value of a frame of these lengths goes, relative to the frame's start.

        Arrays start 8-byte aligned, so that a reader may map them in place, and each frame's size is a multiple
        of 8; an empty array has nothing in the file. The ValueReps of the frames so far are kept first.
        """
        self._fold_reps()
        parts: list[bytes | None] = []
        values: list[tuple[int, np.dtype, tuple[int, ...], int]] = []  # (part, dtype, shape, index) of each written
        reps, shifts = [], []
        end = 0
        for i, (kind, size) in enumerate(zip(self._kinds, sizes, strict=True)):
            if kind == _MATRIX4D:
                reps.append(_rep(_MATRIX4D, end))
                values.append((len(parts), _FLOAT64, (16,), i))
                parts.append(None)
                end += 128
            elif size:
                pad = -end % 8
                reps.append(_VEC3F_ARRAY | (end + pad))
                parts.append(_PADS[pad] + size.to_bytes(8, "little"))
                values.append((len(parts), _FLOAT32, (size, 3), i))
                parts.append(None)
                end += pad + 8 + 12 * size
            else:
                reps.append(_VEC3F_ARRAY)  # payload 0
            shifts.append(1 if kind == _MATRIX4D or size else 0)
        if end % 8:
            parts.append(_PADS[-end % 8])
            end += -end % 8
        self._sizes, self._parts, self._frame_bytes = sizes, parts, end
        self._values = values
        self._layout_reps = np.asarray(reps, np.uint64), np.asarray(shifts, np.uint64)

    def _fold_reps(self) -> None:
        """Turn the frames added in the current layout into ValueReps, one column per attribute."""
        if self._starts:
            reps, shifts = self._layout_reps
            starts = np.asarray(self._starts, np.uint64)[:, None]
            self._rep_blocks.append(reps[None, :] + shifts[None, :] * starts)
            self._starts = []

    def define(self, prim: str, type_name: str) -> None:
        """Make the prim at absolute path ``prim`` (made where new) a ``def`` of type ``type_name``."""
        self._root.find(prim).type_name = type_name

    def set_default(self, attribute: str, type_name: str, value: object, uniform: bool = False) -> None:
        """Give ``attribute`` (an absolute prim path and a property name) the default ``value``.

        ``uniform``: its variability (else varying). Not for a sampled attribute; type names from
        :data:`DEFAULT_TYPES`.
        """
        if type_name not in DEFAULT_TYPES:
            raise ValueError(f"attribute {attribute}: type {type_name!r} is not one of {list(DEFAULT_TYPES)}")
        prim, _, name = attribute.rpartition(".")
        node = self._root.find(prim).child(name, type_name)
        if any(node is sampled for sampled in self._attributes):
            raise ValueError(f"attribute {attribute} is sampled: it takes no default value")
        node.attribute, node.default, node.uniform = type_name, value, uniform

    def set_metadata(self, name: str, value: str | float) -> None:
        """Set the layer's metadata field ``name`` (e.g. ``upAxis``) to a token (str) or a double (float)."""
        self._metadata[name] = value

    def _write(self, data: bytes | np.ndarray) -> None:
        """Append ``data`` (bytes, or a C-contiguous array as it is in memory) to what closing writes.

        It goes at :attr:`_offset`, which it advances.
        """
        self._tail.append(data)
        self._offset += data.nbytes if isinstance(data, np.ndarray) else len(data)

    def close(self) -> None:
        """Write the time-sample records and the structural sections, then the header: the file is complete.

        They are gathered in memory (large arrays as they are, not copied) and written with as few system calls
        as can take them: each one lets the other threads take the interpreter lock, and waiting to take it back
        costs the writer far more than the call.
        """
        start = times = self._offset
        self._write(struct.pack("<Q", len(self._times)) + np.asarray(self._times, "<f8").tobytes())
        self._fold_reps()
        columns = (
            np.concatenate(self._rep_blocks) if self._rep_blocks else np.zeros((0, len(self._attributes)), np.uint64)
        )
        for node, reps in zip(self._attributes, columns.T, strict=True):
            node.samples = self._offset
            record = struct.pack("<qQq", 8, _rep(_DOUBLE_VECTOR, times), 8)  # no nested data: each jump is 8
            self._write(record + struct.pack("<Q", len(reps)) + np.asarray(reps, "<u8").tobytes())
        sections = self._structure()
        toc = self._offset
        entries = b"".join(struct.pack("<16sqq", name, start, size) for name, start, size in sections)
        self._write(struct.pack("<Q", len(sections)) + entries)
        _pwrite_all(self._fd, self._tail, start, self._offset - start)
        header = b"PXR-USDC" + bytes(VERSION) + bytes(5) + struct.pack("<q", toc)
        _pwrite_all(self._fd, [header], 0, len(header))
        self._tail = []
        self._release()

    def discard(self) -> None:
        """Close and remove the file."""
        self._release()
        self.path.unlink(missing_ok=True)

    def _release(self) -> None:
        """Close the file."""
        if self._fd >= 0:
            os.close(self._fd)
            self._fd = -1

    def _structure(self) -> list[tuple[bytes, int, int]]:
        """Write tokens, strings, fields, field sets, paths and specs; return ``(name, start, size)`` of each."""
        specs = _SpecTables(self)
        specs.visit(self._root, _SPEC_PSEUDO_ROOT, True)
        names = list(specs.tokens)
        sections: list[tuple[bytes, int, int]] = []

        def section(name: bytes, data: bytes) -> None:
            sections.append((name, self._offset, len(data)))
            self._write(data)

        text = b"".join(n.encode() + b"\0" for n in names)
        block = lz4_literal_block(text)
        section(b"TOKENS", struct.pack("<QQQ", len(names), len(text), len(block)) + block)
        section(b"STRINGS", struct.pack("<Q", 0))
        fields, field_sets, paths = specs.fields, specs.field_sets, specs.paths
        reps = lz4_literal_block(np.asarray([r for _, r in fields], "<u8").tobytes())
        section(
            b"FIELDS",
            struct.pack("<Q", len(fields))
            + compressed_ints([t for t, _ in fields])
            + struct.pack("<Q", len(reps))
            + reps,
        )
        section(b"FIELDSETS", struct.pack("<Q", len(field_sets)) + compressed_ints(field_sets))
        section(
            b"PATHS",
            struct.pack("<QQ", len(paths), len(paths))
            + compressed_ints(range(len(paths)))
            + compressed_ints([e for e, _ in paths])
            + compressed_ints([j for _, j in paths]),
        )
        section(
            b"SPECS",
            struct.pack("<Q", len(specs.specs))
            + compressed_ints([p for p, _, _ in specs.specs])
            + compressed_ints([f for _, f, _ in specs.specs])
            + compressed_ints([k for _, _, k in specs.specs]),
        )
        return sections


class _SpecTables:
    """The crate's structural tables for a tree of prims and attributes, built by :meth:`visit`.

    Token vectors (a prim's children and properties) are written to ``stream`` as they come; the rest is
    kept here for :meth:`CrateStream._structure` to write as sections.
    """

    def __init__(self, stream: CrateStream) -> None:
        self.stream = stream
        self.tokens: dict[str, int] = {"": 0}
        self.fields: list[tuple[int, int]] = []
        self.field_sets: list[int] = []
        self.specs: list[tuple[int, int, int]] = []
        self.paths: list[tuple[int, int]] = []  # (element token, or minus it for a property; jump)

    def token(self, text: str) -> int:
        return self.tokens.setdefault(text, len(self.tokens))

    def add_spec(self, kind: int, entries: list[tuple[str, int]]) -> None:
        self.specs.append((len(self.paths) - 1, len(self.field_sets), kind))
        for name, rep in entries:
            self.field_sets.append(len(self.fields))
            self.fields.append((self.token(name), rep))
        self.field_sets.append(0xFFFFFFFF)

    def token_vector(self, names: list[str]) -> int:
        offset = self.stream._offset
        indices = [self.token(n) for n in names]
        self.stream._write(struct.pack("<Q", len(indices)) + struct.pack(f"<{len(indices)}I", *indices))
        return _rep(_TOKEN_VECTOR, offset)

    def value(self, type_name: str, value: object) -> int:
        """Write ``value`` of USD type ``type_name`` (one of :data:`DEFAULT_TYPES` or ``double``); its ValueRep.

        A token is inlined; anything else goes to the stream, 8-byte aligned: a double as itself, an array as
        its element count and its elements (uncompressed, which every crate reader takes).
        """
        if type_name == "token":
            return _rep(_TOKEN, self.token(value), inlined=True)
        stream = self.stream
        stream._write(_PADS[-stream._offset % 8])
        offset = stream._offset
        if type_name == "double":
            stream._write(struct.pack("<d", value))
            return _rep(_DOUBLE, offset)
        if type_name == "matrix4d":
            stream._write(np.ascontiguousarray(value, "<f8").reshape(16))
            return _rep(_MATRIX4D, offset)
        if type_name == "token[]":
            kind, data = _TOKEN, np.asarray([self.token(t) for t in value], "<u4")
        elif type_name == "int[]":
            kind, data = _INT, np.ascontiguousarray(value, "<i4").reshape(-1)
        else:
            kind, data = _VEC3F, np.ascontiguousarray(value, _FLOAT32).reshape(-1, 3)
        if not len(data):
            return _rep(kind, 0, array=True)
        stream._write(len(data).to_bytes(8, "little"))
        stream._write(data)
        return _rep(kind, offset, array=True)

    def visit(self, node: _Node, kind: int, last: bool) -> None:
        """Add ``node``'s path and spec, then its children's, depth first (``last``: no sibling follows)."""
        index = len(self.paths)
        self.paths.append((-self.token(node.name) if node.attribute else self.token(node.name), 0))
        if node.attribute:
            variability = _VARIABILITY_UNIFORM if node.uniform else _VARIABILITY_VARYING
            value = (
                ("timeSamples", _rep(_TIME_SAMPLES, node.samples))
                if node.samples >= 0
                else ("default", self.value(node.attribute, node.default))
            )
            self.add_spec(
                _SPEC_ATTRIBUTE,
                [
                    ("typeName", _rep(_TOKEN, self.token(node.attribute), inlined=True)),
                    ("custom", _rep(_BOOL, 0, inlined=True)),
                    ("variability", _rep(_VARIABILITY, variability, inlined=True)),
                    value,
                ],
            )
        else:
            prims = [c.name for c in node.children if c.attribute is None]
            props = [c.name for c in node.children if c.attribute is not None]
            if kind == _SPEC_PSEUDO_ROOT:
                metadata = self.stream._metadata.items()
                entries = [(k, self.value("token" if isinstance(v, str) else "double", v)) for k, v in metadata]
            else:
                specifier = _SPECIFIER_DEF if node.type_name else _SPECIFIER_OVER
                entries = [("specifier", _rep(_SPECIFIER, specifier, True))]
                entries += [("typeName", self.value("token", node.type_name))] if node.type_name else []
            entries += [("primChildren", self.token_vector(prims))] if prims else []
            entries += [("properties", self.token_vector(props))] if props else []
            self.add_spec(kind, entries)
        for i, child in enumerate(node.children):
            self.visit(child, _SPEC_PRIM, i == len(node.children) - 1)
        has_child, has_sibling = bool(node.children), not last
        jump = len(self.paths) - index if has_child and has_sibling else 0 if has_sibling else -1 if has_child else -2
        self.paths[index] = (self.paths[index][0], jump)


def _pwrite_all(fd: int, parts: Sequence[bytes | memoryview | np.ndarray], offset: int, size: int = -1) -> None:
    """Write ``parts`` (C-contiguous buffers) one after the other from ``offset``, ``size`` bytes in all if known.

    One ``pwritev`` where it writes them all, as it does for a frame; it may write less than asked: go on.
    """
    if 0 <= size and len(parts) <= _IOV_MAX:
        written = os.pwritev(fd, parts, offset) if parts else 0
        if written == size:
            return
    else:
        written = 0
    views = [memoryview(part).cast("B") for part in parts if len(part)]
    while views:
        while views and written >= views[0].nbytes:
            written -= views[0].nbytes
            offset += views[0].nbytes
            views.pop(0)
        if written:
            offset += written
            views[0], written = views[0][written:], 0
        if views:
            written = os.pwritev(fd, views[:_IOV_MAX], offset)
