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


def test_crop_confusion_counts_at_the_networks_resolution():
    """Ground truth sent into the crop and compared there: labels equal to the sampled
    truth score 1.0 even where the full-image truth has detail finer than a crop pixel
    (the upsampled labels cannot show it), and the pixels the network's input did not
    hold (too far behind the person) are not counted."""
    from smpl_depth_ros.net.preprocess import square_crop
    H, W = 240, 320
    depth = np.zeros((H, W), np.float32)
    depth[40:200, 100:220] = 2.0
    depth[40:60, 100:220] = 4.0          # beyond the input's 1 m window: not seen
    gt = np.zeros((H, W), np.uint8)
    gt[40:200, 100:160] = 1
    gt[40:200, 160:220] = 2
    gt[100:200:2, 100:220] = 3           # one-pixel stripes, finer than a crop pixel
    crop = square_crop(100, 40, 219, 199, size=32, median_depth=2.0)
    rr, cc, inside = crop.sample_indices(depth.shape)
    sampled = np.where(inside, gt[rr, cc], 0)
    c = ev.crop_confusion(crop, sampled, depth, gt)
    assert ev.miou(c) == 1.0
    seen = (depth[rr, cc] == 2.0) & inside
    assert c.sum() == int((seen & (sampled > 0)).sum())
    # Upsampled back to the full image the same labels miss the stripes' detail.
    i = np.clip(((np.arange(H) + 0.5 - crop.v0) / crop.scale).astype(int), 0, 31)
    j = np.clip(((np.arange(W) + 0.5 - crop.u0) / crop.scale).astype(int), 0, 31)
    up = np.where(depth == 2.0, sampled[np.ix_(i, j)], 0)
    assert ev.miou(ev.confusion(up, np.where(depth == 2.0, gt, 0))) < 0.9
    wrong = np.where(sampled == 3, 1, sampled)
    assert ev.miou(ev.crop_confusion(crop, wrong, depth, gt)) < 0.7
