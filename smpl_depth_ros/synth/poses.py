"""Pose, shape and placement sampling for synthetic data (no ROS).

Poses are built in canonical anatomical axes (x = left, y = up, z = forward; see
body.base) and mapped to the model frame; the same code serves every backend through the
generic joint names. Two distributions (`PoseSampler(mode=...)`):

* 'templates': activity templates (standing, walking, sitting, reaching, crouching, arms
  crossed, ...) with random amplitudes and per-joint noise, mirrored at random, clipped
  to the joint limits the fitting prior uses;
* 'broad': poses people take beyond those activities - a mixture of the templates, more
  postures (`BROAD_TEMPLATES`: kneeling, deep squats, sitting on the floor, bending to
  the floor, reaching overhead, lifting, kicking, on all fours, lying) with wider noise
  and amplitudes, and poses drawn uniformly within the anatomical joint limits, either
  independently per joint or left/right coupled (elbows and knees as hinges, within
  their flexion range). Postures with a whole-body tilt (on all fours, lying) carry a
  root pitch or roll (`ROOT`, degrees) that the frame placement adds;
* 'seated': people on a chair (`SEATED_TEMPLATES`: upright, leaning forward with the
  forearms on the knees, leaning back, legs apart or stretched out, reaching, arms
  crossed, a phone), with amplitudes that keep them seated; `synth.dataset` puts a chair
  (`synth.render.chair_under`) under them. No network was trained on these: they measure
  a person merged with the furniture they sit on;
* 'mocap': real motion capture retargeted to anny (`data/mocap_poses_anny.npz`, written
  by tools/export_mocap_poses from the demo clips of holosoma-retargeting: climbing, 1,264
  poses, upright, and box lifting, 119, bent over as the person was: the clip's pitch
  and roll of the whole body, `sample_with_root`), a motion drawn first (each as often),
  then one of its poses, mirrored at random, with a little noise. For evaluation on
  motions nobody designed; the other modes are what the networks were trained on.
"""
from __future__ import annotations

import numpy as np
import torch

from smpl_depth_ros.body.base import BodyModel

