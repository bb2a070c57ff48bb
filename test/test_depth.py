"""Depth decoding without DDS: the raw bytes of sensor_msgs/Image fields -> metres.

Each case builds the bytes by hand (struct, not depth.encode_depth), so a decoder that gets the
byte order, the row padding or the millimetre scale wrong fails here in milliseconds.
"""

from __future__ import annotations

import struct

import numpy as np
import pytest

from task_outcome_ros.depth import DepthDecodeError, decode_depth, encode_depth, sanitize_depth

pytestmark = pytest.mark.unit

# 2 rows x 3 columns; 0 and NaN are the encodings' "no return".
METRES = [[1.0, 2.5, 0.0], [4.25, 0.5, 3.0]]
MILLIMETRES = [[1000, 2500, 0], [4250, 500, 3000]]


def _rows(values: list[list], fmt: str, pad: bytes = b"") -> bytes:
    """Pack each row with ``struct`` format ``fmt`` ('<f', '>H', ...) and append ``pad``."""
    return b"".join(struct.pack(fmt[0] + fmt[1] * len(row), *row) + pad for row in values)


def _expected_metres() -> np.ndarray:
    out = np.array(METRES, np.float32)
    out[out == 0] = np.nan
    return out


@pytest.mark.parametrize("fmt,bigendian", [("<f", False), (">f", True)])
def test_32fc1_either_endianness(fmt, bigendian):
    data = _rows([[v if v else float("nan") for v in row] for row in METRES], fmt)
    got = decode_depth("32FC1", 2, 3, 12, bigendian, data)
    np.testing.assert_array_equal(got, _expected_metres())
    assert got.dtype == np.float32


@pytest.mark.parametrize("encoding", ["16UC1", "mono16"])
@pytest.mark.parametrize("fmt,bigendian", [("<H", False), (">H", True)])
def test_millimetre_encodings_either_endianness(encoding, fmt, bigendian):
    got = decode_depth(encoding, 2, 3, 6, bigendian, _rows(MILLIMETRES, fmt))
    np.testing.assert_allclose(got, _expected_metres(), rtol=0, atol=1e-6)


@pytest.mark.parametrize("encoding,fmt,itemsize", [("32FC1", ">f", 4), ("16UC1", "<H", 2)])
def test_padded_rows_are_cut_at_the_width(encoding, fmt, itemsize):
    values = METRES if encoding == "32FC1" else MILLIMETRES
    pad = bytes([0xAB] * 5)  # garbage that would decode to huge or NaN values
    data = _rows(values, fmt, pad)
    got = decode_depth(encoding, 2, 3, 3 * itemsize + len(pad), fmt[0] == ">", data)
    np.testing.assert_allclose(got, _expected_metres(), rtol=0, atol=1e-6)


def test_inf_and_negative_values_are_invalid():
    data = _rows([[float("inf"), -1.0, 2.0]], "<f")
    got = decode_depth("32FC1", 1, 3, 12, False, data)
    assert np.isnan(got[0, :2]).all() and got[0, 2] == 2.0


def test_decoding_leaves_the_message_buffer_alone():
    values = np.array([[np.inf, -1.0, 2.0, np.nan]], "<f4")
    buffer = values.view(np.uint8).ravel().copy()
    got = decode_depth("32FC1", 1, 4, 16, False, buffer)
    assert np.isnan(got[0, [0, 1, 3]]).all() and got[0, 2] == 2.0
    np.testing.assert_array_equal(buffer.view("<f4"), values.ravel())  # inf, -1 still there


def test_sanitize_copies_unless_asked_not_to():
    depth = np.array([[0.0, 1.5, -np.inf]], np.float32)
    assert np.isnan(sanitize_depth(depth)[0, [0, 2]]).all() and depth[0, 0] == 0.0
    assert sanitize_depth(depth, copy=False) is depth and np.isnan(depth[0, [0, 2]]).all()


def test_numpy_buffer_in_is_the_same_as_bytes():
    data = _rows(MILLIMETRES, "<H")
    as_array = np.frombuffer(data, np.uint8).copy()
    np.testing.assert_array_equal(decode_depth("16UC1", 2, 3, 6, False, as_array),
                                  decode_depth("16UC1", 2, 3, 6, False, data))


@pytest.mark.parametrize("kwargs,says", [
    ({"encoding": "rgb8"}, "unsupported encoding 'rgb8'"),
    ({"height": 0}, "image size must be positive"),
    ({"width": 9000}, "exceeds the 8192 px limit"),
    ({"step": 5}, "step 5 is smaller than one row"),
    ({"data": b"\x00" * 11}, "data has 11 bytes, expected step x height = 6 x 2 = 12"),
])
def test_malformed_fields_are_refused_with_the_reason(kwargs, says):
    fields = {"encoding": "16UC1", "height": 2, "width": 3, "step": 6, "is_bigendian": False,
              "data": _rows(MILLIMETRES, "<H"), **kwargs}
    with pytest.raises(DepthDecodeError, match=says.replace("(", r"\(")):
        decode_depth(**fields)


@pytest.mark.parametrize("encoding", ["32FC1", "16UC1"])
def test_encode_then_decode_round_trips(encoding):
    data, step = encode_depth(_expected_metres(), encoding)
    got = decode_depth(encoding, 2, 3, step, False, data)
    np.testing.assert_allclose(got, _expected_metres(), rtol=0, atol=1e-6)

