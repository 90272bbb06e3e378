"""Accuracy metrics (core, no ROS)."""
import numpy as np
from scipy.spatial.transform import Rotation

from smpl_depth_ros import evaluation as ev


def test_pve_and_procrustes():
    rng = np.random.default_rng(0)
    gt = rng.normal(size=(100, 3))
    moved = 1.3 * gt @ Rotation.from_rotvec([0.3, -0.2, 1.0]).as_matrix().T + [1.0, 2.0, 3.0]
    assert ev.pve(moved, gt) > 0.5
    assert ev.pa_pve(moved, gt) < 1e-9
    assert abs(ev.pve(gt + [0.0, 0.0, 0.01], gt) - 0.01) < 1e-12


def test_miou_and_its_network_resolution_weighting():
    # Near frame: part 1 right, part 2 half wrong (labelled 3); 100 pixels per crop pixel.
    gt_near = np.array([[1, 1, 2, 2]]).repeat(100, 0)
    pred_near = np.array([[1, 1, 2, 3]]).repeat(100, 0)
    # Far frame: everything right; 1 pixel per crop pixel.
    gt_far = np.array([[1, 2, 3, 0]])
    pred_far = gt_far.copy()
    c = ev.confusion(pred_near, gt_near) + ev.confusion(pred_far, gt_far)
    assert c.sum() == 400 + 3 and c[2, 3] == 100
    # Full resolution: the near frame dominates.
    assert abs(ev.miou(c) - np.mean([201 / 201, 101 / 201, 1 / 101])) < 1e-12
    # One count per network-input pixel: both frames weigh the same.
    w = ev.confusion(pred_near, gt_near, weight=1 / 100) + ev.confusion(pred_far, gt_far)
    assert abs(ev.miou(w) - np.mean([3 / 3, 2 / 3, 1 / 2])) < 1e-12
    # Background is excluded; a part nobody has or predicts does not count.
    assert ev.miou(ev.confusion(np.zeros((2, 2), int), np.array([[0, 5], [5, 0]]))) == 0.0