MODES = ('templates', 'broad', 'seated', 'mocap')

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
# Postures beyond the activities (same conventions; 'ROOT': (pitch, roll) in degrees
# of the whole body, pitch > 0 leaning forward, added to the camera's tilt).
BROAD_TEMPLATES = {
    'kneel': {'left_hip': (-5, 0, 5), 'right_hip': (-5, 0, -5), 'left_knee': (100, 0, 0),
              'right_knee': (100, 0, 0), 'left_ankle': (30, 0, 0), 'right_ankle': (30, 0, 0),
              'ELBOW': (30, 30)},
    'kneel_one': {'left_hip': (-90, 0, 5), 'right_hip': (0, 0, -5), 'left_knee': (90, 0, 0),
                  'right_knee': (95, 0, 0), 'right_ankle': (30, 0, 0), 'spine1': (10, 0, 0),
                  'ELBOW': (40, 20)},
    'squat_deep': {'left_hip': (-125, 0, 25), 'right_hip': (-125, 0, -25),
                   'left_knee': (150, 0, 0), 'right_knee': (150, 0, 0),
                   'left_ankle': (-35, 0, 0), 'right_ankle': (-35, 0, 0),
                   'spine1': (40, 0, 0), 'spine2': (20, 0, 0), 'left_shoulder': (-60, 0, 0),
                   'right_shoulder': (-60, 0, 0), 'ELBOW': (60, 60)},
    'sit_floor': {'left_hip': (-90, 0, 20), 'right_hip': (-90, 0, -20),
                  'left_knee': (20, 0, 0), 'right_knee': (20, 0, 0), 'spine1': (20, 0, 0),
                  'left_shoulder': (-30, 0, 10), 'right_shoulder': (-30, 0, -10),
                  'ELBOW': (30, 30)},
    'sit_cross': {'left_hip': (-80, -35, 40), 'right_hip': (-80, 35, -40),
                  'left_knee': (140, 0, 0), 'right_knee': (140, 0, 0), 'spine1': (15, 0, 0),
                  'ELBOW': (70, 70)},
    'bend_floor': {'left_hip': (-100, 0, 5), 'right_hip': (-100, 0, -5),
                   'spine1': (45, 0, 0), 'spine2': (30, 0, 0), 'spine3': (25, 0, 0),
                   'neck': (-20, 0, 0), 'left_shoulder': (-90, 0, 0),
                   'right_shoulder': (-90, 0, 0), 'ELBOW': (10, 10)},
    'lift_box': {'left_hip': (-80, 0, 20), 'right_hip': (-80, 0, -20),
                 'left_knee': (90, 0, 0), 'right_knee': (90, 0, 0), 'spine1': (30, 0, 0),
                 'spine2': (10, 0, 0), 'left_shoulder': (-50, 0, -20),
                 'right_shoulder': (-50, 0, 20), 'ELBOW': (60, 60)},
    'reach_overhead': {'left_shoulder': (-10, 0, 115), 'right_shoulder': (-10, 0, -115),
                       'spine1': (-15, 0, 0), 'spine2': (-10, 0, 0), 'neck': (-25, 0, 0),
                       'ELBOW': (15, 15)},
    'reach_side': {'left_shoulder': (0, 0, 90), 'spine1': (0, 0, -20), 'spine2': (0, 0, -15),
                   'left_hip': (0, 0, 20), 'right_knee': (30, 0, 0), 'ELBOW': (5, 60)},
    'kick': {'left_hip': (-90, 0, 0), 'left_knee': (10, 0, 0), 'right_knee': (15, 0, 0),
             'spine1': (-10, 0, 0), 'left_shoulder': (20, 0, 30),
             'right_shoulder': (-30, 0, -40), 'ELBOW': (50, 50)},
    'throw': {'left_shoulder': (-20, -60, 100), 'right_shoulder': (-60, 0, 0),
              'spine1': (0, 30, 0), 'spine2': (0, 20, 0), 'left_hip': (20, 0, 0),
              'right_hip': (-30, 0, 0), 'right_knee': (30, 0, 0), 'ELBOW': (100, 40)},
    'hands_on_hips': {'left_shoulder': (0, 0, 40), 'right_shoulder': (0, 0, -40),
                      'ELBOW': (110, 110), 'left_wrist': (0, 0, 20)},
    'phone': {'left_shoulder': (-30, 0, 20), 'ELBOW': (145, 20), 'head': (20, 0, 0),
              'neck': (15, 0, 0)},
    'all_fours': {'left_hip': (-90, 0, 5), 'right_hip': (-90, 0, -5),
                  'left_knee': (95, 0, 0), 'right_knee': (95, 0, 0),
                  'left_shoulder': (-90, 0, 5), 'right_shoulder': (-90, 0, -5),
                  'neck': (-30, 0, 0), 'ROOT': (85, 0)},
    'lie_back': {'left_hip': (-5, 0, 10), 'right_hip': (-5, 0, -10),
                 'left_shoulder': (0, 0, 30), 'right_shoulder': (0, 0, -30),
                 'ELBOW': (20, 20), 'ROOT': (-85, 0)},
    'lie_side': {'left_hip': (-40, 0, 0), 'right_hip': (-20, 0, 0), 'left_knee': (60, 0, 0),
                 'right_knee': (40, 0, 0), 'left_shoulder': (-60, 0, 0),
                 'right_shoulder': (-80, 0, 0), 'ELBOW': (60, 40), 'ROOT': (0, 80)},
}
BROAD_TEMPLATE_WEIGHTS = {'kneel': 1.0, 'kneel_one': 1.0, 'squat_deep': 1.0,
                          'sit_floor': 0.8, 'sit_cross': 0.6, 'bend_floor': 1.0,
                          'lift_box': 1.0, 'reach_overhead': 1.0, 'reach_side': 1.0,
                          'kick': 0.7, 'throw': 0.7, 'hands_on_hips': 0.7, 'phone': 0.7,
                          'all_fours': 0.5, 'lie_back': 0.4, 'lie_side': 0.4}
# 'broad' mixture: activity templates, broad postures, independent and coupled uniform
# draws within the joint limits.
BROAD_MIX = {'templates': 0.3, 'postures': 0.35, 'uniform': 0.15, 'coupled': 0.2}
# Seated on a chair (mode 'seated'): hips flexed 70-100 deg, thighs on the seat.
_SIT = {'left_hip': (-90, 0, 8), 'right_hip': (-90, 0, -8), 'left_knee': (90, 0, 0),
        'right_knee': (90, 0, 0)}
