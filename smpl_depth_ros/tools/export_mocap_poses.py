"""Write smpl_depth_ros/data/mocap_poses_anny.npz: real motion-capture poses on anny.

    pip install --no-deps --target /tmp/holosoma holosoma-retargeting==0.1.0
    python -m smpl_depth_ros.tools.export_mocap_poses --source /tmp/holosoma

Two motions that `holosoma-retargeting` (Apache-2.0) ships as demo data, each a set of
clips of motion-capture joint positions (metres, z up):

* climbing: `demo_data/climb/mocap_climb_seq_*/…_joint_positions_*.npy`, (frames, 53, 3)
  in the LAFAN-style skeleton of `MOCAP_JOINTS`;
* box lifting: `demo_data/OMOMO_new/*_largebox_*.pt` (OMOMO: a person picking up, carrying
  and putting down a large box), one float tensor (frames, 591) per clip whose columns
  162-317 are the 52 SMPL-H joints of `SMPLH_JOINTS` (holosoma's
  `src/utils.load_intermimic_data`); read with `torch.load(weights_only=True)`.

Every `every`-th frame of a clip (`MOTIONS`) is retargeted to anny: the body model (pose,
shape and global orientation) is fitted to the joints that name the same anatomical
points (fit.Fitter.fit_joints on that subset), and the fitted joint rotations are kept in
canonical axes (synth.poses), with the whole body's tilt from upright (pitch and roll,
`root`; its heading is dropped) where the motion keeps it (`MOTIONS`: box lifting, not
climbing). Frames whose fit leaves a mean joint distance above
`--max-residual-m` are dropped (the mocap and anny skeletons put some joint centres
differently; a fit that misses by more has not reproduced the pose). The result is small
and committed; nothing reads holosoma at run time.
"""
from __future__ import annotations

import argparse
import glob
import os
import sys

import numpy as np

# anny joint <- the mocap joint at the same anatomical point (holosoma's MOCAP_DEMO_JOINTS
# names; the mocap 'Spine' sits 8 cm above the hips, where anny has no joint, and anny's
# spine2 has no mocap counterpart).
JOINT_MAP = {
    'pelvis': 'Hips', 'left_hip': 'LeftUpLeg', 'right_hip': 'RightUpLeg',
    'left_knee': 'LeftLeg', 'right_knee': 'RightLeg',
    'left_ankle': 'LeftFoot', 'right_ankle': 'RightFoot',
    'spine3': 'Spine1', 'neck': 'Neck', 'head': 'Head',
    'left_collar': 'LeftShoulder', 'right_collar': 'RightShoulder',
    'left_shoulder': 'LeftArm', 'right_shoulder': 'RightArm',
    'left_elbow': 'LeftForeArm', 'right_elbow': 'RightForeArm',
    'left_wrist': 'LeftHand', 'right_wrist': 'RightHand',
}
# holosoma_retargeting/config_types/data_type.py MOCAP_DEMO_JOINTS, in file order (53).
MOCAP_JOINTS = (
    ['Hips', 'Spine', 'Spine1', 'Neck', 'Head', 'LeftShoulder', 'LeftArm', 'LeftForeArm',
     'LeftHand']
    + [f'LeftHand{f}{i}' for f in ('Thumb', 'Index', 'Middle', 'Ring', 'Pinky')
       for i in (1, 2, 3)]
    + ['RightShoulder', 'RightArm', 'RightForeArm', 'RightHand']
    + [f'RightHand{f}{i}' for f in ('Thumb', 'Index', 'Middle', 'Ring', 'Pinky')
       for i in (1, 2, 3)]
    + ['LeftUpLeg', 'LeftLeg', 'LeftFoot', 'LeftToeBase', 'RightUpLeg', 'RightLeg',
       'RightFoot', 'RightToeBase', 'LeftFootMod', 'RightFootMod'])
