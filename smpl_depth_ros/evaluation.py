"""Accuracy metrics (no ROS): paper Eq. 5 and friends."""
from __future__ import annotations

import json
import os

import numpy as np


def write_json(out: dict, path: str | None, command: str | None = None) -> None:
    """Write `out` to `path` (if given) and print it as one JSON line (the tools' output);
    `command`, the command line that produced the figures, is recorded with them."""
    if command:
        out = dict(out, command=command)
    if path:
        os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
        with open(path, 'w') as fh:
            json.dump(out, fh, indent=1)
    print(json.dumps(out))


def pve(pred: np.ndarray, gt: np.ndarray, valid: np.ndarray | None = None) -> float:
    """Mean per-vertex error (paper Eq. 5), metres, camera frame, no alignment."""
    d = np.linalg.norm(pred - gt, axis=-1)
    return float(d[valid].mean() if valid is not None else d.mean())


def procrustes(pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """pred aligned to gt by the similarity transform (rotation, translation, scale)."""
    mp, mg = pred.mean(0), gt.mean(0)
    p, g = pred - mp, gt - mg
    U, S, Vt = np.linalg.svd(p.T @ g)
    d = np.sign(np.linalg.det(U @ Vt))
    D = np.diag([1.0, 1.0, d])
    R = U @ D @ Vt
    s = (S * np.diag(D)).sum() / (p ** 2).sum()
    return s * p @ R + mg


def part_errors(pred: np.ndarray, gt: np.ndarray, part_of: np.ndarray, n: int = 15
                ) -> np.ndarray:
    """(n - 1,) mean per-vertex error (m) of each body part (background excluded; NaN
    for a part without vertices)."""
    e = np.linalg.norm(np.asarray(pred, np.float64) - gt, axis=-1)
    s = np.bincount(part_of, e, n)[1:]
    c = np.bincount(part_of, None, n)[1:]
    return np.where(c > 0, s / np.maximum(c, 1), np.nan)


def pa_pve(pred, gt, valid=None) -> float:
    return pve(procrustes(pred, gt), gt, valid)


def mpjpe(pred_joints, gt_joints) -> float:
    return float(np.linalg.norm(pred_joints - gt_joints, axis=-1).mean())


def confusion(pred: np.ndarray, gt: np.ndarray, n: int = 15, weight: float = 1.0
              ) -> np.ndarray:
    """(n, n) pixel counts, rows = ground truth, on pixels where either is a body part;
    each pixel counts `weight` (e.g. 1 / crop scale^2: one per network-input pixel)."""
    m = (pred > 0) | (gt > 0)
    c = np.bincount(gt[m].astype(np.int64) * n + pred[m], minlength=n * n).reshape(n, n)
    return c if weight == 1.0 else c * float(weight)


def crop_confusion(crop, crop_labels: np.ndarray, depth: np.ndarray, gt_labels: np.ndarray,
                   n: int = 15) -> np.ndarray:
    """Confusion of the network's labels at its own input resolution: the ground truth
    sampled into the crop the network saw (nearest full-image pixel, as its input was),
    on the crop pixels its input holds (valid, near the person's depth, no neighbour).

    At sensor resolution the nearest-neighbour upsampled crop labels are blocky at part
    borders: on close people (4+ sensor pixels per crop pixel) even the ground truth sent
    through the crop and back scores ~0.87 mIoU, which is not the network's doing."""
    from smpl_depth_ros.net.preprocess import crop_depth, network_input
    rr, cc, inside = crop.sample_indices(depth.shape)
    seen = network_input(crop_depth(depth, crop), crop.median_depth)[1] > 0
    g = np.where(seen & inside, gt_labels[rr, cc], 0)
    return confusion(np.where(seen, crop_labels, 0), g, n)


def miou(conf: np.ndarray) -> float:
    """Mean IoU over the 14 body parts (background excluded) from a confusion matrix."""
    tp = np.diag(conf)
    union = conf.sum(0) + conf.sum(1) - tp
    seen = union[1:] > 0
    return float((tp[1:][seen] / union[1:][seen]).mean())


def sample_surface(vertices: np.ndarray, faces: np.ndarray, n: int,
                   rng: np.random.Generator) -> np.ndarray:
    """(n, 3) points uniformly distributed over a triangle mesh's area."""
    v = np.asarray(vertices, np.float64)
    tri = v[np.asarray(faces)]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    f = rng.choice(len(tri), n, p=area / area.sum())
    a, b = rng.random((2, n))
    flip = a + b > 1
    a, b = np.where(flip, 1 - a, a), np.where(flip, 1 - b, b)
    t = tri[f]
    return t[:, 0] + a[:, None] * (t[:, 1] - t[:, 0]) + b[:, None] * (t[:, 2] - t[:, 0])


def surface_distance(pred_v, pred_f, gt_v, gt_f, n: int = 4000, seed: int = 0
                     ) -> tuple[float, float]:
    """Symmetric surface distance between two meshes of any topology, no alignment:
    both surfaces sampled uniformly by area (n points each), each sample's distance to
    the nearest sample of the other surface (densely sampled, 4n points), both
    directions pooled. Returns (median, mean) in metres."""
    from scipy.spatial import cKDTree
    rng = np.random.default_rng(seed)
    pa, pb = sample_surface(pred_v, pred_f, n, rng), sample_surface(gt_v, gt_f, n, rng)
    da = cKDTree(sample_surface(gt_v, gt_f, 4 * n, rng)).query(pa)[0]
    db = cKDTree(sample_surface(pred_v, pred_f, 4 * n, rng)).query(pb)[0]
    d = np.concatenate([da, db])
    return float(np.median(d)), float(d.mean())


class TrackScore:
    """Multi-person tracking scores over a sequence (CLEAR MOT style).

    Per frame, predicted persons are matched to the true ones by pelvis distance (optimal
    assignment within `max_dist_m`). A true person with at least `min_visible` pixels in
    view must be found; one with fewer (mostly occluded or outside the image) may be
    found: matching it is neither a hit nor a false positive. Counts: hits, misses, false
    positives, ID switches (a true person matched to another ID than at its previous
    match); MOTA = 1 - (misses + false positives + switches) / persons to find; the PVE of
    every hit. `records`: one [frame, true id, pixels in view, 'hit' | 'miss' | 'optional',
    predicted id or -1, PVE mm or None] per true person in view a frame, and one
    [frame, -1, 0, 'false', predicted id, None] per false positive.
    """

    def __init__(self, min_visible: int, max_dist_m: float = 0.5):
        self.min_visible, self.max_dist_m = int(min_visible), float(max_dist_m)
        self.hits = self.misses = self.false_pos = self.switches = self.must = 0
        self.pve: list[float] = []
        self.last_id: dict[int, int] = {}
        self.ids_seen: set[int] = set()
        self.records: list[list] = []
        self._frame = 0

    def add(self, pred_ids, pred_pelvis, pred_vertices, gt_ids, gt_pelvis, gt_vertices,
            visible) -> None:
        from scipy.optimize import linear_sum_assignment
        must = np.asarray(visible) >= self.min_visible
        self.must += int(must.sum())
        present = np.asarray(visible) > 0
        P, G = len(pred_ids), len(gt_ids)
        matched_p, pred_of, err = set(), {}, {}  # pred_of: true person -> its match
        if P and G:
            cost = np.linalg.norm(np.asarray(pred_pelvis)[:, None] -
                                  np.asarray(gt_pelvis)[None], axis=-1)
            cost = np.where(present[None], cost, 1e6)
            rows, cols = linear_sum_assignment(np.minimum(cost, 1e6))
            for r, c in zip(rows, cols):
                if cost[r, c] > self.max_dist_m:
                    continue
                matched_p.add(r)
                pred_of[c] = r
                if not must[c]:
                    continue
                self.hits += 1
                g, pid = int(gt_ids[c]), int(pred_ids[r])
                if g in self.last_id and self.last_id[g] != pid:
                    self.switches += 1
                self.last_id[g] = pid
                err[c] = pve(pred_vertices[r], gt_vertices[c])
                self.pve.append(err[c])
        self.ids_seen.update(int(i) for i in pred_ids)
        f = self._frame
        for c in range(G):
            if not present[c]:
                continue
            r = pred_of.get(c)
            e = round(float(err[c]) * 1000, 2) if c in err else None
            self.records.append([f, int(gt_ids[c]), int(visible[c]),
                                 'optional' if not must[c] else 'hit' if r is not None
                                 else 'miss', -1 if r is None else int(pred_ids[r]), e])
        self.records.extend([f, -1, 0, 'false', int(pred_ids[r]), None]
                            for r in range(P) if r not in matched_p)
        self._frame += 1
        self.misses += int(sum(1 for c in range(G) if must[c] and c not in pred_of))
        self.false_pos += P - len(matched_p)

    def summary(self) -> dict:
        found = self.hits + self.false_pos
        return dict(
            persons_to_find=self.must, hits=self.hits, misses=self.misses,
            false_positives=self.false_pos, id_switches=self.switches,
            recall=self.hits / max(self.must, 1), precision=self.hits / max(found, 1),
            id_switches_per_100=100.0 * self.switches / max(self.hits, 1),
            mota=1.0 - (self.misses + self.false_pos + self.switches) / max(self.must, 1),
            pve_mm=float(np.mean(self.pve) * 1000) if self.pve else float('nan'),
            pve_mm_median=float(np.median(self.pve) * 1000) if self.pve else float('nan'),
            ids_used=len(self.ids_seen))
