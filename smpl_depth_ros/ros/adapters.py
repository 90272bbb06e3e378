"""Thin message <-> array adapters, shared by the node (rclpy) and bag tools (rosbags).

Reading is duck-typed on field names, so every reader accepts an rclpy message or a
rosbags dataclass alike. Every builder takes `msgs`, which picks the message classes:

* ``None`` (default): rclpy's generated classes (``sensor_msgs.msg.Image`` ...);
* a rosbags ``Typestore`` (or ``MsgFactory(typestore)``): rosbags dataclasses, ready for
  ``typestore.serialize_cdr`` and a rosbags ``Writer``.

Conventions: depth arrays are (H, W) float32 metres with 0 for invalid pixels; vertices
and joints are (N, 3) metres in the camera frame of the input header. Every output copies
the header it is given (stamp and frame_id).

The `~/smpl_params` schema (sensor_msgs/JointState used as a self-describing parameter
vector, values in ``position``)::

    transl.x  transl.y  transl.z                      metres, camera frame
    global_orient.rx  .ry  .rz                         axis-angle, radians
    <joint>.rx  <joint>.ry  <joint>.rz                 for body.joint_names[1:]
    shape.<name>                                       for body.shape_names

`joint_state_to_params` decodes it back into arrays.

The `~/bodies/params` schema: the same names for every person of the frame, each
prefixed with its track ID (``body_<id>/transl.x`` ...), plus one
``body_<id>/<joint>.confidence`` per fitted joint (body.joint_names, root first; 0-1, how
well observed pixels and the fit support it). `joint_state_to_bodies` decodes it into
{id: params}. `~/bodies/tracked` (JointState): ``name`` = the ``body_<id>`` tracked in the
frame, ``position`` = each one's mean joint confidence.
"""
from __future__ import annotations

import array
import collections
import importlib
import itertools
import struct
from typing import Any, Iterable, Mapping, Sequence

import numpy as np

from smpl_depth_ros.types import InputError

# body.parts (for the part colours) pulls in scipy and torch: imported where used, so that
# importing the adapters (and the node module) stays light.

DEPTH_ENCODINGS = {'16UC1': (np.uint16, 0.001), '32FC1': (np.float32, 1.0)}

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