# holosoma_retargeting/config_types/data_type.py SMPLH_DEMO_JOINTS, in file order (52).
SMPLH_JOINTS = (
    ['Pelvis', 'L_Hip', 'L_Knee', 'L_Ankle', 'L_Toe', 'R_Hip', 'R_Knee', 'R_Ankle', 'R_Toe',
     'Torso', 'Spine', 'Chest', 'Neck', 'Head', 'L_Thorax', 'L_Shoulder', 'L_Elbow',
     'L_Wrist']
    + [f'L_{f}{i}' for f in ('Index', 'Middle', 'Pinky', 'Ring', 'Thumb') for i in (1, 2, 3)]
    + ['R_Thorax', 'R_Shoulder', 'R_Elbow', 'R_Wrist']
    + [f'R_{f}{i}' for f in ('Index', 'Middle', 'Pinky', 'Ring', 'Thumb') for i in (1, 2, 3)])
SMPLH_COLUMNS = slice(162, 162 + 52 * 3)  # of an OMOMO clip's rows
# anny joint <- the SMPL-H joint at the same anatomical point (SMPL-H's Chest is spine3).
SMPLH_MAP = {
    'pelvis': 'Pelvis', 'left_hip': 'L_Hip', 'right_hip': 'R_Hip',
    'left_knee': 'L_Knee', 'right_knee': 'R_Knee',
    'left_ankle': 'L_Ankle', 'right_ankle': 'R_Ankle',
    'spine3': 'Chest', 'neck': 'Neck', 'head': 'Head',
    'left_collar': 'L_Thorax', 'right_collar': 'R_Thorax',
    'left_shoulder': 'L_Shoulder', 'right_shoulder': 'R_Shoulder',
    'left_elbow': 'L_Elbow', 'right_elbow': 'R_Elbow',
    'left_wrist': 'L_Wrist', 'right_wrist': 'R_Wrist',
}
# motion: (clip files under the package's folder, every n-th frame taken by default,
# whether the body's tilt is kept). The climbers lean on a wall the renderer does not
# draw: their tilt is dropped (upright, they stand on its floor); box lifting happens on
# the floor, bent over it.
MOTIONS = {
    'climbing': ('demo_data/climb/mocap_climb_seq_*/*_joint_positions_*.npy', 10, False),
    'box lifting': ('demo_data/OMOMO_new/*_largebox_*.pt', 3, True),
}
# mocap world (z up) <- canonical world (y up): (x, y, z) -> (x, -z, y).
WORLD_FROM_CANONICAL = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])
OUT = os.path.join(os.path.dirname(__file__), '..', 'data', 'mocap_poses_anny.npz')


def clip_files(source: str) -> list[tuple[str, str]]:
    """(motion, path) of every clip of `MOTIONS` under an installed holosoma_retargeting
    (its folder, or a --target folder holding it), sorted by motion then path."""
    root = os.path.join(source, 'holosoma_retargeting') if os.path.isdir(
        os.path.join(source, 'holosoma_retargeting')) else source
    files = [(motion, f) for motion, (pattern, _, _) in MOTIONS.items()
             for f in sorted(glob.glob(os.path.join(root, pattern)))]
    if not files:
        raise FileNotFoundError(f'no motion-capture clips under {root} (demo_data/climb, '
                                'demo_data/OMOMO_new)')
    return files


def load_clip(path: str) -> tuple[np.ndarray, list[str], dict[str, str]]:
    """A clip's joint positions (frames, J, 3), its skeleton's joint names and the map
    from anny's joints to them."""
    if path.endswith('.pt'):
        import torch
        rows = torch.load(path, map_location='cpu', weights_only=True)
        if not torch.is_tensor(rows) or rows.ndim != 2 or rows.shape[1] < SMPLH_COLUMNS.stop:
            raise ValueError(f'{path}: expected a (frames, >= {SMPLH_COLUMNS.stop}) tensor')
        pos = rows.detach().cpu().numpy()[:, SMPLH_COLUMNS].reshape(len(rows), -1, 3)
        return pos, SMPLH_JOINTS, SMPLH_MAP
    pos = np.load(path, allow_pickle=False)
    if pos.ndim != 3 or pos.shape[1:] != (len(MOCAP_JOINTS), 3):
        raise ValueError(f'{path}: expected (frames, {len(MOCAP_JOINTS)}, 3), got {pos.shape}')
    return pos, MOCAP_JOINTS, JOINT_MAP


