"""Houdini's classic binary geometry (``.bgeo``, "BgeoV" version 5) for point clouds: numpy only.

This is the layout Houdini reads as ``.bgeo`` (and writes as ``.bhclassic``), the one partio reads and
writes and SPlisHSPlasH exports particles in.  Everything is big-endian, 32-bit:

* header (41 bytes): the magic ``b"Bgeo"``, the version character ``b"V"``, then nine int32: the
  version (5), the number of points, of primitives, of point groups and of primitive groups, and the
  number of point, vertex, primitive and detail attributes;
* the point attribute dictionary, one entry per attribute: its name (uint16 length and the bytes),
  its size in 32-bit words (uint16), its type (int32: 0 float, 1 int, 5 vector, 4 index (string
  table)) and its default value (``size`` words; zero here).  Position is not in the dictionary:
  every point record starts with it;
* the points, one record each: ``P`` as four float32 (x, y, z and the homogeneous w = 1), then every
  attribute's words in dictionary order;
* no primitives and no groups (a point cloud);
* the detail (whole-geometry) attribute dictionary, as the point one, where an index attribute is
  followed by its string table (int32 count, then uint16 length and bytes per string) instead of a
  default, then one record of the detail values (an index attribute's value is its string's index);
* two closing bytes, ``0x00`` and ``0xff`` (the empty "extra" section).

:func:`write_bgeo` writes it (gzip-compressed when the name ends in ``.gz``, as ``name.bgeo.gz``,
which Houdini and partio also open); :func:`read_bgeo` reads such a point cloud back.  Float
attributes are stored as float32 and int attributes as int32, the only widths the format has.
"""
from __future__ import annotations

import gzip
import io
import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import Mapping

import numpy as np

from .files import atomic_path

__all__ = ["MAGIC", "VERSION", "FLOAT", "INT", "INDEX", "VECTOR", "HEADER", "Bgeo", "write_bgeo", "read_bgeo"]

MAGIC = b"Bgeo"
VERSION = 5
HEADER = struct.Struct(">4sc9i")       # magic, b"V", version, points, prims, point groups, prim groups,
#                                        point / vertex / primitive / detail attribute counts
FLOAT, INT, INDEX, VECTOR = 0, 1, 4, 5
_TYPE_NAMES = {FLOAT: "float", INT: "int", INDEX: "index", VECTOR: "vector"}
_NEW_FORMAT_MAGIC = b"\x7fNSJ"         # Houdini 12+ binary JSON geometry, not this layout
_MAX_NAME = 0xFFFF


@dataclass
class Bgeo:
    """A point cloud read by :func:`read_bgeo`.

    ``points``: ``P`` (N, 3) float32, ``Pw`` (N,) the homogeneous coordinate, and each point attribute
    by name: float32 (N,) or (N, size), int32 likewise.  ``detail``: each detail attribute as a Python
    value (float, int, str; a tuple when its size is above 1).  ``point_types`` and ``detail_types``: the
    format's type name of each attribute (``"float"``, ``"int"``, ``"vector"``, ``"index"``); a point and a
    detail attribute may share a name."""
    points: dict = field(default_factory=dict)
    detail: dict = field(default_factory=dict)
    point_types: dict = field(default_factory=dict)
    detail_types: dict = field(default_factory=dict)

    @property
    def n_points(self) -> int:
        return len(self.points["P"])


# ---- writing -------------------------------------------------------------------------------------
def _string_bytes(text: str) -> bytes:
    raw = str(text).encode("utf-8")
    if len(raw) > _MAX_NAME:
        raise ValueError(f"string {text[:40]!r}...: longer than {_MAX_NAME} bytes")
    return struct.pack(">H", len(raw)) + raw


def _name_bytes(name: str) -> bytes:
    if not str(name):
        raise ValueError("attribute names cannot be empty")
    return _string_bytes(name)


def _point_column(name: str, value, n: int, vector: bool):
    """(type, size, big-endian array (n, size)) of one point attribute."""
    arr = np.asarray(value)
    if arr.ndim == 0 or arr.shape[0] != n or arr.ndim > 2:
        raise ValueError(f"point attribute {name!r}: shape {arr.shape}, expected ({n},) or ({n}, k)")
    if arr.ndim == 1:
        arr = arr[:, None]
    size = arr.shape[1]
    if not 1 <= size <= 0xFFFF:
        raise ValueError(f"point attribute {name!r}: {size} components (1 to 65535)")
    if arr.dtype.kind == "f":
        kind = VECTOR if vector and size == 3 else FLOAT
        return kind, size, arr.astype(">f4")
    if arr.dtype.kind in "iub":
        if arr.size and (arr.min() < -2**31 or arr.max() >= 2**31):
            raise ValueError(f"point attribute {name!r}: values outside int32, which is all .bgeo stores")
        return INT, size, arr.astype(">i4")
    raise TypeError(f"point attribute {name!r}: dtype {arr.dtype} (numbers only)")


