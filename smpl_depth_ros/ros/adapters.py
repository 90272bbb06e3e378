"""Thin message <-> array adapters, shared by the node (rclpy) and bag tools (rosbags):
the message factory, headers, images, camera info and diagnostics. Markers are in
`ros.markers`, body parameters and TF in `ros.body_msgs`.

Reading is duck-typed on field names, so every reader accepts an rclpy message or a
rosbags dataclass alike. Every builder takes `msgs`, which picks the message classes:

* ``None`` (default): rclpy's generated classes (``sensor_msgs.msg.Image`` ...);
* a rosbags ``Typestore`` (or ``MsgFactory(typestore)``): rosbags dataclasses, ready for
  ``typestore.serialize_cdr`` and a rosbags ``Writer``.

Conventions: depth arrays are (H, W) float32 metres with 0 for invalid pixels (the
encodings are `depth_codec`'s); vertices and joints are (N, 3) metres in the camera frame
of the input header. Every output copies the header it is given (stamp and frame_id);
stamps convert to and from nanoseconds with `smpl_depth_ros.stamps`.
"""
from __future__ import annotations

import array
import collections
import importlib
import itertools
from dataclasses import dataclass
from typing import Any, Iterable, Mapping, Sequence

import numpy as np

from smpl_depth_ros.depth_codec import (bytes_to_depth, depth_mm_to_bytes, depth_to_bytes,
                                        pack_rows, u8_buffer)
from smpl_depth_ros.stamps import ns_to_stamp
from smpl_depth_ros.types import InputError

# body.parts (for the part colours) pulls in scipy and torch: imported where used, so that
# importing the adapters (and the node module) stays light.

_NUMPY_OF_ROS = {
    'bool': np.bool_, 'byte': np.uint8, 'octet': np.uint8, 'char': np.uint8,
    'int8': np.int8, 'uint8': np.uint8, 'int16': np.int16, 'uint16': np.uint16,
    'int32': np.int32, 'uint32': np.uint32, 'int64': np.int64, 'uint64': np.uint64,
    'float32': np.float32, 'float64': np.float64,
}
_ARRAY_TYPECODE = {np.dtype(np.uint8): 'B', np.dtype(np.float64): 'd',
                   np.dtype(np.float32): 'f', np.dtype(np.int32): 'i'}