SEATED_TEMPLATES = {
    'seat_upright': {**_SIT, 'spine1': (5, 0, 0), 'left_shoulder': (-20, 0, 5),
                     'right_shoulder': (-20, 0, -5), 'ELBOW': (70, 70)},
    'seat_lean_forward': {**_SIT, 'left_hip': (-100, 0, 12), 'right_hip': (-100, 0, -12),
                          'left_knee': (95, 0, 0), 'right_knee': (95, 0, 0),
                          'spine1': (30, 0, 0), 'spine2': (10, 0, 0),
                          'left_shoulder': (-50, 0, 0), 'right_shoulder': (-50, 0, 0),
                          'ELBOW': (100, 100)},
    'seat_lean_back': {**_SIT, 'left_hip': (-75, 0, 10), 'right_hip': (-75, 0, -10),
                       'left_knee': (80, 0, 0), 'right_knee': (80, 0, 0),
                       'spine1': (-10, 0, 0), 'ELBOW': (30, 30)},
    'seat_legs_apart': {**_SIT, 'left_hip': (-90, 0, 30), 'right_hip': (-90, 0, -30),
                        'left_knee': (100, 0, 0), 'right_knee': (100, 0, 0),
                        'spine1': (10, 0, 0), 'ELBOW': (50, 50)},
    'seat_legs_out': {**_SIT, 'left_hip': (-80, 0, 10), 'right_hip': (-80, 0, -10),
                      'left_knee': (35, 0, 0), 'right_knee': (45, 0, 0),
                      'ELBOW': (40, 40)},
    'seat_reach': {**_SIT, 'spine1': (15, 0, 0), 'left_shoulder': (-85, 0, 20),
                   'right_shoulder': (-30, 0, 0), 'ELBOW': (10, 60)},
    'seat_arms_crossed': {**_SIT, 'left_shoulder': (-45, 0, -20),
                          'right_shoulder': (-45, 0, 20), 'ELBOW': (115, 115)},
    'seat_phone': {**_SIT, 'spine1': (15, 0, 0), 'left_shoulder': (-30, 0, 20),
                   'ELBOW': (145, 60), 'head': (20, 0, 0), 'neck': (15, 0, 0)},
}
_ALL_TEMPLATES = {**TEMPLATES, **BROAD_TEMPLATES, **SEATED_TEMPLATES}
_MIRROR_AXES = np.array([1.0, -1.0, -1.0])  # reflection x -> -x of an axis-angle vector


def _mirror_name(n: str) -> str:
    if n.startswith('left_'):
        return 'right_' + n[5:]
    if n.startswith('right_'):
        return 'left_' + n[6:]
    return n


