"""Write smpl_depth_ros/data/mocap_poses_anny.npz: real motion-capture poses on anny.

    pip install --no-deps --target /tmp/holosoma holosoma-retargeting==0.1.0
    python -m smpl_depth_ros.tools.export_mocap_poses --source /tmp/holosoma

The climbing clips that `holosoma-retargeting` (Apache-2.0) ships as demo data
(`demo_data/climb/mocap_climb_seq_*/…_joint_positions_*.npy`: motion-capture joint
positions, 53 joints, metres, z up) are retargeted to anny: every `--every`-th frame, the
body model (pose and shape) is fitted to the 19 joints that name the same anatomical
points (fit.Fitter.fit_joints on that subset), and the fitted joint rotations are kept in
canonical axes (synth.poses). Frames whose fit leaves a mean joint distance above
`--max-residual-m` are dropped (the mocap and anny skeletons put some joint centres
differently; a fit that misses by more has not reproduced the pose). The whole-body
orientation is not kept: `PoseSampler(mode='mocap')` places the bodies upright like its
other poses. The result is small and committed; nothing reads holosoma at run time.
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
OUT = os.path.join(os.path.dirname(__file__), '..', 'data', 'mocap_poses_anny.npz')


def clip_files(source: str) -> list[str]:
    """The climbing clips' joint-position files under an installed holosoma_retargeting
    (its folder, or a --target folder holding it), sorted."""
    root = os.path.join(source, 'holosoma_retargeting') if os.path.isdir(
        os.path.join(source, 'holosoma_retargeting')) else source
    files = sorted(glob.glob(os.path.join(root, 'demo_data', 'climb', 'mocap_climb_seq_*',
                                          '*_joint_positions_*.npy')))
    if not files:
        raise FileNotFoundError(f'no climbing clips under {root} (demo_data/climb)')
    return files


def retarget(files: list[str], body, every: int, max_residual_m: float) -> dict:
    """Fit anny to every `every`-th frame of the clips; returns the arrays of the file."""
    from smpl_depth_ros.fit import Fitter
    fitter = Fitter(body)
    names = list(body.joint_names)
    ours = [n for n in names if n in JOINT_MAP]
    ids = np.array([names.index(n) for n in ours])
    src = np.array([MOCAP_JOINTS.index(JOINT_MAP[n]) for n in ours])
    C = body.canonical_rotation.cpu().numpy().astype(np.float64)
    poses, clips, frames, residuals = [], [], [], []
    for k, path in enumerate(files):
        pos = np.load(path, allow_pickle=False)
        if pos.ndim != 3 or pos.shape[1:] != (len(MOCAP_JOINTS), 3):
            raise ValueError(f'{path}: expected (frames, {len(MOCAP_JOINTS)}, 3), got {pos.shape}')
        for f in range(0, len(pos), every):
            target = pos[f, src].astype(np.float64)
            r = fitter.fit(target, ids, targets_are_joints=True, iterations=30)
            res = float(np.linalg.norm(r.joints[ids] - target, axis=1).mean())
            if res > max_residual_m:
                continue
            poses.append(np.asarray(r.params.pose, np.float64) @ C.T)
            clips.append(k)
            frames.append(f)
            residuals.append(res)
    return dict(poses=np.asarray(poses, np.float32), clip=np.asarray(clips, np.int16),
                frame=np.asarray(frames, np.int32), residual_m=np.asarray(residuals, np.float32),
                joint_names=np.array(names[1:]),
                clips=np.array([os.path.basename(p) for p in files]),
                source=np.array('holosoma-retargeting 0.1.0 demo_data/climb (Apache-2.0)'))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog='export_mocap_poses', description=__doc__.split('\n')[0])
    ap.add_argument('--source', required=True,
                    help='an installed holosoma_retargeting (or the --target folder of a '
                         'pip install --no-deps of holosoma-retargeting==0.1.0)')
    ap.add_argument('--out', default=OUT)
    ap.add_argument('--every', type=int, default=10, help='take every n-th frame')
    ap.add_argument('--max-residual-m', type=float, default=0.05)
    args = ap.parse_args(argv)
    import torch

    from smpl_depth_ros.body import load_body_model
    body = load_body_model('anny', dtype=torch.float64)
    data = retarget(clip_files(args.source), body, args.every, args.max_residual_m)
    np.savez_compressed(args.out, **data)
    print(f'{args.out}: {len(data["poses"])} poses from {len(data["clips"])} clips, mean '
          f'joint residual {1e3 * data["residual_m"].mean():.1f} mm', file=sys.stderr)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
