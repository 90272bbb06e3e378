"""Depth images as sensor_msgs/Image fields, without ROS: (H, W) metres <-> (encoding,
step, bytes). The one encoder and decoder of depth pixels, used by the message adapters
(`ros.adapters`, rclpy and rosbags) and the bag tools (`bagio`).

Encodings (REP 118):

* '16UC1': uint16 millimetres, 0 = invalid (the openni / realsense convention). Written
  as round(metres / 1 mm) (half to even) clipped to 0..65,535, every invalid pixel (0,
  NaN, inf, negative) as 0; sensor millimetres go out as they are (`depth_mm_to_bytes`).
* '32FC1': float32 metres. REP 118 marks invalid pixels NaN; the writer says which it
  wants: ``nan_invalid=True`` writes every invalid pixel (0, NaN, inf, negative) as NaN
  (the bags of `bagio`), ``nan_invalid=False`` writes the values as given (0 stays 0,
  NaN stays NaN: the adapters' images).

Layout: samples in either byte order (``is_bigendian``); rows `step` bytes apart, step >=
width x bytes per pixel (the writer pads with zeros; the reader needs no padding after
the last row). Reading either encoding gives (H, W) float32 metres with 0 wherever the
sample is invalid (0, NaN, inf, negative); input it cannot read raises
`types.InputError` (a ValueError) with reason 'encoding', 'size_mismatch' or 'too_large'.
"""
from __future__ import annotations

import numpy as np

from smpl_depth_ros.types import InputError

# Encoding -> (sample dtype, metres per unit).
ENCODINGS = {'16UC1': (np.dtype(np.uint16), 0.001), '32FC1': (np.dtype(np.float32), 1.0)}


def check_encoding(encoding: str) -> None:
    """A writer's check: ValueError unless `encoding` is one of ENCODINGS."""
    if encoding not in ENCODINGS:
        raise ValueError(f'encoding must be one of {sorted(ENCODINGS)}, got {encoding!r}')


# -- writing ---------------------------------------------------------------------------
def pack_rows(pix: np.ndarray, step: int | None = None,
              bigendian: bool = False) -> tuple[np.ndarray, int]:
    """(H, W[, C]) samples of any image -> ((H, step) uint8 rows, step).

    Samples are written in the requested byte order; `step` (default: a packed row)
    must hold a row, the bytes past it are zeros.
    """
    h = pix.shape[0]
    pix = pix.astype(pix.dtype.newbyteorder('>' if bigendian else '<'), copy=False)
    row = np.ascontiguousarray(pix).view(np.uint8).reshape(h, -1)
    step = row.shape[1] if step is None else int(step)
    if step < row.shape[1]:
        raise ValueError(f'step {step} is smaller than a row ({row.shape[1]} bytes)')
    if step > row.shape[1]:
        padded = np.zeros((h, step), np.uint8)
        padded[:, :row.shape[1]] = row
        row = padded
    return row, step


def depth_to_bytes(depth: np.ndarray, encoding: str = '16UC1', *, nan_invalid: bool,
                   step: int | None = None, bigendian: bool = False
                   ) -> tuple[np.ndarray, int]:
    """(H, W) metres -> (data: (H x step,) uint8, step) of an Image in `encoding`.

    Args:
        depth: (H, W) metres; 0, NaN, inf and negative values are invalid.
        encoding: '16UC1' (millimetres, invalid -> 0, clipped to 65,535) or '32FC1'.
        nan_invalid: 32FC1 only: write invalid pixels as NaN (True) or the values as
            given (False).
        step: bytes per row (>= W x bytes per pixel); default packed rows.
        bigendian: big-endian samples (the message's is_bigendian = 1).
    """
    depth = np.asarray(depth)
    if depth.ndim != 2:
        raise ValueError(f'depth must be (H, W), got {depth.shape}')
    check_encoding(encoding)
    if encoding == '16UC1':
        d = np.asarray(depth, np.float64)
        valid = np.isfinite(d) & (d > 0)
        unit = ENCODINGS[encoding][1]
        pix = np.clip(np.rint(np.where(valid, d, 0.0) / unit), 0, 65535).astype(np.uint16)
    elif nan_invalid:
        d = np.asarray(depth, np.float64)
        pix = np.where(np.isfinite(d) & (d > 0), d, np.nan).astype(np.float32)
    else:
        pix = np.asarray(depth, np.float32)
    rows, step = pack_rows(pix, step, bigendian)
    return rows.reshape(-1), step