# -- headers and time ------------------------------------------------------------------
def stamp_to_ns(stamp) -> int:
    """builtin_interfaces/Time (either system) -> integer nanoseconds."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def cdr_stamp_ns(data: bytes) -> int:
    """header.stamp (ns) of a serialized message whose first field is a std_msgs/Header
    (Image, Marker, ...), read from its CDR bytes without deserializing the rest: what a
    raw subscription needs to time a 2 MB mesh without building 82k Point objects."""
    if len(data) < 12 or data[1] not in (0, 1):
        raise ValueError('not a CDR-serialized message')
    sec, nsec = struct.unpack_from('<iI' if data[1] == 1 else '>iI', data, 4)
    return sec * 1_000_000_000 + nsec


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
        sec, nsec = divmod(int(stamp_ns), 1_000_000_000)
    if frame_id is None:
        frame_id = str(header.frame_id) if header is not None else ''
    stamp = f.new('builtin_interfaces/msg/Time', sec=sec, nanosec=nsec)
    return f.new('std_msgs/msg/Header', stamp=stamp, frame_id=frame_id)


def _duration(seconds: float, f: MsgFactory):
    sec = int(np.floor(seconds))
    return f.new('builtin_interfaces/msg/Duration', sec=sec,
                 nanosec=int(round((seconds - sec) * 1e9)) % 1_000_000_000)


# -- images ----------------------------------------------------------------------------
def _u8_buffer(data) -> np.ndarray:
    if isinstance(data, np.ndarray):  # any layout: a user's sliced array is strided
        return np.ascontiguousarray(data).reshape(-1).view(np.uint8) \
            if data.dtype.itemsize == 1 else np.frombuffer(data.tobytes(), np.uint8)
    try:
        return np.frombuffer(data, dtype=np.uint8)
    except TypeError:
        return np.asarray(data, dtype=np.uint8)


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
    enc = str(msg.encoding)
    if enc not in DEPTH_ENCODINGS:
        raise InputError('encoding', f"depth image encoding '{enc}' is not supported: "
                         "expected '16UC1' (millimetres) or '32FC1' (metres)")
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    if h <= 0 or w <= 0:
        raise InputError('size_mismatch', f'depth image is empty ({w}x{h})')
    if max_pixels is not None and h * w > max_pixels:
        raise InputError('too_large', f'depth image {w}x{h} has {h * w} pixels, '
                         f'more than the limit of {max_pixels}')
    base, scale = DEPTH_ENCODINGS[enc]
    bpp = np.dtype(base).itemsize
    if step < w * bpp:
        raise InputError('size_mismatch', f'depth image step {step} is smaller than '
                         f'width {w} x {bpp} bytes')
    buf = _u8_buffer(msg.data)
    need = step * (h - 1) + w * bpp
    if buf.size < need:
        raise InputError('size_mismatch', f'depth image {w}x{h} {enc} step {step} needs '
                         f'at least {need} bytes of data ({h - 1} rows of {step} and a last '
                         f'row of {w * bpp}), got {buf.size}')
    dt = np.dtype(base).newbyteorder('>' if msg.is_bigendian else '<')
    view = np.ndarray(shape=(h, w), dtype=dt, buffer=buf, strides=(step, bpp))
    depth = view.astype(np.float32)
    if scale != 1.0:
        depth *= np.float32(scale)
    else:
        bad = ~np.isfinite(depth)
        if bad.any():
            depth[bad] = 0.0
    depth[depth < 0] = 0.0
    return depth


def depth_to_image_msg(depth: np.ndarray, header=None, encoding: str = '32FC1', msgs=None, *,
                       step: int | None = None, bigendian: bool = False):
    """(H, W) metres -> sensor_msgs/Image.

    Args:
        depth: (H, W) float metres; 0/NaN invalid.
        encoding: '32FC1' (metres, NaN kept) or '16UC1' (millimetres, invalid -> 0,
            clipped to 65,535).
        step: bytes per row (>= W x bytes per pixel); extra bytes are zero padding.
        bigendian: write big-endian samples (is_bigendian = 1).
    """
    f = as_factory(msgs)
    depth = np.asarray(depth)
    if depth.ndim != 2:
        raise ValueError(f'depth must be (H, W), got {depth.shape}')
    if encoding not in DEPTH_ENCODINGS:
        raise ValueError(f'encoding must be one of {sorted(DEPTH_ENCODINGS)}, got {encoding!r}')
    h, w = depth.shape
    base, scale = DEPTH_ENCODINGS[encoding]
    if encoding == '16UC1':
        mm = np.nan_to_num(np.asarray(depth, np.float64) / scale, nan=0.0, posinf=0.0,
                           neginf=0.0)
        pix = np.clip(np.round(mm), 0, 65535).astype(np.uint16)
    else:
        pix = np.asarray(depth, np.float32)
    return _image_msg(pix, header, encoding, f, step=step, bigendian=bigendian)


def depth_mm_to_image_msg(depth_mm: np.ndarray, header=None, msgs=None):
    """(H, W) uint16 millimetres (0 invalid), as sensors give them -> 16UC1 Image, no
    conversion through metres."""
    depth_mm = np.asarray(depth_mm)
    if depth_mm.ndim != 2 or depth_mm.dtype != np.uint16:
        raise ValueError(f'depth_mm must be (H, W) uint16, got {depth_mm.shape} '
                         f'{depth_mm.dtype}')
    return _image_msg(depth_mm, header, '16UC1', as_factory(msgs))


def _image_msg(pix: np.ndarray, header, encoding: str, f: MsgFactory, *,
               step: int | None = None, bigendian: bool = False):
    h, w = pix.shape[:2]
    pix = pix.astype(pix.dtype.newbyteorder('>' if bigendian else '<'), copy=False)
    row = np.ascontiguousarray(pix).view(np.uint8).reshape(h, -1)
    step = row.shape[1] if step is None else int(step)
    if step < row.shape[1]:
        raise ValueError(f'step {step} is smaller than a row ({row.shape[1]} bytes)')
    if step > row.shape[1]:
        padded = np.zeros((h, step), np.uint8)
        padded[:, :row.shape[1]] = row
        row = padded
    return f.new('sensor_msgs/msg/Image', header=make_header(header, f), height=h, width=w,
                 encoding=encoding, is_bigendian=int(bool(bigendian)), step=step,
                 data=f.seq(row, np.uint8))


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
    buf = _u8_buffer(msg.data)
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


def camera_info_msg(K: np.ndarray, size: tuple[int, int], header=None, msgs=None,
                    D: Sequence[float] = ()):
    """sensor_msgs/CameraInfo for a pinhole camera (plumb_bob, R = I, P = [K | 0])."""
    f = as_factory(msgs)
    K = np.asarray(K, np.float64).reshape(3, 3)
    P = np.zeros((3, 4))
    P[:, :3] = K
    w, h = size
    return f.new('sensor_msgs/msg/CameraInfo', header=make_header(header, f), height=int(h),
                 width=int(w), distortion_model='plumb_bob',
                 d=f.seq(np.asarray(D, np.float64), np.float64),
                 k=np.asarray(K.reshape(-1), np.float64), r=np.eye(3).reshape(-1),
                 p=P.reshape(-1))


# -- markers ---------------------------------------------------------------------------
def _color(rgba, f: MsgFactory):
    r, g, b, a = (list(rgba) + [1.0])[:4] if len(rgba) == 3 else rgba
    return f.new('std_msgs/msg/ColorRGBA', r=float(r), g=float(g), b=float(b), a=float(a))


def _identity_pose(f: MsgFactory):
    return f.new('geometry_msgs/msg/Pose',
                 position=f.new('geometry_msgs/msg/Point', x=0.0, y=0.0, z=0.0),
                 orientation=f.new('geometry_msgs/msg/Quaternion', x=0.0, y=0.0, z=0.0,
                                   w=1.0))


def _marker(f: MsgFactory, header, ns: str, id: int, type_name: str, color, lifetime_s,
            scale=(1.0, 1.0, 1.0), points=None):
    M = f.cls('visualization_msgs/msg/Marker')
    return f.new('visualization_msgs/msg/Marker', header=make_header(header, f), ns=ns,
                 id=int(id), type=int(getattr(M, type_name)), action=int(M.ADD),
                 pose=_identity_pose(f),
                 scale=f.new('geometry_msgs/msg/Vector3', x=float(scale[0]),
                             y=float(scale[1]), z=float(scale[2])),
                 color=_color(color, f), lifetime=_duration(max(0.0, lifetime_s), f),
                 frame_locked=False, points=points if points is not None else [])


def decimate_faces(vertices: np.ndarray, faces: np.ndarray, target: int) -> np.ndarray:
    """Deterministic mesh decimation by vertex clustering, keeping original vertex ids.

    Vertices are snapped to a cubic grid whose cell size is searched so that at most
    `target` triangles survive; each cell is represented by its original vertex nearest
    the cell mean, so the returned faces index the original vertices and can be applied
    to any posed copy of the same topology.

    Args:
        vertices: (V, 3) a reference pose (e.g. the rest mesh).
        faces: (F, 3) int triangles.
        target: the most triangles to keep (>= 1).

    Returns:
        (F', 3) int64 faces into `vertices`, F' <= target (F' = F when target >= F).
    """
    faces = np.asarray(faces, np.int64)
    if target >= len(faces):
        return faces
    if target < 1:
        raise ValueError(f'target must be >= 1, got {target}')
    v = np.asarray(vertices, np.float64)
    lo = v.min(0)
    extent = float(np.ptp(v, axis=0).max()) or 1.0

    def cluster(cell: float) -> np.ndarray:
        keys = np.floor((v - lo) / cell).astype(np.int64)
        _, inv = np.unique(keys, axis=0, return_inverse=True)
        inv = inv.reshape(-1)
        n = inv.max() + 1
        mean = np.zeros((n, 3))
        np.add.at(mean, inv, v)
        mean /= np.bincount(inv, minlength=n)[:, None]
        d = np.linalg.norm(v - mean[inv], axis=1)
        order = np.lexsort((np.arange(len(v)), d, inv))  # per cell: nearest, then lowest id
        first = np.ones(len(order), bool)
        first[1:] = inv[order][1:] != inv[order][:-1]
        rep = np.empty(n, np.int64)
        rep[inv[order][first]] = order[first]
        nf = rep[inv[faces]]
        keep = (nf[:, 0] != nf[:, 1]) & (nf[:, 1] != nf[:, 2]) & (nf[:, 0] != nf[:, 2])
        nf = nf[keep]
        _, idx = np.unique(np.sort(nf, axis=1), axis=0, return_index=True)
        return nf[np.sort(idx)]

    lo_c, hi_c = extent * 1e-4, extent
    best = cluster(hi_c)
    for _ in range(24):
        c = np.sqrt(lo_c * hi_c)
        nf = cluster(c)
        if len(nf) > target:
            lo_c = c
        else:
            best, hi_c = nf, c
        if hi_c / lo_c < 1.01:
            break
    if len(best) == 0:  # a target too small for any triangle: keep a deterministic subset
        best = faces[np.linspace(0, len(faces) - 1, target).astype(np.int64)]
    return best


_decimate = decimate_faces  # mesh_marker's argument of the same name shadows it
_DECIMATION_CACHE: dict = {}


def mesh_marker(vertices: np.ndarray, faces: np.ndarray, header=None, ns: str = 'body_mesh',
                id: int = 0, color=(0.85, 0.65, 0.45, 0.85), lifetime_s: float = 0.5,
                decimate_faces: int | None = None, msgs=None):
    """visualization_msgs/Marker TRIANGLE_LIST of a mesh (3 points per triangle).

    Args:
        vertices: (V, 3) metres, in header.frame_id.
        faces: (F, 3) int triangles.
        color: RGBA in [0, 1] (one colour for the whole mesh).
        lifetime_s: marker lifetime (0 = forever).
        decimate_faces: optional most triangles to send; the decimation (see
            `decimate_faces`) is computed once per (faces, target) from the first
            vertices given and cached.
    """
    f = as_factory(msgs)
    vertices = np.asarray(vertices, np.float64)
    faces = np.asarray(faces)
    if vertices.ndim != 2 or vertices.shape[1] != 3:
        raise ValueError(f'vertices must be (V, 3), got {vertices.shape}')
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f'faces must be (F, 3), got {faces.shape}')
    if decimate_faces is not None and decimate_faces < len(faces):
        key = (faces.shape, hash(faces.tobytes()), int(decimate_faces))
        dec = _DECIMATION_CACHE.get(key)
        if dec is None:
            if len(_DECIMATION_CACHE) > 16:
                _DECIMATION_CACHE.clear()
            dec = _DECIMATION_CACHE[key] = _decimate(vertices, faces, int(decimate_faces))
        faces = dec
    pts = f.points(vertices[faces.reshape(-1)])
    return _marker(f, header, ns, id, 'TRIANGLE_LIST', color, lifetime_s, points=pts)


_SENTINEL = (1.2345678901234567e-300, -7.654321098765432e-301, 3.141592653589793e-299)


def marker_cdr(marker, xyz: np.ndarray, msgs=None) -> bytes:
    """CDR bytes of a visualization_msgs/Marker (rclpy or rosbags, see `as_factory`) with
    `points` = xyz (N, 3).

    Both serializers visit every Point (rosbags in Python: ~60 ms for a body mesh); here
    the marker is serialised with one sentinel point and the (aligned, little-endian)
    block of N points is spliced in with numpy: identical bytes, a fraction of the time.
    rclpy publishers take the bytes as they are.
    """
    f = as_factory(msgs)
    marker.points = f.points(np.array([_SENTINEL]))
    one = f.serialize(marker, 'visualization_msgs/msg/Marker')
    at = one.find(struct.pack('<3d', *_SENTINEL))
    count = at - 4 if one[at - 4:at] == struct.pack('<I', 1) else at - 8
    if at < 0 or one[count:count + 4] != struct.pack('<I', 1) or one[:2] != b'\x00\x01':
        raise RuntimeError('unexpected Marker CDR layout')
    xyz = np.ascontiguousarray(xyz, dtype='<f8').reshape(-1, 3)
    marker.points = []
    return b''.join((one[:count], struct.pack('<I', len(xyz)), one[count + 4:at],
                     xyz.tobytes(), one[at + 24:]))


def marker_array_cdr(array_msg, blocks: Sequence[np.ndarray], msgs=None) -> bytes:
    """CDR bytes of a visualization_msgs/MarkerArray whose first len(blocks) markers get
    `points` = blocks[k] (N_k, 3), spliced in as `marker_cdr` does (each block changes the
    length by a multiple of 8 bytes, so every later field keeps its alignment)."""
    f = as_factory(msgs)
    marks = [tuple(v * (k + 2) for v in _SENTINEL) for k in range(len(blocks))]
    for m, sent in zip(array_msg.markers, marks):
        m.points = f.points(np.array([sent]))
    data = f.serialize(array_msg, 'visualization_msgs/msg/MarkerArray')
    parts, pos = [], 0
    for sent, xyz in zip(marks, blocks):
        at = data.find(struct.pack('<3d', *sent), pos)
        if at < 0 or data[at - 4:at] != struct.pack('<I', 1):
            raise RuntimeError('unexpected MarkerArray CDR layout')
        xyz = np.ascontiguousarray(xyz, dtype='<f8').reshape(-1, 3)
        parts += [data[pos:at - 4], struct.pack('<I', len(xyz)), xyz.tobytes()]
        pos = at + 24
    parts.append(data[pos:])
    for m in array_msg.markers:
        m.points = []
    return b''.join(parts)


def skeleton_markers(joints: np.ndarray, parents: Sequence[int], header=None,
                     ns: str = 'skeleton', id: int = 0, lifetime_s: float = 0.5,
                     joint_color=(1.0, 0.2, 0.2, 1.0), bone_color=(0.2, 0.6, 1.0, 1.0),
                     joint_diameter: float = 0.04, bone_width: float = 0.015, msgs=None,
                     confidence: np.ndarray | None = None):
    """visualization_msgs/MarkerArray: a SPHERE_LIST of joints (ns '<ns>/joints') and a
    LINE_LIST of bones child-parent (ns '<ns>/bones'), both with marker id `id`.

    Args:
        joints: (J, 3) metres.
        parents: (J,) parent index (-1 for the root).
        confidence: optional (J,) in [0, 1]: each joint's sphere gets alpha
            0.2 + 0.8 confidence (a joint nothing observed is faint).
    """
    f = as_factory(msgs)
    joints = np.asarray(joints, np.float64)
    parents = np.asarray([int(p) for p in np.asarray(parents).reshape(-1)])
    if joints.ndim != 2 or joints.shape[1] != 3 or len(parents) != len(joints):
        raise ValueError(f'joints must be (J, 3) with J = len(parents) = {len(parents)}, '
                         f'got {joints.shape}')
    child = np.flatnonzero(parents >= 0)
    segs = np.stack([joints[child], joints[parents[child]]], 1).reshape(-1, 3)
    d = joint_diameter
    sphere = _marker(f, header, f'{ns}/joints', id, 'SPHERE_LIST', joint_color, lifetime_s,
                     scale=(d, d, d), points=f.points(joints))
    if confidence is not None:
        c = np.clip(np.asarray(confidence, np.float64).reshape(-1), 0, 1)
        r, g, b = joint_color[:3]
        sphere.colors = [_color((r, g, b, 0.2 + 0.8 * float(v)), f) for v in c]
    lines = _marker(f, header, f'{ns}/bones', id, 'LINE_LIST', bone_color, lifetime_s,
                    scale=(bone_width, 0.0, 0.0), points=f.points(segs))
    return f.new('visualization_msgs/msg/MarkerArray', markers=[sphere, lines])


# -- body parameters as JointState -----------------------------------------------------
def _names(values) -> tuple[str, ...]:
    return tuple(str(n) for n in values)


def params_to_joint_state(person, body, header=None, msgs=None):
    """Fitted parameters -> sensor_msgs/JointState (schema in the module docstring).

    Args:
        person: a types.PersonResult, or types.BodyParams (anything with .params or
            with pose/shape/global_orient/transl).
        body: the BodyModel (or anything with joint_names, shape_names).
    """
    f = as_factory(msgs)
    p = getattr(person, 'params', person)
    joints, shapes = _names(body.joint_names[1:]), _names(body.shape_names)
    pose = np.asarray(p.pose, np.float64).reshape(-1, 3)
    shape = np.asarray(p.shape, np.float64).reshape(-1)
    if len(pose) != len(joints):
        raise ValueError(f'pose has {len(pose)} joints, the body model {len(joints)}')
    if len(shape) != len(shapes):
        raise ValueError(f'shape has {len(shape)} values, the body model {len(shapes)}')
    names = ['transl.x', 'transl.y', 'transl.z',
             'global_orient.rx', 'global_orient.ry', 'global_orient.rz']
    names += [f'{j}.{a}' for j in joints for a in ('rx', 'ry', 'rz')]
    names += [f'shape.{s}' for s in shapes]
    values = np.concatenate([np.asarray(p.transl, np.float64).reshape(3),
                             np.asarray(p.global_orient, np.float64).reshape(3),
                             pose.reshape(-1), shape])
    return f.new('sensor_msgs/msg/JointState', header=make_header(header, f), name=names,
                 position=f.seq(values, np.float64))


def bodies_to_joint_state(persons, body, header=None, msgs=None):
    """All persons of a frame -> one `~/bodies/params` JointState (module docstring)."""
    f = as_factory(msgs)
    names, values = [], []
    joints = _names(body.joint_names)
    for p in persons:
        one = params_to_joint_state(p, body, header, msgs=f)
        pre = f'body_{int(p.track_id)}/'
        names += [pre + str(n) for n in one.name]
        values.append(np.asarray(one.position, np.float64))
        conf = getattr(p, 'joint_confidence', None)
        conf = np.zeros(len(joints)) if conf is None else np.asarray(conf, np.float64)
        names += [f'{pre}{j}.confidence' for j in joints]
        values.append(conf.reshape(-1))
    v = np.concatenate(values) if values else np.zeros(0)
    return f.new('sensor_msgs/msg/JointState', header=make_header(header, f), name=names,
                 position=f.seq(v, np.float64))


def joint_state_to_bodies(msg) -> dict[int, dict[str, Any]]:
    """Decode a `~/bodies/params` JointState: {track ID: the `joint_state_to_params`
    dict plus joint_confidence (J,) float32 and confidence_joint_names (J,)}."""
    names = [str(n) for n in msg.name]
    pos = np.asarray(msg.position, np.float64).reshape(-1)
    if len(pos) != len(names):
        raise ValueError(f'JointState has {len(names)} names but {len(pos)} positions')
    groups: dict[int, tuple[list, list]] = {}
    for n, v in zip(names, pos):
        head, sep, rest = n.partition('/')
        if not sep or not head.startswith('body_') or not head[5:].isdigit():
            raise ValueError(f'JointState name {n!r} has no body_<id>/ prefix')
        g = groups.setdefault(int(head[5:]), ([], []))
        g[0].append(rest)
        g[1].append(v)
    out = {}
    for tid, (ns, vs) in groups.items():
        conf = [(n[:-len('.confidence')], v) for n, v in zip(ns, vs) if n.endswith('.confidence')]
        rest = [(n, v) for n, v in zip(ns, vs) if not n.endswith('.confidence')]
        d = joint_state_to_params(_NamedValues([n for n, _ in rest], [v for _, v in rest]))
        d['joint_confidence'] = np.array([v for _, v in conf], np.float32)
        d['confidence_joint_names'] = tuple(n for n, _ in conf)
        out[tid] = d
    return out


class _NamedValues:
    """A JointState-like (name, position) pair."""

    def __init__(self, name, position):
        self.name, self.position = name, position


def tracked_ids_msg(persons, header=None, msgs=None):
    """`~/bodies/tracked`: JointState, name = body_<id> per person, position = its mean
    joint confidence."""
    f = as_factory(msgs)
    conf = [float(np.mean(p.joint_confidence)) if getattr(p, 'joint_confidence', None)
            is not None else 0.0 for p in persons]
    return f.new('sensor_msgs/msg/JointState', header=make_header(header, f),
                 name=[f'body_{int(p.track_id)}' for p in persons],
                 position=f.seq(np.asarray(conf, np.float64), np.float64))


def body_index_image(persons, shape, header=None, msgs=None):
    """mono8 body index image (the Azure Kinect convention): each person's pixels hold
    its position in the frame's `~/bodies/tracked` list (0, 1, ...), 255 elsewhere."""
    idx = np.full(tuple(shape), 255, np.uint8)
    for k, p in enumerate(persons[:255]):
        if p.mask is not None and p.mask.shape == idx.shape:
            idx[p.mask & (idx == 255)] = k
    return _image_msg(idx, header, 'mono8', as_factory(msgs))


def delete_markers(ns_ids: Iterable[tuple[str, int]], header=None, msgs=None) -> list:
    """visualization_msgs/Marker DELETE actions for (ns, id) pairs."""
    f = as_factory(msgs)
    M = f.cls('visualization_msgs/msg/Marker')
    out = []
    for ns, i in ns_ids:
        m = _marker(f, header, ns, i, 'TRIANGLE_LIST', (0, 0, 0, 0), 0.0)
        m.action = int(M.DELETE)
        out.append(m)
    return out


def _transform(f: MsgFactory, header, child: str, R: np.ndarray, t: np.ndarray):
    from scipy.spatial.transform import Rotation
    q = Rotation.from_matrix(np.asarray(R, np.float64)).as_quat()  # x, y, z, w
    return f.new('geometry_msgs/msg/TransformStamped', header=make_header(header, f),
                 child_frame_id=child,
                 transform=f.new('geometry_msgs/msg/Transform',
                                 translation=f.new('geometry_msgs/msg/Vector3',
                                                   x=float(t[0]), y=float(t[1]),
                                                   z=float(t[2])),
                                 rotation=f.new('geometry_msgs/msg/Quaternion',
                                                x=float(q[0]), y=float(q[1]), z=float(q[2]),
                                                w=float(q[3]))))


def body_transforms(track_id: int, rotations: np.ndarray, positions: np.ndarray,
                    parents: Sequence[int], joint_names: Sequence[str], header=None,
                    msgs=None) -> list:
    """geometry_msgs/TransformStamped of one body's TF tree (REP-155 naming): the
    root joint as `body_<id>` parented to the header's frame, every other joint as
    `<joint>_<id>` parented to its parent joint's frame, with the joint's rotation
    (the body model's bone frames) and position."""
    f = as_factory(msgs)
    R = np.asarray(rotations, np.float64)
    x = np.asarray(positions, np.float64)
    parents = [int(p) for p in np.asarray(parents).reshape(-1)]
    name = [f'body_{track_id}'] + [f'{j}_{track_id}' for j in list(joint_names)[1:]]
    out = [_transform(f, header, name[0], R[0], x[0])]
    for j in range(1, len(parents)):
        p = parents[j]
        Rl = R[p].T @ R[j]
        tl = R[p].T @ (x[j] - x[p])
        out.append(_transform(f, make_header(header, f, frame_id=name[p]), name[j], Rl, tl))
    return out


def joint_state_to_params(msg) -> dict[str, Any]:
    """Decode a `~/smpl_params` JointState (either system).

    Returns:
        dict with transl (3,), global_orient (3,), pose (P, 3), shape (S,) float32
        arrays, joint_names (P,) and shape_names (S,) tuples of str.

    Raises:
        ValueError: names and positions disagree, or a triple is incomplete.
    """
    names = [str(n) for n in msg.name]
    pos = np.asarray(msg.position, np.float64).reshape(-1)
    if len(pos) != len(names):
        raise ValueError(f'JointState has {len(names)} names but {len(pos)} positions')
    value = dict(zip(names, pos))
    if len(value) != len(names):
        raise ValueError('JointState names are not unique')

    def triple(prefix: str, axes: Iterable[str]) -> np.ndarray:
        try:
            return np.array([value[f'{prefix}.{a}'] for a in axes], np.float32)
        except KeyError as e:
            raise ValueError(f'JointState lacks {e.args[0]!r}') from None

    joint_names, shape_names = [], []
    for n in names:
        base, _, comp = n.rpartition('.')
        if n.startswith('shape.'):
            shape_names.append(n[len('shape.'):])
        elif not base:
            raise ValueError(f'JointState name {n!r} is not part of the schema')
        elif base in ('transl', 'global_orient'):
            continue
        elif comp == 'rx':
            joint_names.append(base)
        elif comp not in ('ry', 'rz'):
            raise ValueError(f'JointState name {n!r} is not part of the schema')
    rot = ('rx', 'ry', 'rz')
    pose = np.stack([triple(j, rot) for j in joint_names]) if joint_names else \
        np.zeros((0, 3), np.float32)
    return dict(transl=triple('transl', 'xyz'), global_orient=triple('global_orient', rot),
                pose=pose.astype(np.float32),
                shape=np.array([value[f'shape.{s}'] for s in shape_names], np.float32),
                joint_names=tuple(joint_names), shape_names=tuple(shape_names))


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
    'MsgFactory', 'as_factory', 'rosbags_factory', 'stamp_to_ns', 'make_header',
    'image_to_depth', 'depth_to_image_msg', 'labels_to_image_msgs', 'image_to_array',
    'camera_info_to_K', 'camera_info_msg', 'decimate_faces', 'mesh_marker',
    'skeleton_markers', 'params_to_joint_state', 'joint_state_to_params',
    'diagnostic_status', 'diagnostics', 'diagnostic_values', 'diagnostic_level',
    'OK', 'WARN', 'ERROR', 'STALE',
]
