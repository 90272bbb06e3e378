"""Input preparation for a real sensor frame (no ROS).

1. Valid pixels in [depth_min, depth_max].
2. The floor removed: RANSAC on a subsample for near-horizontal planes (normal within
   ~40 deg of the image vertical) holding > 3 % of the valid points and spanning > 1 m
   in both in-plane directions (up to two, e.g. floor and a table top).
3. Connected components of what remains, with edges cut at depth jumps > 6 cm between
   neighbouring pixels; a blob is a person candidate when it has enough pixels and a
   plausible 3D size (0.4-2.6 m tall, < 1.6 m wide).
4. Candidates sorted most central first (distance of the blob centroid to the image
   centre); each gets a square crop (1.15 x the larger bbox side) resampled
   (nearest neighbour) to INPUT_SIZE x INPUT_SIZE.
5. Network input: channel 0 = (depth - person median) / 0.5 m for valid pixels within
   +-1 m of the median (0 elsewhere), channel 1 = that validity mask.

`Crop` keeps the mapping back to full-image pixels.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from smpl_depth_ros.net.unet import INPUT_SIZE

NORM_SCALE = 0.5   # metres per unit of normalised depth
NEAR_RANGE = 1.0   # pixels further than this from the person's median depth are dropped


@dataclass
class Crop:
    """A square crop of the full image.

    Attributes:
        u0, v0: full-image pixel (column, row) of the crop's top-left corner (float).
        scale: full-image pixels per crop pixel.
        size: crop side in crop pixels (INPUT_SIZE).
        median_depth: the person's median depth (metres).
        mask: (H, W) bool person blob in the full image (None for training crops).
        exclude: (H, W) bool pixels of other person candidates at least half this one's
            size: hidden from the network and the fit (neighbours at a similar depth),
            while this person's own self-occluding parts (separate blobs, smaller) stay.
    """

    u0: float
    v0: float
    scale: float
    size: int
    median_depth: float
    mask: np.ndarray | None = None
    exclude: np.ndarray | None = None  # (H, W) bool: other (larger) persons' blobs

    def pixel_grid(self) -> tuple[np.ndarray, np.ndarray]:
        """Full-image (rows, cols) float centres of the crop pixels: (S,), (S,)."""
        i = np.arange(self.size) + 0.5
        return self.v0 + i * self.scale - 0.5, self.u0 + i * self.scale - 0.5

    def sample_indices(self, shape) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Nearest full-image pixel of every crop pixel and an in-image mask (S, S)."""
        rows, cols = self.pixel_grid()
        r = np.rint(rows).astype(np.int64)
        c = np.rint(cols).astype(np.int64)
        rr, cc = np.meshgrid(r, c, indexing='ij')
        inside = (rr >= 0) & (rr < shape[0]) & (cc >= 0) & (cc < shape[1])
        return np.clip(rr, 0, shape[0] - 1), np.clip(cc, 0, shape[1] - 1), inside

    def crop_K(self, K: np.ndarray) -> np.ndarray:
        """Intrinsics of the virtual S x S camera that sees exactly this crop."""
        Kc = np.array(K, dtype=np.float64).copy()
        Kc[0, 0] /= self.scale
        Kc[1, 1] /= self.scale
        Kc[0, 2] = (K[0, 2] + 0.5 - self.u0) / self.scale - 0.5
        Kc[1, 2] = (K[1, 2] + 0.5 - self.v0) / self.scale - 0.5
        return Kc


def square_crop(u_min, v_min, u_max, v_max, margin=1.15, size=INPUT_SIZE,
                median_depth=0.0, mask=None) -> Crop:
    side = max(u_max - u_min + 1, v_max - v_min + 1) * margin
    cu, cv = (u_min + u_max + 1) / 2, (v_min + v_max + 1) / 2
    return Crop(u0=cu - side / 2, v0=cv - side / 2, scale=side / size, size=size,
                median_depth=float(median_depth), mask=mask)