# -- message classes -----------------------------------------------------------------
class MsgFactory:
    """Creates messages by type name ('sensor_msgs/msg/Image') for one message system.

    Args:
        typestore: a rosbags ``Typestore`` for rosbags dataclasses, or None for rclpy's
            generated classes.
    """

    def __init__(self, typestore=None):
        self.typestore = typestore
        self.is_rosbags = typestore is not None
        self._classes: dict[str, Any] = {}

    def cls(self, msgtype: str):
        """The class of `msgtype` (gives access to constants such as Marker.TRIANGLE_LIST)."""
        c = self._classes.get(msgtype)
        if c is None:
            if self.is_rosbags:
                c = self.typestore.types[msgtype]
            else:
                pkg, _, name = msgtype.split('/')
                c = getattr(importlib.import_module(f'{pkg}.msg'), name)
            self._classes[msgtype] = c
        return c

    def new(self, msgtype: str, **fields):
        """A message with the given fields; the others hold their defaults."""
        if not self.is_rosbags:
            return self.cls(msgtype)(**fields)
        _, defs = self.typestore.fielddefs[msgtype]
        kw = {}
        for name, spec in defs:
            kw[name] = fields.pop(name) if name in fields else self._default(spec)
        if fields:
            raise TypeError(f'{msgtype} has no field(s) {sorted(fields)}')
        return self.cls(msgtype)(**kw)

    def serialize(self, msg, msgtype: str) -> bytes:
        """CDR bytes of a message (rosbags' serializer or rclpy's)."""
        if self.is_rosbags:
            return bytes(self.typestore.serialize_cdr(msg, msgtype))
        from rclpy.serialization import serialize_message
        return serialize_message(msg)

    def _default(self, spec):
        kind, detail = spec
        kind = int(kind)
        if kind == 1:  # BASE
            t = detail[0]
            if t == 'string' or t == 'wstring':
                return ''
            if t == 'bool':
                return False
            return 0.0 if t.startswith('float') else 0
        if kind == 2:  # NAME
            return self.new(detail)
        sub, n = detail
        if int(sub[0]) == 1 and sub[1][0] in _NUMPY_OF_ROS:
            return np.zeros(n if kind == 3 else 0, dtype=_NUMPY_OF_ROS[sub[1][0]])
        return [self._default(sub) for _ in range(n if kind == 3 else 0)]

    # Field values whose representation differs between the two systems.
    def seq(self, values, dtype) -> Any:
        """A primitive sequence field (uint8[], float64[] ...) from an array or list."""
        a = np.ascontiguousarray(values, dtype=dtype).reshape(-1)
        if self.is_rosbags:
            return a
        out = array.array(_ARRAY_TYPECODE[np.dtype(dtype)])
        out.frombytes(a.tobytes())
        return out

    def points(self, xyz: np.ndarray) -> list:
        """geometry_msgs/Point list from (N, 3)."""
        P = self.cls('geometry_msgs/msg/Point')
        slots = [getattr(P, n, None) for n in ('_x', '_y', '_z', '_check_fields')]
        if self.is_rosbags or any(s is None for s in slots):
            rows = np.asarray(xyz, dtype=np.float64).reshape(-1, 3).tolist()
            if self.is_rosbags:
                return [P(x=x, y=y, z=z) for x, y, z in rows]
            # Not the rosidl-generated layout: the slow way.
            return [P(x=x, y=y, z=z, check_fields=False) for x, y, z in rows]
        # Values come from a float64 array: fill rosidl's slots directly instead of
        # running __init__ and the checked property setters, with map() so that no Python
        # code runs per point (a mesh marker has thousands of points: ~20x faster).
        a = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
        n = len(a)
        out = list(map(P.__new__, itertools.repeat(P, n)))
        for setter, values in zip(slots, (a[:, 0].tolist(), a[:, 1].tolist(),
                                          a[:, 2].tolist(), itertools.repeat(False, n))):
            collections.deque(map(setter.__set__, out, values), maxlen=0)
        return out


_RCLPY = None


def as_factory(msgs=None) -> MsgFactory:
    """`msgs` as a MsgFactory: None -> rclpy, a rosbags Typestore -> rosbags."""
    global _RCLPY
    if isinstance(msgs, MsgFactory):
        return msgs
    if msgs is None:
        if _RCLPY is None:
            _RCLPY = MsgFactory()
        return _RCLPY
    if hasattr(msgs, 'fielddefs') and hasattr(msgs, 'types'):
        return MsgFactory(msgs)
    raise TypeError(f'msgs must be None, a MsgFactory or a rosbags Typestore, got {msgs!r}')


def rosbags_factory(typestore=None) -> MsgFactory:
    """A factory of rosbags dataclasses (Jazzy typestore by default)."""
    if typestore is None:
        from rosbags.typesys import Stores, get_typestore
        typestore = get_typestore(Stores.ROS2_JAZZY)
    return MsgFactory(typestore)


# -- headers ---------------------------------------------------------------------------
def make_header(header=None, msgs=None, *, stamp_ns: int | None = None,
                frame_id: str | None = None):
    """std_msgs/Header of the factory's system, copied from any header (duck-typed).

    Args:
        header: a Header of either system, or None.
        stamp_ns, frame_id: override (or, without `header`, set) the fields.
    """
    f = as_factory(msgs)
    if stamp_ns is None:
        sec, nsec = (int(header.stamp.sec), int(header.stamp.nanosec)) if header else (0, 0)
    else:
        sec, nsec = ns_to_stamp(stamp_ns)
    if frame_id is None:
        frame_id = str(header.frame_id) if header is not None else ''
    stamp = f.new('builtin_interfaces/msg/Time', sec=sec, nanosec=nsec)
    return f.new('std_msgs/msg/Header', stamp=stamp, frame_id=frame_id)