def mocap_poses(names: list[str]) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    """The shipped motion capture (data/mocap_poses_anny.npz) for the fitted joints `names`
    (generic joint names; a joint the file lacks stays at rest): (N, P, 3) canonical
    poses, (N, 2) whole-body (pitch, roll) in radians, and each motion's pose indices."""
    from importlib import resources
    path = resources.files('smpl_depth_ros') / 'data' / 'mocap_poses_anny.npz'
    with np.load(str(path), allow_pickle=False) as f:
        poses, have = f['poses'].astype(np.float64), list(f['joint_names'])
        root = f['root'].astype(np.float64)
        motion = f['clip_motion'][f['clip']]
    out = np.zeros((len(poses), len(names), 3))
    for i, n in enumerate(names):
        if n in have:
            out[:, i] = poses[:, have.index(n)]
    return out, root, {str(m): np.flatnonzero(motion == m) for m in np.unique(motion)}


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
        mode: 'templates' (the activity templates; the stream earlier bags and training
            runs drew) or 'broad' (see the module doc).
        root_tilt: in 'broad' mode, whether postures may tilt the whole body (on all
            fours, lying); `sample_with_root` returns that tilt.
        head_turn_deg: 0 (default), or the head is also turned: a yaw drawn uniformly in
            +-head_turn_deg added at the neck and again at the head (up to twice that in
            all, within the joint limits), and a head pitch in +-head_turn_deg / 2. The
            templates turn the head little (one twists it 25 deg); people look aside.
            Off, the random stream is the one earlier bags and training runs drew.
    """

    def __init__(self, body: BodyModel, noise_deg: float = 9.0, head_turn_deg: float = 0.0,
                 mode: str = 'templates', root_tilt: bool = True):
        if mode not in MODES:
            raise ValueError(f'pose mode must be one of {MODES}, got {mode!r}')
        self.body = body
        self.mode = mode
        self.root_tilt = bool(root_tilt)
        self.head_turn = np.deg2rad(head_turn_deg)
        self.names = list(body.joint_names[1:])
        self.limits = body.limits_canonical().cpu().numpy().astype(np.float64)  # (P,3,2)
        self.C = body.canonical_rotation.cpu().numpy().astype(np.float64)
        self.elbows = elbow_axes(body)
        self.noise = np.deg2rad(noise_deg)
        self.templates = list(TEMPLATES)
        w = np.array([TEMPLATE_WEIGHTS[t] for t in self.templates])
        self.weights = w / w.sum()
        self.postures = [t for t in BROAD_TEMPLATES if root_tilt or 'ROOT' not in
                         BROAD_TEMPLATES[t]]
        w = np.array([BROAD_TEMPLATE_WEIGHTS[t] for t in self.postures])
        self.posture_weights = w / w.sum()
        self.hinges = [i for i, n in enumerate(self.names) if n.endswith(('_knee', '_elbow'))]
        self.mocap, self.mocap_root, self.motions = (
            mocap_poses(self.names) if mode == 'mocap' else (None, None, {}))
        self.last_motion: str | None = None  # the motion of the last mocap draw

    def template(self, name: str, amplitude: float = 1.0, mirror: bool = False) -> np.ndarray:
        """(P, 3) canonical axis-angle (radians) of a template."""
        out = np.zeros((len(self.names), 3))
        for jn, val in _ALL_TEMPLATES[name].items():
            if jn == 'ROOT':
                continue
            if jn == 'ELBOW':
                for side, ang in zip(('left', 'right'), val):
                    key = f'{side}_elbow'
                    if key in self.names:
                        out[self.names.index(key)] = self.elbows[key] * np.deg2rad(ang)
                continue
            if jn in self.names:
                out[self.names.index(jn)] = np.deg2rad(val)
        out *= amplitude
        return self.mirror(out) if mirror else out

    def mirror(self, pose: np.ndarray) -> np.ndarray:
        """(P, 3) canonical pose of the mirror-image person (left and right swapped)."""
        m = np.zeros_like(pose)
        for i, n in enumerate(self.names):
            j = self.names.index(_mirror_name(n)) if _mirror_name(n) in self.names else i
            m[j] = pose[i] * _MIRROR_AXES
        # Elbow hinge axes are mirror images of each other, so the reflection is exact.
        return m

    def clip(self, canon: np.ndarray) -> np.ndarray:
        return np.clip(canon, self.limits[..., 0], self.limits[..., 1])

    def to_model(self, canon: np.ndarray) -> np.ndarray:
        """Canonical (..., P, 3) -> model-frame axis-angle (float32)."""
        return (canon @ self.C).astype(np.float32)

    def _hinge(self, i: int, flexion: float) -> np.ndarray:
        n = self.names[i]
        if n.endswith('_elbow'):
            return self.elbows[n] * flexion
        return np.array([flexion, 0.0, 0.0])

    def _uniform(self, rng: np.random.Generator, coupled: bool) -> np.ndarray:
        """Uniform within the joint limits (knees and elbows as hinges), the spine, neck,
        collars and wrists drawn in the inner half of theirs; coupled: the right side
        mirrors the left, with noise."""
        lo, hi = self.limits[..., 0], self.limits[..., 1]
        inner = np.array([not n.endswith(('_hip', '_shoulder', '_knee', '_elbow'))
                          for n in self.names])
        c, h = 0.5 * (lo + hi), 0.5 * (hi - lo)
        h = np.where(inner[:, None], 0.5 * h, h)
        pose = rng.uniform(c - h, c + h)
        for i in self.hinges:
            pose[i] = self._hinge(i, rng.uniform(0.0, np.deg2rad(150)))
        if coupled:
            for i, n in enumerate(self.names):
                if n.startswith('left_') and _mirror_name(n) in self.names:
                    j = self.names.index(_mirror_name(n))
                    if i in self.hinges:
                        ang = float(np.linalg.norm(pose[i]))
                        pose[j] = self._hinge(j, ang)
                    else:
                        pose[j] = pose[i] * _MIRROR_AXES
                    pose[j] = pose[j] + rng.normal(0, 2 * self.noise, 3)
        return pose

    def sample_with_root(self, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """(P, 3) canonical pose and the whole-body (pitch, roll) in radians it implies
        (non-zero for 'broad' postures such as lying, and for motion capture)."""
        root = np.zeros(2)
        if self.mode == 'templates':
            return self.sample_canonical(rng), root
        if self.mode == 'seated':
            names = list(SEATED_TEMPLATES)
            return self._from_templates(rng, names, np.full(len(names), 1 / len(names)),
                                        9.0, amp=(0.85, 1.1)), root
        if self.mode == 'mocap':
            self.last_motion = list(self.motions)[rng.integers(len(self.motions))]
            of = self.motions[self.last_motion]
            i = of[rng.integers(len(of))]
            pose, root = self.mocap[i].astype(np.float64), self.mocap_root[i].copy()
            self.last_mirror = bool(rng.random() < 0.5)
            if self.last_mirror:
                pose, root[1] = self.mirror(pose), -root[1]
            pose = pose + rng.normal(0, np.deg2rad(3.0), pose.shape)
            return self._head(rng, pose), root
        kinds = list(BROAD_MIX)
        k = kinds[rng.choice(len(kinds), p=np.array(list(BROAD_MIX.values())))]
        if k == 'templates':
            return self._from_templates(rng, self.templates, self.weights, 9.0), root
        if k == 'postures':
            t = self.postures[rng.choice(len(self.postures), p=self.posture_weights)]
            pose = self._from_templates(rng, [t], np.ones(1), 14.0, amp=(0.6, 1.15))
            r = BROAD_TEMPLATES[t].get('ROOT')
            if r is not None:
                root = np.deg2rad(np.asarray(r, np.float64)) * rng.uniform(0.85, 1.05)
                if self.last_mirror:
                    root[1] = -root[1]
            return pose, root
        return self.clip(self._uniform(rng, coupled=k == 'coupled')), root

    def _from_templates(self, rng, names, weights, noise_deg, amp=(0.3, 1.15)):
        t = names[rng.choice(len(names), p=weights)]
        self.last_mirror = bool(rng.random() < 0.5)
        pose = self.template(t, rng.uniform(*amp), mirror=self.last_mirror)
        pose = pose + rng.normal(0, np.deg2rad(noise_deg), pose.shape)
        return self._head(rng, pose)

    def _head(self, rng, pose):
        """The optional head turn (head_turn_deg) added, then the joint limits."""
        if self.head_turn > 0:
            yaw = rng.uniform(-self.head_turn, self.head_turn)
            for j in ('neck', 'head'):
                if j in self.names:
                    pose[self.names.index(j), 1] += yaw
            if 'head' in self.names:
                pose[self.names.index('head'), 0] += rng.uniform(-0.5, 0.5) * self.head_turn
        return self.clip(pose)

    def sample_canonical(self, rng: np.random.Generator) -> np.ndarray:
        """(P, 3) canonical pose (any whole-body tilt of a 'broad' posture dropped)."""
        if self.mode in ('broad', 'seated', 'mocap'):
            return self.sample_with_root(rng)[0]
        t = self.templates[rng.choice(len(self.templates), p=self.weights)]
        amp = rng.uniform(0.3, 1.15)
        pose = self.template(t, amp, mirror=bool(rng.random() < 0.5))
        pose = pose + rng.normal(0, self.noise, pose.shape)
        return self._head(rng, pose)

    def sample(self, rng: np.random.Generator, n: int = 1) -> np.ndarray:
        """(n, P, 3) model-frame axis-angle poses."""
        return self.to_model(np.stack([self.sample_canonical(rng) for _ in range(n)]))

    def sample_posed(self, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """One (P, 3) model-frame pose and its whole-body (pitch, roll) in radians."""
        canon, root = self.sample_with_root(rng)
        return self.to_model(canon[None])[0], root

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
