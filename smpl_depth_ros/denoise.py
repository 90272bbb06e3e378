"""Noise-adaptive, edge-preserving smoothing of depth images (no ROS).

Everything after it reads single pixels: person finding compares neighbours across
depth jumps, the network reads the crop's depths pixel by pixel (sampled by nearest
neighbour), the fit back-projects them. Its thresholds and the networks were made for
the noise of a Kinect v1 (`sensor_noise`); a stereo camera far away has several times
that (sigma grows as z^2: a D435 at 3 m 3-6 cm against a Kinect's 1.4), and per-pixel
noise of that size buries the body's relief of a few centimetres: the network's labels
fall apart, person finding cuts the body into pieces.

`smooth(depth, noise)` averages each pixel with its neighbours along its row, then
along its column, that lie within K_SIGMA sigma(z) of it (of the row pass's result, for
the column pass): a depth edge (a silhouette, an arm in front of the chest by more than
that) is kept, a surface's noise is averaged. The window is as wide as it must be to
bring per-pixel noise down to what the defaults were tuned for, EXCESS_OVER x a Kinect
v1's sigma at that depth: radius r = ceil((sigma / target - 1) / 2) each way (a
(2r + 1)^2 window divides white noise by 2r + 1), at most MAX_RADIUS, from a noise
SMOOTH_FROM times the target on. Below that nothing changes: the `auto` estimate of a
Kinect v1's own frames reads up to 1.14 times the target over a run of people at 1-5 m
(1.26 in single frames at 1.2 m), so a Kinect v1 or a time-of-flight camera is left as
it is beyond about 1.5 m; nearer, where their estimate holds the person's own curved
surfaces and a Kinect v1's sigma is small, it can read 1.3-1.7 and a 3 x 3 window is
applied (the sensor sweep's 1.0-1.5 m bins: Kinect v1 59.5 -> 59.2 mm, Kinect v2 34.5
-> 31.9). Noise correlated over a
few pixels (block matching) is averaged less, but helped too (`docs/EXPERIMENTS.md`).
"""
from __future__ import annotations

import numpy as np

from smpl_depth_ros.sensor_noise import EXCESS_OVER, NoiseModel, kinect_v1_sigma

K_SIGMA = 2.5   # neighbours farther than this many sigma from the pixel are an edge
MAX_RADIUS = 3  # widest window: 7 x 7
SMOOTH_FROM = 1.3  # smoothing starts at this multiple of the noise the defaults assume
TABLE_STEP_M = 0.01  # sigma and radius are looked up per centimetre of depth


def _tables(depth: np.ndarray, noise: NoiseModel) -> tuple[np.ndarray, np.ndarray]:
    """sigma (float32) and the window radius its noise asks for (int8; 0: left as it is,
    and at index 0, invalid pixels), per TABLE_STEP_M of depth up to `depth`'s largest."""
    zmax = float(depth.max()) if depth.size else 0.0
    zs = np.maximum(np.arange(0.0, zmax + 2 * TABLE_STEP_M, TABLE_STEP_M), TABLE_STEP_M)
    sig = noise(zs)
    ratio = sig / (EXCESS_OVER * kinect_v1_sigma(zs))
    r = np.clip(np.ceil((ratio - 1.0) / 2.0), 0, MAX_RADIUS).astype(np.int8)
    r[ratio < SMOOTH_FROM] = 0
    r[0] = 0
    return sig.astype(np.float32), r


def _index(depth: np.ndarray) -> np.ndarray:
    """Each pixel's row of the `_tables` (0 for invalid pixels)."""
    return np.rint(np.where(depth > 0, depth, 0.0) / TABLE_STEP_M).astype(np.int32)


def radius_map(depth: np.ndarray, noise: NoiseModel) -> np.ndarray:
    """Per pixel, the window radius its noise asks for (0: left as it is; int8)."""
    return _tables(depth, noise)[1][_index(depth)]


def _pass(z: np.ndarray, r: np.ndarray, thr: np.ndarray, axis: int) -> np.ndarray:
    """One direction's edge-preserving mean: each pixel with its valid neighbours up to
    r[pixel] away along `axis` that lie within thr[pixel] of it."""
    acc = z.copy()
    cnt = (z > 0).astype(np.float32)
    n = z.shape[axis]
    diff = np.empty_like(z)
    for k in range(1, int(r.max()) + 1):
        if k >= n:
            break
        near = r >= k
        for a, b in ((slice(0, n - k), slice(k, n)), (slice(k, n), slice(0, n - k))):
            dst, src = ((a, slice(None)), (b, slice(None))) if axis == 0 else \
                ((slice(None), a), (slice(None), b))
            nb, d = z[src], diff[dst]
            np.subtract(nb, z[dst], out=d)
            np.abs(d, out=d)
            ok = (d < thr[dst]) & (nb > 0) & near[dst]
            acc[dst] += nb * ok
            cnt[dst] += ok
    return np.where(z > 0, acc / np.maximum(cnt, 1.0), 0.0).astype(np.float32)


def smooth(depth: np.ndarray, noise: NoiseModel | None) -> np.ndarray:
    """`depth` (H, W metres, 0 invalid) smoothed where `noise` exceeds the defaults'
    (see the module doc); the same array when nothing needs it. Validity is unchanged."""
    if noise is None or not noise.z:
        return depth
    sig_t, r_t = _tables(depth, noise)
    if not r_t.any():  # (a quiet sensor: no depth in view asks for a window)
        return depth
    idx = _index(depth)
    r = r_t[idx]
    if not r.any():
        return depth
    rows = np.flatnonzero(r.any(axis=1))
    cols = np.flatnonzero(r.any(axis=0))
    R = int(r.max())
    # the window that holds every pixel to change, and the neighbours they read
    r0, r1 = max(rows[0] - R, 0), min(rows[-1] + R + 1, depth.shape[0])
    c0, c1 = max(cols[0] - R, 0), min(cols[-1] + R + 1, depth.shape[1])
    z = np.asarray(depth[r0:r1, c0:c1], np.float32)
    rr = r[r0:r1, c0:c1]
    thr = K_SIGMA * sig_t[idx[r0:r1, c0:c1]]  # sigma looked up in the window only
    out = _pass(_pass(z, rr, thr, axis=1), rr, thr, axis=0)
    res = np.array(depth, np.float32, copy=True)
    res[r0:r1, c0:c1] = out
    return res.astype(depth.dtype, copy=False)
