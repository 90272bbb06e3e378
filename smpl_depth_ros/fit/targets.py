"""The fit's targets (no ROS): depth pixels back-projected to camera-frame points
(`backproject`), and points with correspondences aggregated to one robust target per
corresponded vertex (`aggregate_by_vertex`).
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree


def backproject(depth: np.ndarray, K: np.ndarray, mask: np.ndarray | None = None):
    """Pixels to 3D points (paper: p_i from the intrinsic matrix).

    Args:
        depth: (H, W) float32 metres, 0/NaN invalid.
        K: (3, 3) intrinsics.
        mask: optional (H, W) bool, pixels to keep.

    Returns:
        points (N, 3) float32 camera frame, pixels (N, 2) int (row, col).
    """
    valid = np.isfinite(depth) & (depth > 0)
    if mask is not None:
        valid &= mask
    r, c = np.nonzero(valid)
    z = depth[r, c].astype(np.float64)
    x = (c - K[0, 2]) * z / K[0, 0]
    y = (r - K[1, 2]) * z / K[1, 1]
    return np.stack([x, y, z], 1).astype(np.float32), np.stack([r, c], 1)


def _group_median(values: np.ndarray, grp: np.ndarray, lo: np.ndarray, hi: np.ndarray):
    """Median of `values` within contiguous groups `grp` (sorted), group bounds lo/hi."""
    span = max(float(values.max() - values.min()), 1e-9)
    # Sort by (group, value) with one argsort: the values map into [0, 1).
    xs = values[np.argsort(grp + (values - values.min()) / (span * (1 + 1e-6)), kind='stable')]
    return 0.5 * (xs[lo] + xs[hi])


def aggregate_by_vertex(points: np.ndarray, ids: np.ndarray, weights: np.ndarray | None = None,
                        spread_m: float = 0.02, min_points: int = 2,
                        template: np.ndarray | None = None, tolerance_m: float = 0.05):
    """One robust target per corresponded vertex.

    Many pixels share a vertex (a 1,229-vertex template spans ~3 cm between vertices):
    the median of its cell of points sits near the vertex itself, whereas single pixels
    scatter by the vertex spacing plus sensor noise. The target is the coordinate-wise
    median of the vertex's points; its weight is their number (or summed weights) times
    1 / (1 + (d / spread_m)^2), d = the median distance of the points to the target, and
    0 beyond d > 3 spread_m: a coherent cell keeps its weight, a cell made of scattered
    wrong correspondences (e.g. a hidden vertex that only wrong pixels name) is dropped -
    a small weight would still drag a limb that nothing else constrains.

    A cell also needs `min_points` points once the typical cell (the count-weighted
    median) holds twice that: a visible vertex collects a patch of pixels, whereas
    isolated wrong correspondences scatter over hundreds of otherwise empty cells, each a
    perfectly "coherent" singleton. With 30 % wrong correspondences those singletons
    carried 15-55 % of the total weight. Given the `template` (rest vertex positions), a
    small cell is kept when it agrees with its nearest full cell instead: their vertices
    are at most their observed distance + `tolerance_m` apart on the template (a genuine
    sparse cell, e.g. a limb edge, sits beside its template neighbours).

    Returns:
        targets (M, 3), vertex ids (M,), weights (M,).
    """
    ids = np.asarray(ids, np.int64)
    order = np.argsort(ids, kind='stable')
    uniq, start, counts = np.unique(ids[order], return_index=True, return_counts=True)
    lo, hi = start + (counts - 1) // 2, start + counts // 2
    grp = np.repeat(np.arange(len(uniq)), counts)
    p = np.asarray(points, np.float64)[order]
    out = np.stack([_group_median(p[:, c], grp, lo, hi) for c in range(3)], 1)
    spread = _group_median(np.linalg.norm(p - out[grp], axis=1), grp, lo, hi)
    w = counts.astype(np.float64) if weights is None else \
        np.bincount(grp, np.asarray(weights, np.float64)[order], len(uniq))
    w = w / (1.0 + (spread / spread_m) ** 2)
    keep = spread <= 3 * spread_m
    cs = np.sort(counts)
    typical = cs[np.searchsorted(np.cumsum(cs), 0.5 * cs.sum())]
    small = counts < min_points
    if typical >= 2 * min_points and small.any():
        full = keep & ~small
        if template is not None and full.sum() >= 3:
            d, nn = cKDTree(out[full]).query(out[small])
            far = np.linalg.norm(template[uniq[small]] - template[uniq[full][nn]], axis=1)
            keep[small] &= far <= d + tolerance_m
        else:
            keep &= ~small
    return out[keep], uniq[keep], w[keep]