def _detail_entry(name: str, value):
    """(definition bytes, value bytes) of one detail attribute."""
    if isinstance(value, (str, bytes)):
        text = value.decode("utf-8") if isinstance(value, bytes) else value
        table = struct.pack(">Hii", 1, INDEX, 1) + _string_bytes(text)
        return _name_bytes(name) + table, struct.pack(">i", 0)
    arr = np.atleast_1d(np.asarray(value))
    if arr.ndim != 1 or not 1 <= arr.size <= 0xFFFF:
        raise ValueError(f"detail attribute {name!r}: a number, a 1-D list of numbers or a string")
    if arr.dtype.kind == "f":
        kind, data = FLOAT, arr.astype(">f4")
    elif arr.dtype.kind in "iub":
        if arr.min() < -2**31 or arr.max() >= 2**31:
            raise ValueError(f"detail attribute {name!r}: values outside int32")
        kind, data = INT, arr.astype(">i4")
    else:
        raise TypeError(f"detail attribute {name!r}: {type(value).__name__} (numbers or a string)")
    definition = _name_bytes(name) + struct.pack(">Hi", arr.size, kind) + bytes(4 * arr.size)
    return definition, data.tobytes()


def encode_bgeo(position, attributes: Mapping[str, np.ndarray] | None = None,
                detail: Mapping[str, object] | None = None, vectors=("v", "N")) -> bytes:
    """The bytes of a .bgeo point cloud (see :func:`write_bgeo`)."""
    pos = np.asarray(position)
    if pos.ndim != 2 or pos.shape[1] != 3 or pos.dtype.kind != "f":
        raise ValueError(f"position: float array (N, 3), got {pos.dtype} {pos.shape}")
    n = len(pos)
    attributes = dict(attributes or {})
    detail = dict(detail or {})
    for reserved in ("P", "Pw"):
        if reserved in attributes:
            raise ValueError(f"point attribute {reserved!r} is the position; pass it as `position`")
    columns = [(name, *_point_column(name, value, n, name in vectors)) for name, value in attributes.items()]

    out = io.BytesIO()
    out.write(HEADER.pack(MAGIC, b"V", VERSION, n, 0, 0, 0, len(columns), 0, 0, len(detail)))
    for name, kind, size, _ in columns:
        out.write(_name_bytes(name) + struct.pack(">Hi", size, kind) + bytes(4 * size))
    # one big-endian record per point: P (x, y, z, w = 1), then each attribute
    fields = [("P", ">f4", (4,))] + [(f"a{i}", arr.dtype.str, (size,)) for i, (_, _, size, arr) in enumerate(columns)]
    records = np.empty(n, dtype=np.dtype(fields))
    records["P"][:, :3] = pos
    records["P"][:, 3] = 1.0
    for i, (_, _, _, arr) in enumerate(columns):
        records[f"a{i}"] = arr
    out.write(records.tobytes())
    entries = [_detail_entry(name, value) for name, value in detail.items()]
    for definition, _ in entries:
        out.write(definition)
    for _, value in entries:
        out.write(value)
    out.write(b"\x00\xff")
    return out.getvalue()


def write_bgeo(path: str | Path, position, attributes: Mapping[str, np.ndarray] | None = None,
               detail: Mapping[str, object] | None = None, vectors=("v", "N")) -> Path:
    """Write a point cloud as classic binary ``.bgeo`` (atomically); returns the path.

    ``position``: (N, 3) floats, stored as ``P`` with w = 1.  ``attributes``: per-point arrays (N,)
    or (N, k) by name; floats become float attributes (``vector`` when the name is in ``vectors`` and
    k = 3, so Houdini transforms them as directions), integers and booleans int attributes (values must
    fit int32).  ``detail``: whole-geometry values (a number, a short 1-D list of numbers, or a string,
    stored as an index attribute).  A name ending in ``.gz`` is gzip-compressed."""
    path = Path(path)
    data = encode_bgeo(position, attributes, detail, vectors)
    with atomic_path(path) as tmp:
        if path.name.endswith(".gz"):
            with gzip.open(tmp, "wb") as fh:
                fh.write(data)
        else:
            Path(tmp).write_bytes(data)
    return path


