"""Pose, shape and placement sampling for synthetic data (no ROS).

Poses are built in canonical anatomical axes (x = left, y = up, z = forward; see
body.base) from activity templates (standing, walking, sitting, reaching, crouching,
arms crossed, ...) with random amplitudes and per-joint noise, mirrored at random, clipped
to the joint limits the fitting prior uses, then mapped to the model frame. The same code
serves every backend through the generic joint names.
"""
from __future__ import annotations

import numpy as np
import torch

from smpl_depth_ros.body.base import BodyModel

# Activity templates: generic joint -> canonical axis-angle in degrees. 'ELBOW' entries
# are hinge flexion angles (about the elbow's own flexion axis), handled separately.
TEMPLATES = {
    'stand': {},
    'walk': {'left_hip': (-25, 0, 0), 'right_hip': (20, 0, 0), 'left_knee': (35, 0, 0),
             'right_knee': (10, 0, 0), 'left_shoulder': (20, 0, 0),
             'right_shoulder': (-25, 0, 0), 'ELBOW': (20, 30)},
    'sit': {'left_hip': (-90, 0, 8), 'right_hip': (-90, 0, -8), 'left_knee': (90, 0, 0),
            'right_knee': (90, 0, 0), 'spine1': (10, 0, 0), 'ELBOW': (40, 40)},
    'reach_up': {'left_shoulder': (-20, 0, 110), 'ELBOW': (10, 30),
                 'spine2': (0, 0, -10)},
    'reach_forward': {'left_shoulder': (-85, 0, 20), 'right_shoulder': (-40, 0, 0),
                      'spine1': (15, 0, 0), 'ELBOW': (5, 60)},
    'crouch': {'left_hip': (-110, 0, 15), 'right_hip': (-110, 0, -15), 'left_knee': (125, 0, 0),
               'right_knee': (125, 0, 0), 'left_ankle': (-25, 0, 0), 'right_ankle': (-25, 0, 0),
               'spine1': (30, 0, 0), 'spine2': (10, 0, 0), 'ELBOW': (40, 40)},
    'arms_crossed': {'left_shoulder': (-45, 0, -20), 'right_shoulder': (-45, 0, 20),
                     'ELBOW': (115, 115)},
    't_pose': {'left_shoulder': (0, 0, 45), 'right_shoulder': (0, 0, -45)},
    'wave': {'left_shoulder': (-10, 0, 100), 'ELBOW': (90, 10), 'left_wrist': (0, 0, 20)},
    'lunge': {'left_hip': (-60, 0, 5), 'right_hip': (20, 0, -5), 'left_knee': (70, 0, 0),
              'right_knee': (40, 0, 0), 'ELBOW': (20, 20)},
    'bend': {'spine1': (40, 0, 0), 'spine2': (25, 0, 0), 'spine3': (15, 0, 0),
             'left_shoulder': (-40, 0, 0), 'right_shoulder': (-40, 0, 0), 'ELBOW': (20, 20)},
    'twist': {'spine1': (0, 25, 0), 'spine2': (0, 20, 0), 'neck': (0, 25, 0),
              'ELBOW': (30, 30)},
}
TEMPLATE_WEIGHTS = {'stand': 2.0, 'walk': 3.0, 'sit': 1.0, 'reach_up': 1.0,
                    'reach_forward': 1.0, 'crouch': 0.7, 'arms_crossed': 1.0, 't_pose': 0.5,
                    'wave': 1.0, 'lunge': 0.7, 'bend': 0.7, 'twist': 0.8}
_MIRROR_AXES = np.array([1.0, -1.0, -1.0])  # reflection x -> -x of an axis-angle vector


def _mirror_name(n: str) -> str:
    if n.startswith('left_'):
        return 'right_' + n[5:]
    if n.startswith('right_'):
        return 'left_' + n[6:]
    return n


def elbow_axes(body: BodyModel) -> dict[str, np.ndarray]:
    """Canonical flexion axis per elbow: rotating the rest forearm towards +z (forward)."""
    p = body.zero_params(1)
    with torch.no_grad():
        j = (body(**p).joints[0] @ body.canonical_rotation.T).cpu().numpy().astype(np.float64)
    names = list(body.joint_names)
    out = {}
    for side in ('left', 'right'):
        a = j[names.index(f'{side}_wrist')] - j[names.index(f'{side}_elbow')]
        a /= np.linalg.norm(a)
        k = np.cross(a, [0.0, 0.0, 1.0])
        out[f'{side}_elbow'] = k / np.linalg.norm(k)
    return out


