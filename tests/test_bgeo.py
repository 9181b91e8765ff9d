"""Houdini's classic .bgeo (cloudpbf_io.bgeo): the bytes of the header and records read with struct alone,
write -> read round trips bit for bit, a property over random clouds, gzip, and the refusals."""
from __future__ import annotations

import gzip
import struct

import numpy as np
import pytest

from cloudpbf_io.bgeo import decode_bgeo, encode_bgeo, read_bgeo, write_bgeo
from cloudpbf_io.export import PARTICLE_UNITS, state_to_bgeo, write_bgeo_series


def _state(n, rng, step=0, time=0.0):
    return {"position": rng.uniform(-50, 3000, (n, 3)).astype(np.float32),
            "velocity": rng.normal(size=(n, 3)).astype(np.float32),
            "temperature": rng.uniform(250, 300, n).astype(np.float32),
            "vapor": rng.uniform(0, 0.02, n).astype(np.float32),
            "cloud": rng.uniform(0, 1e-3, n).astype(np.float32),
            "mass": rng.uniform(1e5, 3e5, n).astype(np.float32),
            "level": rng.integers(0, 3, n).astype(np.int32),
            "kernel_radius": np.full(n, 7.0, np.float32),
            "id": rng.permutation(n).astype(np.uint32) + np.uint32(2**31 - n - 1),
            "step": np.int64(step), "time_s": np.float64(time)}


def test_header_and_records_are_big_endian_bgeov5(tmp_path):
    """Read with struct, independently of read_bgeo: magic, version, counts, the dictionary, and the
    first point record (P with w = 1, then v, then temperature), all big-endian."""
    pos = np.array([[1.5, -2.0, 3.25], [4.0, 5.0, 6.0]], np.float32)
    vel = np.array([[0.1, 0.2, 0.3], [-1.0, -2.0, -3.0]], np.float32)
    temp = np.array([280.5, 281.0], np.float32)
    level = np.array([2, 0], np.int32)
    path = write_bgeo(tmp_path / "two.bgeo", pos, {"v": vel, "temperature": temp, "level": level},
                      {"time": 12.5, "scene": "growing"})
    raw = path.read_bytes()
    assert raw[:5] == b"BgeoV"
    header = struct.unpack(">9i", raw[5:41])
    assert header == (5, 2, 0, 0, 0, 3, 0, 0, 2)     # version, points, prims, groups x2, attrs p/v/prim/detail
    assert struct.unpack("<i", raw[5:9])[0] != 5     # really big-endian: little-endian would misread it
    off = 41
    seen = []
    for _ in range(3):
        (length,) = struct.unpack(">H", raw[off:off + 2])
        name = raw[off + 2:off + 2 + length].decode()
        size, kind = struct.unpack(">Hi", raw[off + 2 + length:off + 8 + length])
        default = struct.unpack(f">{size}i", raw[off + 8 + length:off + 8 + length + 4 * size])
        seen.append((name, size, kind, default))
        off += 8 + length + 4 * size
    assert seen == [("v", 3, 5, (0, 0, 0)), ("temperature", 1, 0, (0,)), ("level", 1, 1, (0,))]
    record = struct.unpack(">4f3ffi", raw[off:off + 36])
    assert record == (1.5, -2.0, 3.25, 1.0, np.float32(0.1), np.float32(0.2), np.float32(0.3), 280.5, 2)
    second = struct.unpack(">4f3ffi", raw[off + 36:off + 72])
    assert second[3] == 1.0 and second[-1] == 0 and second[:3] == (4.0, 5.0, 6.0)
    assert raw[-2:] == b"\x00\xff"
    # detail: 'time' float, 'scene' an index attribute with a one-string table, then the values (12.5, index 0)
    assert raw[-10:-2] == struct.pack(">fi", 12.5, 0)
    assert b"growing" in raw[off + 72:]


def test_state_round_trip_is_bitwise(tmp_path):
    rng = np.random.default_rng(3)
    state = _state(500, rng, step=40, time=80.0)
    pos, attrs, detail = state_to_bgeo(state, time=80.0, step=40, scene_name="growing")
    back = read_bgeo(write_bgeo(tmp_path / "s.bgeo", pos, attrs, detail))
    assert back.n_points == 500
    assert back.points["P"].tobytes() == state["position"].tobytes()
    assert (back.points["Pw"] == 1.0).all()
    assert back.points["v"].tobytes() == state["velocity"].tobytes() and back.point_types["v"] == "vector"
    for name in ("temperature", "vapor", "cloud", "mass", "kernel_radius"):
        assert back.points[name].dtype == np.float32 and back.point_types[name] == "float"
        assert back.points[name].tobytes() == state[name].tobytes(), name
    for name in ("level", "id"):
        assert back.point_types[name] == "int"
        np.testing.assert_array_equal(back.points[name].astype(np.int64), state[name].astype(np.int64))
    assert back.detail["time"] == 80.0 and back.detail["step"] == 40 and back.detail["scene"] == "growing"
    assert back.detail["P_unit"] == "m" and back.detail["v_unit"] == "m/s"
    for name in ("temperature", "vapor", "cloud", "mass", "level", "id", "kernel_radius"):
        assert back.detail[f"{name}_unit"] == PARTICLE_UNITS[name]
    assert set(back.points) == {"P", "Pw", "v", "temperature", "vapor", "cloud", "mass", "level",
                                "kernel_radius", "id"}