def network_input(depth_crop: np.ndarray, median_depth: float) -> np.ndarray:
    """(S, S) metres -> (2, S, S) float32 network input (see module doc)."""
    valid = (depth_crop > 0) & np.isfinite(depth_crop) & \
        (np.abs(depth_crop - median_depth) < NEAR_RANGE)
    x = np.zeros((2,) + depth_crop.shape, np.float32)
    x[0][valid] = (depth_crop[valid] - median_depth) / NORM_SCALE
    x[1] = valid
    return x


def crop_depth(depth: np.ndarray, crop: Crop, only_blob: bool = True) -> np.ndarray:
    """(S, S) depth of the crop (nearest neighbour); with `only_blob`, pixels of other
    person candidates (`crop.exclude`) are zeroed so that neighbours at a similar depth
    do not reach the network or the fit."""
    rr, cc, inside = crop.sample_indices(depth.shape)
    out = depth[rr, cc]
    out[~inside] = 0
    if only_blob and crop.exclude is not None:
        out[crop.exclude[rr, cc]] = 0
    return np.nan_to_num(out, nan=0.0).astype(np.float32)


def _remove_planes(points: np.ndarray, rng: np.random.Generator, max_planes=2,
                   min_fraction=0.03, thresh=0.03, iters=300, min_extent=1.0,
                   min_up=0.75) -> np.ndarray:
    """Boolean mask of points that belong to none of the dominant planes."""
    keep = np.ones(len(points), bool)
    n_all = len(points)
    if n_all < 100:
        return keep
    for _ in range(max_planes):
        idx = np.flatnonzero(keep)
        if len(idx) < 100:
            break
        sub = idx[rng.choice(len(idx), min(len(idx), 4000), replace=False)]
        P = points[sub]
        tri = rng.integers(0, len(P), (iters, 3))
        a, b, c = P[tri[:, 0]], P[tri[:, 1]], P[tri[:, 2]]
        n = np.cross(b - a, c - a)
        nn = np.linalg.norm(n, axis=1)
        ok = nn > 1e-6
        if not ok.any():
            break
        n, a = n[ok] / nn[ok, None], a[ok]
        # Floor-like planes only (normal within ~40 deg of the image's vertical): people
        # are cut from walls by depth jumps, but stand on the floor; side by side, several
        # people at one depth would look like a wall.
        up = np.abs(n[:, 1]) > min_up
        if not up.any():
            break
        n, a = n[up], a[up]
        d = np.abs(np.einsum('hnk,hk->hn', P[None] - a[:, None], n))
        counts = (d < thresh).sum(1)
        best = int(np.argmax(counts))
        dist = np.abs((points[idx] - a[best]) @ n[best])
        inl = dist < thresh
        if inl.sum() < min_fraction * n_all:
            break
        # Only scene-sized planes (floor, walls): both in-plane extents > min_extent m.
        # A person's torso is planar-ish too, but never that large.
        e1 = np.cross(n[best], [1.0, 0, 0] if abs(n[best][0]) < 0.9 else [0, 1.0, 0])
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(n[best], e1)
        q = points[idx[inl]]
        u, v = q @ e1, q @ e2
        lo_u, hi_u, lo_v, hi_v = (np.percentile(u, 2), np.percentile(u, 98),
                                  np.percentile(v, 2), np.percentile(v, 98))
        if min(hi_u - lo_u, hi_v - lo_v) < min_extent:
            break
        # A floor fills its extent; a thin horizontal slice through several people at
        # one height does not (it is a few short segments): require >= 35 % of 10 cm cells.
        cu = ((u - lo_u) / 0.1).astype(np.int64)
        cv = ((v - lo_v) / 0.1).astype(np.int64)
        ok2 = (cu >= 0) & (cv >= 0) & (u <= hi_u) & (v <= hi_v)
        cells = len(set(zip(cu[ok2].tolist(), cv[ok2].tolist())))
        if cells < 0.35 * ((hi_u - lo_u) / 0.1 + 1) * ((hi_v - lo_v) / 0.1 + 1):
            break
        keep[idx[inl]] = False
    return keep