# -- images ----------------------------------------------------------------------------
def image_to_depth(msg, max_pixels: int | None = None) -> np.ndarray:
    """sensor_msgs/Image (16UC1 millimetres or 32FC1 metres) -> (H, W) float32 metres.

    Any row `step` (padding) and either byte order (`is_bigendian`) are handled.
    Invalid pixels (0, NaN, inf, negative) come out as 0.

    Args:
        msg: sensor_msgs/Image, rclpy or rosbags.
        max_pixels: optional limit on width x height, checked before any conversion.

    Raises:
        InputError: 'encoding' for another encoding, 'size_mismatch' for inconsistent
            width/height/step/data, 'too_large' above `max_pixels`.
    """
    return bytes_to_depth(msg.data, msg.width, msg.height, msg.encoding, int(msg.step),
                          bool(msg.is_bigendian), max_pixels=max_pixels)


def depth_to_image_msg(depth: np.ndarray, header=None, encoding: str = '32FC1', msgs=None, *,
                       step: int | None = None, bigendian: bool = False):
    """(H, W) metres -> sensor_msgs/Image.

    Args:
        depth: (H, W) float metres; 0/NaN invalid.
        encoding: '32FC1' (metres, the values as given: 0 and NaN kept) or '16UC1'
            (millimetres, invalid -> 0, clipped to 65,535).
        step: bytes per row (>= W x bytes per pixel); extra bytes are zero padding.
        bigendian: write big-endian samples (is_bigendian = 1).
    """
    f = as_factory(msgs)
    depth = np.asarray(depth)
    data, step = depth_to_bytes(depth, encoding, nan_invalid=False, step=step,
                                bigendian=bigendian)
    return _image(f, header, depth.shape, encoding, data, step, bigendian)


def depth_mm_to_image_msg(depth_mm: np.ndarray, header=None, msgs=None):
    """(H, W) uint16 millimetres (0 invalid), as sensors give them -> 16UC1 Image, no
    conversion through metres."""
    data, step = depth_mm_to_bytes(depth_mm)
    return _image(as_factory(msgs), header, np.shape(depth_mm), '16UC1', data, step)


def _image(f: MsgFactory, header, shape, encoding: str, data: np.ndarray, step: int,
           bigendian: bool = False):
    return f.new('sensor_msgs/msg/Image', header=make_header(header, f), height=shape[0],
                 width=shape[1], encoding=encoding, is_bigendian=int(bool(bigendian)),
                 step=step, data=f.seq(data, np.uint8))


def _image_msg(pix: np.ndarray, header, encoding: str, f: MsgFactory):
    rows, step = pack_rows(pix)
    return _image(f, header, pix.shape, encoding, rows, step)


def labels_to_image_msgs(labels: np.ndarray, header=None, msgs=None):
    """(H, W) part ids -> (rgb8 colour Image, mono8 class-id Image), both at (H, W)."""
    from smpl_depth_ros.body.parts import labels_to_rgb

    f = as_factory(msgs)
    labels = np.asarray(labels)
    if labels.ndim != 2:
        raise ValueError(f'labels must be (H, W), got {labels.shape}')
    ids = labels.astype(np.uint8, copy=False)
    return (_image_msg(labels_to_rgb(ids), header, 'rgb8', f),
            _image_msg(ids, header, 'mono8', f))


def body_index_image(persons, shape, header=None, msgs=None):
    """mono8 body index image (the Azure Kinect convention): each person's pixels hold
    its position in the frame's `~/bodies/tracked` list (0, 1, ...), 255 elsewhere."""
    idx = np.full(tuple(shape), 255, np.uint8)
    for k, p in enumerate(persons[:255]):
        if p.mask is not None and p.mask.shape == idx.shape:
            idx[p.mask & (idx == 255)] = k
    return _image_msg(idx, header, 'mono8', as_factory(msgs))