def body_tilt(global_orient: np.ndarray, C: np.ndarray) -> tuple[float, float]:
    """(pitch, roll) in radians of a body fitted in the z-up mocap world with this global
    orientation (model frame -> world): its tilt from upright, as
    `synth.poses.placement` applies it (R = yaw(y) pitch(x) roll(z) in canonical axes)."""
    from scipy.spatial.transform import Rotation
    R = Rotation.from_rotvec(np.asarray(global_orient, np.float64)).as_matrix()
    T = WORLD_FROM_CANONICAL.T @ R @ C.T  # canonical body -> canonical world
    _, pitch, roll = Rotation.from_matrix(T).as_euler('YXZ')
    return float(pitch), float(roll)


def retarget(files: list[tuple[str, str]], body, every: int | None,
             max_residual_m: float) -> dict:
    """Fit anny to every n-th frame of the clips (`every`, or each motion's own in
    `MOTIONS`); returns the arrays of the file."""
    from smpl_depth_ros.fit import Fitter
    fitter = Fitter(body)
    names = list(body.joint_names)
    C = body.canonical_rotation.cpu().numpy().astype(np.float64)
    poses, roots, clips, frames, residuals = [], [], [], [], []
    for k, (motion, path) in enumerate(files):
        pos, theirs, jmap = load_clip(path)
        ours = [n for n in names if n in jmap]
        ids = np.array([names.index(n) for n in ours])
        src = np.array([theirs.index(jmap[n]) for n in ours])
        for f in range(0, len(pos), every or MOTIONS[motion][1]):
            target = pos[f, src].astype(np.float64)
            r = fitter.fit(target, ids, targets_are_joints=True, iterations=30)
            res = float(np.linalg.norm(r.joints[ids] - target, axis=1).mean())
            if res > max_residual_m:
                continue
            poses.append(np.asarray(r.params.pose, np.float64) @ C.T)
            roots.append(body_tilt(r.params.global_orient, C) if MOTIONS[motion][2]
                         else (0.0, 0.0))
            clips.append(k)
            frames.append(f)
            residuals.append(res)
    return dict(poses=np.asarray(poses, np.float32), root=np.asarray(roots, np.float32),
                clip=np.asarray(clips, np.int16), frame=np.asarray(frames, np.int32),
                residual_m=np.asarray(residuals, np.float32),
                joint_names=np.array(names[1:]),
                clips=np.array([os.path.basename(p) for _, p in files]),
                clip_motion=np.array([m for m, _ in files]),
                source=np.array('holosoma-retargeting 0.1.0 demo_data/climb and '
                                'demo_data/OMOMO_new (Apache-2.0)'))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog='export_mocap_poses', description=__doc__.split('\n')[0])
    ap.add_argument('--source', required=True,
                    help='an installed holosoma_retargeting (or the --target folder of a '
                         'pip install --no-deps of holosoma-retargeting==0.1.0)')
    ap.add_argument('--out', default=OUT)
    ap.add_argument('--every', type=int, default=None,
                    help="take every n-th frame (default: each motion's, MOTIONS)")
    ap.add_argument('--max-residual-m', type=float, default=0.05)
    args = ap.parse_args(argv)
    import torch

    from smpl_depth_ros.body import load_body_model
    body = load_body_model('anny', dtype=torch.float64)
    data = retarget(clip_files(args.source), body, args.every, args.max_residual_m)
    np.savez_compressed(args.out, **data)
    for motion in MOTIONS:
        of = np.isin(data['clip'], np.flatnonzero(data['clip_motion'] == motion))
        print(f'{args.out}: {motion}: {int(of.sum())} poses, mean joint residual '
              f'{1e3 * data["residual_m"][of].mean():.1f} mm', file=sys.stderr)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