def find_persons(depth: np.ndarray, K: np.ndarray, depth_min: float, depth_max: float,
                 min_pixels: int = 400, max_persons: int = 5, seed: int = 0) -> list[Crop]:
    """Person candidates in a depth image, most central first.

    Args:
        depth: (H, W) float32 metres (0/NaN invalid).
        K: (3, 3) intrinsics.

    Returns:
        Crops (with `mask`), at most max_persons.
    """
    H, W = depth.shape
    d = np.nan_to_num(depth, nan=0.0)
    valid = (d >= depth_min) & (d <= depth_max)
    # Subsample for plane removal (every 2nd pixel each way is plenty).
    r, c = np.nonzero(valid)
    if len(r) < min_pixels:
        return []
    z = d[r, c].astype(np.float64)
    pts = np.stack([(c - K[0, 2]) * z / K[0, 0], (r - K[1, 2]) * z / K[1, 1], z], 1)
    keep = _remove_planes(pts, np.random.default_rng(seed))
    fg = np.zeros_like(valid)
    fg[r[keep], c[keep]] = True
    # Cut edges at depth discontinuities: a pixel is an edge if a 4-neighbour differs by
    # more than 6 cm (scaled with depth: Kinect quantisation grows with z^2).
    jump = 0.06 * np.maximum(d / 3.0, 1.0) ** 2
    edge = np.zeros_like(fg)
    dv = np.abs(np.diff(d, axis=0)) > jump[1:]
    dh = np.abs(np.diff(d, axis=1)) > jump[:, 1:]
    edge[1:] |= dv
    edge[:-1] |= dv
    edge[:, 1:] |= dh
    edge[:, :-1] |= dh
    lab, n = ndimage.label(fg & ~edge)
    if n == 0:
        return []
    idx = np.arange(1, n + 1)
    sizes = ndimage.sum_labels(np.ones_like(lab), lab, index=idx)
    meds = ndimage.median(d, lab, index=idx)
    slices = ndimage.find_objects(lab)
    crops = []
    used = np.zeros(n + 1, bool)
    for k in np.argsort(-sizes):
        if sizes[k] < min_pixels:
            break
        if used[k + 1]:
            continue
        # Self-occlusion (an arm in front of the torso) cuts a person into several
        # components: merge the smaller ones inside the (expanded) box at a similar depth.
        sl = slices[k]
        r0, r1, c0, c1 = sl[0].start, sl[0].stop, sl[1].start, sl[1].stop
        pad_r, pad_c = (r1 - r0) // 8 + 2, (c1 - c0) // 4 + 2
        box = lab[max(r0 - pad_r, 0):r1 + pad_r, max(c0 - pad_c, 0):c1 + pad_c]
        near = [j for j in np.unique(box) if j > 0 and j != k + 1 and not used[j]
                and sizes[j - 1] < 0.6 * sizes[k] and abs(meds[j - 1] - meds[k]) < 0.3]
        m = np.isin(lab, [k + 1] + near)
        rr, cc = np.nonzero(m)
        zz = d[rr, cc]
        med = float(np.median(zz))
        P = np.stack([(cc - K[0, 2]) * zz / K[0, 0], (rr - K[1, 2]) * zz / K[1, 1], zz], 1)
        lo, hi = np.percentile(P, 2, axis=0), np.percentile(P, 98, axis=0)
        height, width = hi[1] - lo[1], max(hi[0] - lo[0], hi[2] - lo[2])
        if not (0.4 <= height <= 2.6 and width <= 1.6):
            continue
        used[[k + 1] + near] = True
        # Grow back the edge pixels adjacent to the blob at similar depth.
        grown = ndimage.binary_dilation(m, iterations=3) & valid & (np.abs(d - med) < 0.8)
        crops.append((float(np.hypot(cc.mean() - W / 2, rr.mean() - H / 2)),
                      square_crop(cc.min(), rr.min(), cc.max(), rr.max(), median_depth=med,
                                  mask=grown)))
        if len(crops) >= 3 * max_persons:
            break
    crops.sort(key=lambda t: t[0])
    crops = [c for _, c in crops[:max_persons]]
    sizes = [int(c.mask.sum()) for c in crops]
    for i, c in enumerate(crops):
        others = [crops[j].mask for j in range(len(crops))
                  if j != i and sizes[j] >= 0.5 * sizes[i]]
        if others:
            c.exclude = np.logical_or.reduce(others) & ~c.mask
    return crops