# ---- reading -------------------------------------------------------------------------------------
class _Cursor:
    def __init__(self, data: bytes, source: str):
        self.data, self.pos, self.source = data, 0, source

    def take(self, count: int) -> bytes:
        if self.pos + count > len(self.data):
            raise ValueError(f"{self.source}: truncated .bgeo ({len(self.data)} bytes, needs more at {self.pos})")
        chunk = self.data[self.pos:self.pos + count]
        self.pos += count
        return chunk

    def unpack(self, fmt: str):
        st = struct.Struct(fmt)
        return st.unpack(self.take(st.size))

    def string(self) -> str:
        (length,) = self.unpack(">H")
        return self.take(length).decode("utf-8")


def _dictionary(cur: _Cursor, count: int, where: str):
    """[(name, type, size, strings or None)] of an attribute dictionary."""
    entries = []
    for _ in range(count):
        name = cur.string()
        size, kind = cur.unpack(">Hi")
        if kind in (FLOAT, INT, VECTOR):
            cur.take(4 * size)                      # default value
            entries.append((name, kind, size, None))
        elif kind == INDEX:
            (count_strings,) = cur.unpack(">i")
            entries.append((name, kind, size, [cur.string() for _ in range(count_strings)]))
        else:
            raise ValueError(f"{cur.source}: {where} attribute {name!r} has type {kind}, which this reader "
                             f"does not read (float, int, vector, index)")
    return entries


def decode_bgeo(data: bytes, source: str = "<bytes>") -> Bgeo:
    """A :class:`Bgeo` from the bytes of a classic .bgeo point cloud (see :func:`read_bgeo`)."""
    if data[:2] == b"\x1f\x8b":
        data = gzip.decompress(data)
    cur = _Cursor(data, source)
    if len(data) < HEADER.size:
        raise ValueError(f"{source}: {len(data)} bytes, shorter than a .bgeo header")
    magic, vchar, version, n, prims, point_groups, prim_groups, n_point, n_vertex, n_prim, n_detail = \
        HEADER.unpack(cur.take(HEADER.size))
    if magic == _NEW_FORMAT_MAGIC:
        raise ValueError(f"{source}: Houdini's newer JSON-based .bgeo; this reads the classic format "
                         "(save as .bhclassic in Houdini)")
    if magic != MAGIC or vchar != b"V":
        raise ValueError(f"{source}: not a classic .bgeo (starts {data[:5]!r}, expected b'BgeoV')")
    if version != VERSION:
        raise ValueError(f"{source}: .bgeo version {version}, this reads version {VERSION}")
    if prims or point_groups or prim_groups or n_vertex or n_prim or n < 0:
        raise ValueError(f"{source}: {prims} primitives, {point_groups + prim_groups} groups, "
                         f"{n_vertex + n_prim} vertex/primitive attributes; this reads point clouds only")
    point_dict = _dictionary(cur, n_point, "point")
    fields = [("P", ">f4", (4,))]
    for i, (name, kind, size, _) in enumerate(point_dict):
        fields.append((f"a{i}", ">i4" if kind in (INT, INDEX) else ">f4", (size,)))
    dtype = np.dtype(fields)
    records = np.frombuffer(cur.take(dtype.itemsize * n), dtype=dtype, count=n)
    out = Bgeo()
    out.points["P"] = records["P"][:, :3].astype("=f4")
    out.points["Pw"] = records["P"][:, 3].astype("=f4")
    for i, (name, kind, size, _) in enumerate(point_dict):
        col = records[f"a{i}"].astype("=i4" if kind in (INT, INDEX) else "=f4")
        out.points[name] = col[:, 0].copy() if size == 1 else col.copy()
        out.point_types[name] = _TYPE_NAMES[kind]
    detail_dict = _dictionary(cur, n_detail, "detail")
    for name, kind, size, strings in detail_dict:
        raw = cur.take(4 * size)
        if kind == INDEX:
            index = struct.unpack(f">{size}i", raw)
            values = tuple(strings[k] if 0 <= k < len(strings) else None for k in index)
        else:
            values = struct.unpack(f">{size}{'i' if kind == INT else 'f'}", raw)
        out.detail[name] = values[0] if size == 1 else values
        out.detail_types[name] = _TYPE_NAMES[kind]
    tail = data[cur.pos:]
    if tail[:2] != b"\x00\xff":
        raise ValueError(f"{source}: {len(tail)} unexpected bytes after the detail attributes")
    return out


def read_bgeo(path: str | Path) -> Bgeo:
    """Read a classic binary .bgeo (or .bgeo.gz) point cloud: version 5, points with any float, int,
    vector or index attributes, no primitives or groups; detail attributes of the same types.
    Raises ValueError naming what is not such a file."""
    path = Path(path)
    return decode_bgeo(path.read_bytes(), str(path))