def test_gzip_and_empty_cloud(tmp_path):
    rng = np.random.default_rng(4)
    pos = rng.normal(size=(7, 3)).astype(np.float32)
    path = write_bgeo(tmp_path / "g.bgeo.gz", pos, {"cloud": np.arange(7, dtype=np.float32)},
                      {"step": 3, "origin": [0.5, -1.0, 2.0], "shape": np.array([4, 5, 6])})
    raw = path.read_bytes()
    assert raw[:2] == b"\x1f\x8b" and gzip.decompress(raw)[:5] == b"BgeoV"
    back = read_bgeo(path)
    assert back.points["P"].tobytes() == pos.tobytes()
    assert back.detail == {"step": 3, "origin": (0.5, -1.0, 2.0), "shape": (4, 5, 6)}
    assert back.detail_types["origin"] == "float" and back.detail_types["shape"] == "int"
    empty = decode_bgeo(encode_bgeo(np.zeros((0, 3), np.float32), {"level": np.zeros(0, np.int32)}))
    assert empty.n_points == 0 and empty.points["level"].shape == (0,)


def test_refusals(tmp_path):
    pos = np.zeros((2, 3), np.float32)
    with pytest.raises(ValueError, match="int32"):
        encode_bgeo(pos, {"id": np.array([0, 2**31], np.uint32)})
    with pytest.raises(ValueError, match="shape"):
        encode_bgeo(pos, {"cloud": np.zeros(3, np.float32)})
    with pytest.raises(ValueError, match="position"):
        encode_bgeo(pos, {"P": pos})
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        encode_bgeo(np.zeros((2, 2), np.float32))
    good = encode_bgeo(pos, {"cloud": np.zeros(2, np.float32)})
    with pytest.raises(ValueError, match="truncated"):
        decode_bgeo(good[:-12])
    with pytest.raises(ValueError, match="classic"):
        decode_bgeo(b"\x7fNSJ" + good[4:])
    with pytest.raises(ValueError, match="version 6"):
        decode_bgeo(good[:5] + struct.pack(">i", 6) + good[9:])
    with pytest.raises(ValueError, match="point clouds only"):
        decode_bgeo(good[:13] + struct.pack(">i", 1) + good[17:])


def test_series_names_frames_for_houdini_and_drops_stale_frames(tmp_path):
    rng = np.random.default_rng(5)
    frames = [_state(30, rng, step=s, time=2.0 * s) for s in (0, 5, 10)]
    paths = write_bgeo_series(frames, tmp_path, name="particles-growing", scene_name="growing")
    assert [p.name for p in paths] == [f"particles-growing.000{i}.bgeo" for i in (1, 2, 3)]
    for path, frame in zip(paths, frames):
        back = read_bgeo(path)
        assert back.detail["step"] == int(frame["step"]) and back.detail["time"] == float(frame["time_s"])
        assert back.points["cloud"].tobytes() == frame["cloud"].tobytes()
    (tmp_path / "other.0009.bgeo").write_bytes(b"")
    again = write_bgeo_series(frames[:2], tmp_path, name="particles-growing")
    assert sorted(p.name for p in tmp_path.glob("particles-growing.*.bgeo")) == [p.name for p in again]
    assert (tmp_path / "other.0009.bgeo").exists()


hypothesis = pytest.importorskip("hypothesis")
from hypothesis import given, settings, strategies as st  # noqa: E402
from hypothesis.extra import numpy as hnp  # noqa: E402

_floats = hnp.from_dtype(np.dtype(np.float32), allow_nan=True, allow_infinity=True)


@st.composite
def _clouds(draw):
    n = draw(st.integers(0, 40))
    pos = draw(hnp.arrays(np.float32, (n, 3), elements=_floats))
    names = draw(st.lists(st.from_regex(r"[A-Za-z_][A-Za-z0-9_]{0,12}", fullmatch=True)
                          .filter(lambda s: s not in ("P", "Pw")), max_size=5, unique=True))
    attrs = {}
    for name in names:
        kind = draw(st.sampled_from(["f1", "f3", "f4", "i1", "u1"]))
        width = int(kind[1])
        if kind[0] == "f":
            attrs[name] = draw(hnp.arrays(np.float32, (n,) if width == 1 else (n, width), elements=_floats))
        elif kind[0] == "i":
            attrs[name] = draw(hnp.arrays(np.int32, (n,)))
        else:
            attrs[name] = draw(hnp.arrays(np.uint32, (n,), elements=st.integers(0, 2**31 - 1)))
    detail = draw(st.dictionaries(st.from_regex(r"[a-z]{1,8}", fullmatch=True),
                                  st.one_of(st.integers(-2**31, 2**31 - 1), st.text(max_size=10),
                                            st.floats(width=32, allow_nan=False)), max_size=4))
    return pos, attrs, detail


@settings(max_examples=60, deadline=None)
@given(_clouds())
def test_round_trip_property(cloud):
    pos, attrs, detail = cloud
    back = decode_bgeo(encode_bgeo(pos, attrs, detail, vectors=()))
    assert back.n_points == len(pos)
    assert back.points["P"].tobytes() == pos.tobytes()       # NaN payloads and -0.0 included
    assert back.points["Pw"].tobytes() == np.ones(len(pos), np.float32).tobytes()
    for name, arr in attrs.items():
        got = back.points[name]
        assert got.shape == arr.shape
        if arr.dtype.kind == "f":
            assert back.point_types[name] == "float" and got.tobytes() == arr.tobytes()
        else:
            assert back.point_types[name] == "int" and got.tobytes() == arr.astype(np.int32).tobytes()
    assert back.detail.keys() == detail.keys()
    for key, value in detail.items():
        assert back.detail_types[key] == ("index" if isinstance(value, str) else
                                          "float" if isinstance(value, float) else "int")
        got = back.detail[key]
        if isinstance(value, float):
            assert np.float32(got).tobytes() == np.float32(value).tobytes()
        else:
            assert got == value and type(got) is type(value)