def depth_mm_to_bytes(depth_mm: np.ndarray) -> tuple[np.ndarray, int]:
    """(H, W) uint16 millimetres (0 invalid), as sensors give them -> (16UC1 data, step),
    little-endian packed rows: no conversion through metres."""
    depth_mm = np.asarray(depth_mm)
    if depth_mm.ndim != 2 or depth_mm.dtype != np.uint16:
        raise ValueError(f'depth_mm must be (H, W) uint16, got {depth_mm.shape} '
                         f'{depth_mm.dtype}')
    rows, step = pack_rows(depth_mm)
    return rows.reshape(-1), step


# -- reading ---------------------------------------------------------------------------
def u8_buffer(data) -> np.ndarray:
    """An Image's data (bytes-like, array.array, list, or a numpy array of any dtype and
    layout) as a flat uint8 array of its bytes, without a copy where possible."""
    if isinstance(data, np.ndarray):  # any layout: a user's sliced array is strided
        return np.ascontiguousarray(data).reshape(-1).view(np.uint8) \
            if data.dtype.itemsize == 1 else np.frombuffer(data.tobytes(), np.uint8)
    try:
        return np.frombuffer(data, dtype=np.uint8)
    except TypeError:
        return np.asarray(data, dtype=np.uint8)


def bytes_to_depth(data, width: int, height: int, encoding: str, step: int | None = None,
                   bigendian: bool = False, *, max_pixels: int | None = None) -> np.ndarray:
    """Image data -> (H, W) float32 metres, 0 where invalid.

    Args:
        data: the message's data (see `u8_buffer`).
        width, height: image size.
        encoding: '16UC1' (millimetres) or '32FC1' (metres).
        step: bytes per row (>= width x bytes per pixel); default packed rows.
        bigendian: the message's is_bigendian.
        max_pixels: optional limit on width x height, checked before any conversion.

    Raises:
        InputError: 'encoding' for another encoding, 'size_mismatch' for an empty image
            or inconsistent width/height/step/data, 'too_large' above `max_pixels`.
    """
    enc = str(encoding)
    if enc not in ENCODINGS:
        raise InputError('encoding', f"depth image encoding '{enc}' is not supported: "
                         "expected '16UC1' (millimetres) or '32FC1' (metres)")
    h, w = int(height), int(width)
    if h <= 0 or w <= 0:
        raise InputError('size_mismatch', f'depth image is empty ({w}x{h})')
    if max_pixels is not None and h * w > max_pixels:
        raise InputError('too_large', f'depth image {w}x{h} has {h * w} pixels, '
                         f'more than the limit of {max_pixels}')
    base, scale = ENCODINGS[enc]
    bpp = base.itemsize
    step = w * bpp if step is None else int(step)
    if step < w * bpp:
        raise InputError('size_mismatch', f'depth image step {step} is smaller than '
                         f'width {w} x {bpp} bytes')
    buf = u8_buffer(data)
    need = step * (h - 1) + w * bpp
    if buf.size < need:
        raise InputError('size_mismatch', f'depth image {w}x{h} {enc} step {step} needs '
                         f'at least {need} bytes of data ({h - 1} rows of {step} and a last '
                         f'row of {w * bpp}), got {buf.size}')
    dt = base.newbyteorder('>' if bigendian else '<')
    view = np.ndarray(shape=(h, w), dtype=dt, buffer=buf, strides=(step, bpp))
    depth = view.astype(np.float32)
    if scale != 1.0:  # uint16 millimetres: finite and >= 0 already
        depth *= np.float32(scale)
    else:
        depth[~((depth > 0) & (depth < np.inf))] = 0.0
    return depth