def image_to_array(msg) -> np.ndarray:
    """rgb8 / mono8 / 16UC1 / 32FC1 Image -> (H, W[, C]) array of the raw values."""
    enc = str(msg.encoding)
    dtypes = {'rgb8': (np.uint8, 3), 'bgr8': (np.uint8, 3), 'mono8': (np.uint8, 1),
              '8UC1': (np.uint8, 1), '16UC1': (np.uint16, 1), 'mono16': (np.uint16, 1),
              '32FC1': (np.float32, 1)}
    if enc not in dtypes:
        raise InputError('encoding', f"image encoding '{enc}' is not supported")
    base, c = dtypes[enc]
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    dt = np.dtype(base).newbyteorder('>' if msg.is_bigendian else '<')
    buf = u8_buffer(msg.data)
    bpp = dt.itemsize * c
    if h * w == 0 or step < w * bpp or buf.size < step * (h - 1) + w * bpp:
        raise InputError('size_mismatch', f'{enc} image {w}x{h} step {step}: '
                         f'{buf.size} bytes of data')
    shape, strides = ((h, w), (step, bpp)) if c == 1 else ((h, w, c), (step, bpp, dt.itemsize))
    return np.ndarray(shape=shape, dtype=dt, buffer=buf, strides=strides).astype(base)


# -- camera info -----------------------------------------------------------------------
def camera_info_to_K(msg) -> tuple[np.ndarray, np.ndarray, tuple[int, int]]:
    """sensor_msgs/CameraInfo -> (K (3, 3) float64, D (n,) float64, (width, height)).

    Raises:
        InputError: 'bad_intrinsics' when K is all zeros (an uncalibrated camera),
            non-finite, has non-positive focal lengths or a last row other than
            [0, 0, 1]; the message shows the values as given.
    """
    k = getattr(msg, 'k', None)
    if k is None:
        k = getattr(msg, 'K')
    K = np.asarray(k, dtype=np.float64).reshape(-1)
    if K.size != 9:
        raise InputError('bad_intrinsics', f'camera_info K has {K.size} values, expected 9')
    K = K.reshape(3, 3)
    if not np.any(K):
        raise InputError('bad_intrinsics', 'camera_info K is all zeros (uncalibrated '
                         'camera?): cannot back-project depth')
    if not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0 or \
            not np.allclose(K[2], (0.0, 0.0, 1.0), atol=1e-6):
        raise InputError('bad_intrinsics', 'camera_info K is invalid (finite, fx, fy > 0 and '
                         f'a last row [0, 0, 1] needed): {K.reshape(-1).tolist()}')
    d = getattr(msg, 'd', None)
    if d is None:
        d = getattr(msg, 'D', ())
    D = np.asarray(d, dtype=np.float64).reshape(-1)
    return K, D, (int(msg.width), int(msg.height))


@dataclass(frozen=True)
class CameraIntrinsics:
    """A camera_info as the pipeline takes it (`camera_info_intrinsics`).

    Attributes:
        K: (3, 3) the raw image's intrinsics; P: (3, 3) the rectified image's (P's left
        block; K when P is unset); model, D: the lens (distortion_model, D);
        size: (width, height), (0, 0) when unset.
    """

    K: np.ndarray
    P: np.ndarray
    model: str
    D: np.ndarray
    size: tuple[int, int]

    def lens(self, depth_topic: str):
        """The `rectify.Lens` to give the pipeline with the images of `depth_topic` (its
        name may say rectified), None for a camera without distortion."""
        from smpl_depth_ros.rectify import Lens, named_rectified
        lens = Lens(self.model, self.D, self.P, named_rectified(depth_topic))
        return lens if lens.distorted else None


