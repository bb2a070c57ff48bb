"""Depth decoding and normalisation: every depth image becomes float32 metres, NaN = invalid.

REP 118: ``32FC1`` holds metres with NaN for no return; ``16UC1`` holds millimetres with 0 for
no return. Rows may be padded (``step`` > width * bytes per pixel) and data may be big-endian.
The node, the bag tools, training and evaluation all go through these functions.
"""

from __future__ import annotations

import numpy as np

# encoding -> (numpy little-endian dtype, scale to metres)
SUPPORTED_ENCODINGS: dict[str, tuple[str, float]] = {
    "32FC1": ("<f4", 1.0),
    "16UC1": ("<u2", 1e-3),
    "mono16": ("<u2", 1e-3),  # some drivers label millimetre depth mono16
}
# Refuse absurd sizes before allocating anything (a 16k x 16k float image is 1 GiB).
MAX_SIDE = 8192


class DepthDecodeError(ValueError):
    """A depth message that cannot be turned into a depth image; the text says why."""


def sanitize_depth(depth: np.ndarray, *, copy: bool = True) -> np.ndarray:
    """float32 metres with NaN wherever the value is not a usable range (NaN, inf, <= 0).

    ``copy=False`` sanitises a float32 array in place (for a caller's own fresh array, such
    as ``decode_depth``'s: one full-frame pass fewer per frame on the robot)."""
    arr = np.asarray(depth)
    if arr.ndim != 2:
        raise DepthDecodeError(f"depth must be a 2-D array (H x W), got shape {arr.shape}")
    if not (np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)):
        raise DepthDecodeError(f"depth must be a numeric array, got dtype {arr.dtype}")
    out = arr.astype(np.float32, copy=False)  # converted first: a value float32 cannot hold
    with np.errstate(invalid="ignore"):       # (1e-50, 1e300) becomes 0 or inf, then invalid
        usable = out > 0
        usable &= out < np.inf                # NaN fails both comparisons
    if copy:   # one pass that writes the copy, cheaper than a copy and a masked write
        return np.where(usable, out, np.float32(np.nan))
    np.copyto(out, np.float32(np.nan), where=~usable)
    return out


def decode_depth(encoding: str, height: int, width: int, step: int, is_bigendian: bool,
                 data: bytes | bytearray | memoryview | np.ndarray) -> np.ndarray:
    """Raw sensor_msgs/Image fields -> float32 metres (H x W), NaN invalid.

    Raises DepthDecodeError naming the field and the expected value on malformed input.
    """
    if encoding not in SUPPORTED_ENCODINGS:
        raise DepthDecodeError(
            f"unsupported encoding '{encoding}': expected one of {sorted(SUPPORTED_ENCODINGS)}")
    if height <= 0 or width <= 0:
        raise DepthDecodeError(f"image size must be positive, got height={height} width={width}")
    if height > MAX_SIDE or width > MAX_SIDE:
        raise DepthDecodeError(
            f"image size {width} x {height} exceeds the {MAX_SIDE} px limit per side")
    dtype_str, scale = SUPPORTED_ENCODINGS[encoding]
    dtype = np.dtype(dtype_str)
    if is_bigendian:
        dtype = dtype.newbyteorder(">")
    row_bytes = width * dtype.itemsize
    if step < row_bytes:
        raise DepthDecodeError(
            f"step {step} is smaller than one row ({width} px x {dtype.itemsize} B = {row_bytes})")
    buf = np.frombuffer(data, dtype=np.uint8) if not isinstance(data, np.ndarray) \
        else data.view(np.uint8).ravel()
    if buf.size != step * height:
        raise DepthDecodeError(
            f"data has {buf.size} bytes, expected step x height = {step} x {height} = "
            f"{step * height}")
    rows = buf.reshape(height, step)[:, :row_bytes]
    values = np.ascontiguousarray(rows).view(dtype).reshape(height, width)
    metres = values.astype(np.float32) * np.float32(scale) if scale != 1.0 \
        else values.astype(np.float32)
    return sanitize_depth(metres, copy=False)  # metres is ours: no second copy


def encode_depth(depth_m: np.ndarray, encoding: str = "32FC1") -> tuple[bytes, int]:
    """float metres -> (little-endian bytes, step) for a sensor_msgs/Image; NaN -> invalid."""
    depth = np.asarray(depth_m, dtype=np.float32)
    if encoding == "32FC1":
        data = depth.astype("<f4")
    elif encoding in ("16UC1", "mono16"):
        with np.errstate(invalid="ignore"):
            mm = np.where(np.isfinite(depth) & (depth > 0), np.rint(depth * 1000.0), 0)
        data = np.clip(mm, 0, 65535).astype("<u2")
    else:
        raise DepthDecodeError(f"cannot encode depth as '{encoding}'")
    return data.tobytes(), depth.shape[1] * data.dtype.itemsize
