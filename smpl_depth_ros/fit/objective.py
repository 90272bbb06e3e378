"""The fitting objective of paper Eq. 3-4 (torch, differentiable).

E = lambda_D * mean_i rho(||p_i - v_c(i)||^2)          robust data term (Geman-McClure)
  + lambda_pose * sum_j hinge(limits, C theta_j)^2      joint-limit prior (canonical axes)
  + lambda_pose_l2 * sum_j ||theta_j||^2               weak pull towards rest
  + lambda_pose_weak * sum_{j weak} ||theta_j||^2      pull of the collars and wrists
  + lambda_shape * sum_k ((beta_k - mu_k) / sigma_k)^2  shape prior (adult statistics)

The paper's pose prior sum(exp(theta_i)) only penalises a few SMPLify bends; the hinge on
anatomical joint limits (body.base.JOINT_LIMITS_DEG) keeps every fitted joint plausible
and is zero inside the limits, so it does not bias well-observed poses.

The collars and wrists (WEAK_JOINTS) get a stronger pull towards rest: a depth image
hardly observes them. A collar's rotation moves the whole arm, as the shoulder's does, so
the data cannot tell the two apart; a wrist's only evidence is the orientation of a hand a
few pixels wide, whose regressed coordinates are the noisiest of the body. Left free, both
follow correspondence noise (README, Fitting).
"""
from __future__ import annotations

import numpy as np
import torch

from smpl_depth_ros.config import FitConfig


WEAK_JOINTS = ('left_collar', 'right_collar', 'left_wrist', 'right_wrist')


def weak_joint_mask(body):
    """(P,) bool over the pose joints (root excluded): the WEAK_JOINTS the model has."""
    return np.array([n in WEAK_JOINTS for n in body.joint_names[1:]])


# The penalty helpers take numpy arrays or torch tensors alike (the fast solver runs in
# numpy, the L-BFGS reference and the tests in torch).


def geman_mcclure(sq_dist: torch.Tensor, sigma: float) -> torch.Tensor:
    """rho(r^2) = sigma^2 r^2 / (r^2 + sigma^2): ~r^2 near 0, bounded by sigma^2."""
    s2 = sigma * sigma
    return s2 * sq_dist / (sq_dist + s2)


def gm_weights(sq_dist: torch.Tensor, sigma: float) -> torch.Tensor:
    """IRLS weights d rho / d(r^2) = sigma^4 / (r^2 + sigma^2)^2 (1 at r = 0)."""
    s2 = sigma * sigma
    return (s2 / (sq_dist + s2)) ** 2


def limit_violation(pose_canonical: torch.Tensor, limits: torch.Tensor) -> torch.Tensor:
    """(..., P, 3) signed distance outside the box limits (P, 3, 2); 0 inside."""
    lo, hi = limits[..., 0], limits[..., 1]
    return (lo - pose_canonical).clip(min=0) - (pose_canonical - hi).clip(min=0)


def energy(body, params: dict, points: torch.Tensor, vertex_ids: torch.Tensor,
           cfg: FitConfig, point_weights: torch.Tensor | None = None,
           targets_are_joints: bool = False) -> dict[str, torch.Tensor]:
    """All terms of the objective for batch size 1.

    Args:
        params: pose (1,P,3), shape (1,S), global_orient (1,3), transl (1,3).
        points: (N, 3) observed points, camera frame, metres.
        vertex_ids: (N,) corresponding template vertex (or joint index when
            targets_are_joints).
    """
    if targets_are_joints:
        model = body(params['pose'], params['shape'], params['global_orient'],
                     params['transl']).joints[0, vertex_ids]
    else:
        uniq, inv = torch.unique(vertex_ids, return_inverse=True)
        model = body(params['pose'], params['shape'], params['global_orient'],
                     params['transl'], vertex_ids=uniq).vertices[0, inv]
    sq = ((model - points) ** 2).sum(-1)
    rho = geman_mcclure(sq, cfg.gm_sigma)
    data = (rho * point_weights).sum() / point_weights.sum() if point_weights is not None \
        else rho.mean()
    canon = body.pose_to_canonical(params['pose'][0])
    viol = limit_violation(canon, body.limits_canonical())
    pose_prior = (viol ** 2).sum()
    pose_l2 = (params['pose'] ** 2).sum()
    weak = torch.as_tensor(weak_joint_mask(body), device=params['pose'].device)
    pose_weak = (params['pose'][0][weak] ** 2).sum()
    shape_prior = (((params['shape'][0] - body.shape_mean) / body.shape_std) ** 2).sum()
    total = (cfg.lambda_data * data + cfg.lambda_pose * pose_prior
             + cfg.lambda_pose_l2 * pose_l2 + cfg.lambda_pose_weak * pose_weak
             + cfg.lambda_shape * shape_prior)
    return dict(total=total, data=data, pose_prior=pose_prior, pose_l2=pose_l2,
                pose_weak=pose_weak,
                shape_prior=shape_prior, sq_dist=sq)