def camera_info_intrinsics(msg) -> CameraIntrinsics:
    """sensor_msgs/CameraInfo -> CameraIntrinsics (K checked as `camera_info_to_K`)."""
    K, D, size = camera_info_to_K(msg)
    p = getattr(msg, 'p', None)
    if p is None:
        p = getattr(msg, 'P', ())
    P = np.asarray(p, np.float64).reshape(-1)
    P = P.reshape(3, 4)[:, :3] if P.size == 12 else np.zeros((3, 3))
    if not (np.all(np.isfinite(P)) and P[0, 0] > 0 and P[1, 1] > 0
            and np.allclose(P[2], (0.0, 0.0, 1.0), atol=1e-6)):
        P = K
    model = str(getattr(msg, 'distortion_model', '') or '')
    return CameraIntrinsics(K, P, model, D, size)


def camera_info_msg(K: np.ndarray, size: tuple[int, int], header=None, msgs=None,
                    D: Sequence[float] = (), model: str = 'plumb_bob'):
    """sensor_msgs/CameraInfo (R = I, P = [K | 0]; the lens `model` and `D`)."""
    f = as_factory(msgs)
    K = np.asarray(K, np.float64).reshape(3, 3)
    P = np.zeros((3, 4))
    P[:, :3] = K
    w, h = size
    return f.new('sensor_msgs/msg/CameraInfo', header=make_header(header, f), height=int(h),
                 width=int(w), distortion_model=str(model),
                 d=f.seq(np.asarray(D, np.float64), np.float64),
                 k=np.asarray(K.reshape(-1), np.float64), r=np.eye(3).reshape(-1),
                 p=P.reshape(-1))


# -- diagnostics -----------------------------------------------------------------------
OK, WARN, ERROR, STALE = 0, 1, 2, 3


def _fmt(v) -> str:
    if isinstance(v, (bool, np.bool_)):
        return str(bool(v)).lower()
    if isinstance(v, (float, np.floating)):
        return f'{float(v):.4g}'
    return str(v)


def diagnostic_status(name: str, level: int = OK, message: str = '',
                      values: Mapping[str, Any] | None = None, hardware_id: str = '',
                      msgs=None):
    """diagnostic_msgs/DiagnosticStatus; `values` become KeyValue strings."""
    f = as_factory(msgs)
    kvs = [f.new('diagnostic_msgs/msg/KeyValue', key=str(k), value=_fmt(v))
           for k, v in (values or {}).items()]
    return f.new('diagnostic_msgs/msg/DiagnosticStatus', level=bytes([level])
                 if not f.is_rosbags else int(level), name=name, message=message,
                 hardware_id=hardware_id, values=kvs)


def diagnostics(header, statuses: Iterable, msgs=None):
    """diagnostic_msgs/DiagnosticArray from statuses: DiagnosticStatus messages or
    (name, level, message, values) tuples."""
    f = as_factory(msgs)
    out = []
    for s in statuses:
        if isinstance(s, tuple):
            s = diagnostic_status(*s, msgs=f)
        out.append(s)
    return f.new('diagnostic_msgs/msg/DiagnosticArray', header=make_header(header, f),
                 status=out)


def diagnostic_values(status) -> dict[str, str]:
    """KeyValue list of a DiagnosticStatus -> dict."""
    return {str(kv.key): str(kv.value) for kv in status.values}


def diagnostic_level(status) -> int:
    lv = status.level
    return lv[0] if isinstance(lv, (bytes, bytearray)) else int(lv)


__all__ = [
    'MsgFactory', 'as_factory', 'rosbags_factory', 'make_header',
    'image_to_depth', 'depth_to_image_msg', 'depth_mm_to_image_msg', 'labels_to_image_msgs',
    'body_index_image', 'image_to_array', 'camera_info_to_K', 'camera_info_msg',
    'diagnostic_status', 'diagnostics', 'diagnostic_values', 'diagnostic_level',
    'OK', 'WARN', 'ERROR', 'STALE',
]
