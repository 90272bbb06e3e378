"""Estimate a body model's pose Gaussian (fit.pose_prior) and save it (the shipped
`data/pose_prior_anny.npz`):

    python -m smpl_depth_ros.tools.export_pose_prior --backend anny \\
        --out smpl_depth_ros/data/pose_prior_anny.npz
"""
from __future__ import annotations

import argparse

from smpl_depth_ros.fit.pose_prior import SAMPLES, PoseGaussian


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog='python -m smpl_depth_ros.tools.export_pose_prior',
                                 description='estimate and save the pose Gaussian')
    ap.add_argument('--backend', default='anny', choices=['anny', 'smpl'])
    ap.add_argument('--model-path', default=None)
    ap.add_argument('--out', required=True)
    ap.add_argument('--samples', type=int, default=SAMPLES)
    ap.add_argument('--seed', type=int, default=0)
    args = ap.parse_args(argv)
    from smpl_depth_ros.body import load_body_model
    body = load_body_model(args.backend, args.model_path)
    PoseGaussian.estimate(body, args.samples, args.seed).save(args.out, body)
    print(args.out)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
