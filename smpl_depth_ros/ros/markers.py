"""visualization_msgs Markers of bodies, for rclpy and rosbags alike (`adapters.as_factory`):
mesh TRIANGLE_LISTs (optionally decimated, `decimate_faces`), skeleton SPHERE_/LINE_LISTs,
DELETE actions, and the CDR bytes of mesh markers with their points spliced in as one
numpy block (`marker_cdr`, `marker_array_cdr`).

Vertices and joints are (N, 3) metres in the frame of the header given; every marker
copies that header (stamp and frame_id).
"""
from __future__ import annotations

import struct
from typing import Iterable, Sequence

import numpy as np

from smpl_depth_ros.ros.adapters import MsgFactory, as_factory, make_header


def _duration(seconds: float, f: MsgFactory):
    sec = int(np.floor(seconds))
    return f.new('builtin_interfaces/msg/Duration', sec=sec,
                 nanosec=int(round((seconds - sec) * 1e9)) % 1_000_000_000)


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


__all__ = ['decimate_faces', 'mesh_marker', 'marker_cdr', 'marker_array_cdr',
           'skeleton_markers', 'delete_markers']
