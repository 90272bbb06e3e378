"""Fitted bodies as sensor_msgs/JointState and TF, for rclpy and rosbags alike
(`adapters.as_factory`); every message copies the header it is given (stamp, frame_id).

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

TF (`body_transforms`): one tree per body, REP-155 names (``body_<id>``, ``<joint>_<id>``).
"""
from __future__ import annotations

from typing import Any, Iterable, Sequence

import numpy as np

from smpl_depth_ros.ros.adapters import MsgFactory, as_factory, make_header


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


# -- TF --------------------------------------------------------------------------------
def _transform(f: MsgFactory, header, child: str, q: np.ndarray, t: np.ndarray):
    """One TransformStamped: rotation `q` a quaternion (x, y, z, w), translation `t`."""
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
    from scipy.spatial.transform import Rotation
    f = as_factory(msgs)
    p = np.asarray(parents).reshape(-1).astype(int)
    R = np.asarray(rotations, np.float64)[:len(p)]
    x = np.asarray(positions, np.float64)[:len(p)]
    name = [f'body_{track_id}'] + [f'{j}_{track_id}' for j in list(joint_names)[1:]]
    # Each joint in its parent's frame (the root in the camera's), all at once.
    Rl = np.concatenate([R[:1], R[p[1:]].transpose(0, 2, 1) @ R[1:]])
    tl = np.concatenate([x[:1], np.einsum('nji,nj->ni', R[p[1:]], x[1:] - x[p[1:]])])
    q = Rotation.from_matrix(Rl).as_quat()  # x, y, z, w
    out = [_transform(f, header, name[0], q[0], tl[0])]
    for j in range(1, len(p)):
        out.append(_transform(f, make_header(header, f, frame_id=name[p[j]]), name[j], q[j],
                              tl[j]))
    return out


__all__ = ['params_to_joint_state', 'joint_state_to_params', 'bodies_to_joint_state',
           'joint_state_to_bodies', 'tracked_ids_msg', 'body_transforms']