class PoseSampler:
    """Draws realistic, limit-respecting poses for one body model.

    Args:
        body: the body model (generic joint names are looked up in it).
        noise_deg: per-joint, per-axis Gaussian noise added to every template.
        head_turn_deg: 0 (default), or the head is also turned: a yaw drawn uniformly in
            +-head_turn_deg added at the neck and again at the head (up to twice that in
            all, within the joint limits), and a head pitch in +-head_turn_deg / 2. The
            templates turn the head little (one twists it 25 deg); people look aside.
            Off, the random stream is the one earlier bags and training runs drew.
    """

    def __init__(self, body: BodyModel, noise_deg: float = 9.0, head_turn_deg: float = 0.0):
        self.body = body
        self.head_turn = np.deg2rad(head_turn_deg)
        self.names = list(body.joint_names[1:])
        self.limits = body.limits_canonical().cpu().numpy().astype(np.float64)  # (P,3,2)
        self.C = body.canonical_rotation.cpu().numpy().astype(np.float64)
        self.elbows = elbow_axes(body)
        self.noise = np.deg2rad(noise_deg)
        self.templates = list(TEMPLATES)
        w = np.array([TEMPLATE_WEIGHTS[t] for t in self.templates])
        self.weights = w / w.sum()

    def template(self, name: str, amplitude: float = 1.0, mirror: bool = False) -> np.ndarray:
        """(P, 3) canonical axis-angle (radians) of a template."""
        out = np.zeros((len(self.names), 3))
        for jn, val in TEMPLATES[name].items():
            if jn == 'ELBOW':
                for side, ang in zip(('left', 'right'), val):
                    key = f'{side}_elbow'
                    if key in self.names:
                        out[self.names.index(key)] = self.elbows[key] * np.deg2rad(ang)
                continue
            if jn in self.names:
                out[self.names.index(jn)] = np.deg2rad(val)
        out *= amplitude
        if mirror:
            m = np.zeros_like(out)
            for i, n in enumerate(self.names):
                j = self.names.index(_mirror_name(n)) if _mirror_name(n) in self.names else i
                m[j] = out[i] * _MIRROR_AXES
            # Elbow hinge axes are mirror images of each other, so the reflection is exact.
            out = m
        return out

    def clip(self, canon: np.ndarray) -> np.ndarray:
        return np.clip(canon, self.limits[..., 0], self.limits[..., 1])

    def to_model(self, canon: np.ndarray) -> np.ndarray:
        """Canonical (..., P, 3) -> model-frame axis-angle (float32)."""
        return (canon @ self.C).astype(np.float32)

    def sample_canonical(self, rng: np.random.Generator) -> np.ndarray:
        t = self.templates[rng.choice(len(self.templates), p=self.weights)]
        amp = rng.uniform(0.3, 1.15)
        pose = self.template(t, amp, mirror=bool(rng.random() < 0.5))
        pose = pose + rng.normal(0, self.noise, pose.shape)
        if self.head_turn > 0:
            yaw = rng.uniform(-self.head_turn, self.head_turn)
            for j in ('neck', 'head'):
                if j in self.names:
                    pose[self.names.index(j), 1] += yaw
            if 'head' in self.names:
                pose[self.names.index('head'), 0] += rng.uniform(-0.5, 0.5) * self.head_turn
        return self.clip(pose)

    def sample(self, rng: np.random.Generator, n: int = 1) -> np.ndarray:
        """(n, P, 3) model-frame axis-angle poses."""
        return self.to_model(np.stack([self.sample_canonical(rng) for _ in range(n)]))

    def sequence(self, rng: np.random.Generator, frames: int, keyframe_every: int = 15):
        """(frames, P, 3) smooth trajectory: cosine-interpolated random key poses."""
        nk = frames // keyframe_every + 2
        keys = np.stack([self.sample_canonical(rng) for _ in range(nk)])
        out = []
        for f in range(frames):
            k, r = divmod(f, keyframe_every)
            s = 0.5 - 0.5 * np.cos(np.pi * r / keyframe_every)
            out.append((1 - s) * keys[k] + s * keys[k + 1])
        return self.to_model(np.stack(out))


def sample_shape(body: BodyModel, rng: np.random.Generator, n: int = 1) -> np.ndarray:
    """(n, S) shapes of adults: anny phenotypes ~ the adult statistics shipped with the
    model (clipped normal per phenotype); SMPL betas ~ N(0, 1) clipped to +-2.5."""
    mean = body.shape_mean.cpu().numpy().astype(np.float64)
    if body.shape_bounds is None:
        return np.clip(rng.normal(0, 1, (n, body.num_shape)), -2.5, 2.5).astype(np.float32)
    std = body.shape_std.cpu().numpy().astype(np.float64)
    s = rng.normal(mean, std, (n, body.num_shape))
    lo, hi = body.shape_bounds
    return np.clip(s, lo + 1e-3, hi - 1e-3).astype(np.float32)


# Camera optical frame (x right, y down, z forward) from canonical (x left... of the
# person, y up, z forward of the person): a person facing the camera, upright.
OPTICAL_FROM_CANONICAL = np.array([[1.0, 0, 0], [0, -1.0, 0], [0, 0, -1.0]])


def _rot(axis: int, ang: float) -> np.ndarray:
    c, s = np.cos(ang), np.sin(ang)
    R = np.eye(3)
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    R[i, i], R[i, j], R[j, i], R[j, j] = c, -s, s, c
    return R


def placement(body: BodyModel, shape: np.ndarray, yaw: float, pitch: float, roll: float,
              root_position: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Global orientation and translation putting the body upright in a camera frame.

    Args:
        shape: (S,) body shape (sets the rest root position).
        yaw: rotation about the person's vertical axis (0 = facing the camera), radians.
        pitch, roll: small tilts (radians) about the person's lateral / forward axes.
        root_position: (3,) where the root joint lands, camera optical frame, metres.

    Returns:
        global_orient (3,) axis-angle and transl (3,), float32, for the body's forward.
    """
    from scipy.spatial.transform import Rotation

    C = body.canonical_rotation.cpu().numpy().astype(np.float64)
    R = OPTICAL_FROM_CANONICAL @ _rot(1, yaw) @ _rot(0, pitch) @ _rot(2, roll) @ C
    with torch.no_grad():
        s = torch.as_tensor(shape, dtype=body.dtype, device=body.device)[None]
        zero = torch.zeros(1, body.num_pose_joints, 3, dtype=body.dtype, device=body.device)
        h0 = body(zero, s).joints[0, 0].cpu().numpy()
    t = np.asarray(root_position, np.float64) - h0
    return Rotation.from_matrix(R).as_rotvec().astype(np.float32), t.astype(np.float32)
