"""Input preparation for a real sensor frame (no ROS).

Person detection (steps 1-3) runs on the depth image decimated by nearest neighbour to
about DETECT_WIDTH pixels wide (every s-th pixel each way, s = round(W / DETECT_WIDTH);
pixel counts such as min_pixels scale by 1 / s^2); boxes and masks are full-image pixels.

1. Valid pixels in [depth_min, depth_max].
2. The floor removed: RANSAC (hypotheses scored preemptively on random subsamples) for
   near-horizontal planes (normal within ~40 deg of the image vertical) holding > 3 % of
   the valid points and spanning > 1 m in both in-plane directions (up to two, e.g. floor
   and a table top).
3. Connected components of what remains, cut at depth jumps > 6 cm between neighbouring
   pixels (on the jump's far side: a person keeps their border pixels); smaller
   components at a similar depth near a component's box are merged into it
   (self-occlusion), and so is a component of similar size stacked above or below it (an
   arm across the waist); a blob is a person candidate when it has enough
   pixels and a plausible 3D size (0.4-2.6 m tall, < 1.6 m wide). When no blob is (or,
   with `peel`, when none of them proved to be a person), the planes of any orientation
   are peeled off the large ones and step 3 runs again (a person close to a wall).
4. A candidate's mask: its blob's s x s pixel blocks, grown by ~GROW_PX pixels, where the
   depth is valid and within GROW_DEPTH of the blob's median depth.
5. Candidates sorted most central first (distance of the blob centroid to the image
   centre), those seen through a gap of a nearer candidate (`Crop.behind`) last; the
   first `max_persons` of them are kept, and the `nearest` nearest of the others; each
   gets a square crop (1.15 x the larger bbox side) resampled (nearest neighbour) to
   INPUT_SIZE x INPUT_SIZE.
6. Network input: channel 0 = (depth - person median) / 0.5 m for valid pixels within
   +-1 m of the median (0 elsewhere), channel 1 = that validity mask.

`Crop` keeps the mapping back to full-image pixels.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from smpl_depth_ros.net.unet import INPUT_SIZE

NORM_SCALE = 0.5   # metres per unit of normalised depth
NEAR_RANGE = 1.0   # pixels further than this from the person's median depth are dropped
DETECT_WIDTH = 320  # person detection runs on the image decimated to about this width
GROW_PX = 3         # a person mask reaches this many pixels past its blob ...
GROW_DEPTH = 0.8    # ... at most this far from the person's median depth (metres)
FLOOR_UP = 0.75     # a floor-like plane's normal: |its image-vertical component| above this
ALONE_SHARE = 0.6  # a component this big a share of its merged group is also tried alone
MERGE_GAP_M = 0.1  # a smaller piece merged into a component, when at least FAR_PIECE_SHARE
FAR_PIECE_SHARE = 0.15  # of its size, comes this near it (or a piece merged) in the image
FLOOR_STRIP_M = (0.5, 1.8)  # second look: a floor-like plane this deep and wide (m) is floor
CELL_M = 0.1       # a plane's occupancy is counted on cells this wide (m)
OCCLUDER_M = 0.1   # ... an empty cell this far behind the surface seen there is hidden
SAME_PLANE_COS = math.cos(math.radians(10.0))  # a plane this near in orientation ...
SAME_PLANE_M = 0.15  # ... and offset to one already removed is the same surface


@dataclass
class Crop:
    """A square crop of the full image.

    Attributes:
        u0, v0: full-image pixel (column, row) of the crop's top-left corner (float).
        scale: full-image pixels per crop pixel.
        size: crop side in crop pixels (INPUT_SIZE).
        median_depth: the person's median depth (metres).
        mask: (H, W) bool person mask in the full image (the grown blob, see the module
            doc; None for training crops).
        exclude: (H, W) bool pixels of other person candidates at least half this one's
            size: hidden from the network and the fit (neighbours at a similar depth),
            while this person's own self-occluding parts (separate blobs, smaller) stay.
        behind: the blob lies inside a nearer candidate's box and at least 0.3 m behind
            it: most likely background seen between its legs or arms; ranked last.
        nearest: kept as one of the nearest candidates beyond the most central ones
            (find_persons' `nearest`): looked at after those.
        planes: the scene planes removed in the frame (the floor, a table top; walls
            peeled off a person), each a (4,) array (n, offset): n . x = offset in the
            camera frame, unit n pointing to the camera's side.
    """

    u0: float
    v0: float
    scale: float
    size: int
    median_depth: float
    mask: np.ndarray | None = None
    exclude: np.ndarray | None = None  # (H, W) bool: other (larger) persons' blobs
    behind: bool = False  # seen through a gap of a nearer candidate (see find_persons)
    nearest: bool = False  # kept for being near, beyond the most central (find_persons)
    planes: tuple = ()  # the frame's scene planes (see find_persons)

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


def split_side_by_side(crop: Crop, K: np.ndarray, min_dip_m: float = 0.2,
                       min_width_m: float = 0.25) -> list[Crop]:
    """Two people side by side at the same depth, touching, form one blob: split it where
    the top of its silhouette dips lowest between two high points (heads), if the dip is at
    least `min_dip_m` below the lower of the two and each side is at least `min_width_m`
    wide. Returns the two crops (each excluding the other) or [] when no such dip exists.
    Used only for candidates whose single-body fit was rejected, so a raised arm beside the
    head (the same profile) never splits a person whose fit is good."""
    m = crop.mask
    if m is None or not m.any():
        return []
    H, W = m.shape
    cols = np.flatnonzero(m.any(0))
    c0, c1 = int(cols[0]), int(cols[-1]) + 1
    sub = m[:, c0:c1]
    top = np.where(sub.any(0), sub.argmax(0), H).astype(np.float64)  # first row per column
    px_per_m = K[1, 1] / max(crop.median_depth, 0.1)
    # Smooth over ~5 cm so single ragged columns do not make peaks or dips.
    k = max(1, int(round(0.05 * K[0, 0] / max(crop.median_depth, 0.1))))
    top = ndimage.uniform_filter1d(top, 2 * k + 1, mode='nearest')
    n = len(top)
    wmin = int(math.ceil(min_width_m * K[0, 0] / max(crop.median_depth, 0.1)))
    if n < 2 * wmin:
        return []
    best, best_c = 0.0, -1
    peak_l = np.minimum.accumulate(top)            # highest point left of (and at) c
    peak_r = np.minimum.accumulate(top[::-1])[::-1]
    for c in range(wmin, n - wmin):
        dip = (top[c] - max(peak_l[c], peak_r[c])) / px_per_m  # metres below the lower peak
        if dip > best:
            best, best_c = dip, c
    if best < min_dip_m:
        return []
    split = c0 + best_c
    parts = []
    for lo, hi in ((0, split), (split, W)):
        pm = np.zeros_like(m)
        pm[:, lo:hi] = m[:, lo:hi]
        rr, cc = np.nonzero(pm)
        if len(rr) == 0:
            return []
        parts.append(square_crop(cc.min(), rr.min(), cc.max(), rr.max(),
                                 median_depth=crop.median_depth, mask=pm))
    a, b = parts
    ex = crop.exclude if crop.exclude is not None else np.zeros_like(m)
    a.exclude, b.exclude = ex | b.mask, ex | a.mask
    return parts


def pixel_points(rows, cols, z, K) -> np.ndarray:
    """Full-image pixels (row, col) with depth z -> (N, 3) float64 camera-frame points."""
    z = z.astype(np.float64)
    return np.stack([(cols - K[0, 2]) * z / K[0, 0], (rows - K[1, 2]) * z / K[1, 1], z], 1)


def _scene_sized(q: np.ndarray, n: np.ndarray, min_extent: float,
                 strip: tuple[float, float] | None = None, view=None) -> bool:
    """Whether plane inliers `q` (normal `n`) form a scene-sized plane (floor, wall): both
    in-plane extents > min_extent m (a person's torso is planar-ish too, but never that
    large), and filling that extent: a thin horizontal slice through several people at
    one height is a few short segments, so >= 35 % of its 10 cm cells must be occupied.
    `strip` (short, long): a floor-like plane (normal within ~40 deg of the image's
    vertical) also counts when its extents pass these instead: the strip of floor seen
    between the camera's view and a wall a metre behind a person.
    `view` (depth, K, s): the (decimated) depth image the points come from. Then only the
    cells the camera could see count: an empty cell outside the image, on an invalid
    pixel or behind a nearer surface (the person standing on the floor, the legs of a
    table) is unknown rather than empty; a cell the camera sees through (the wall behind a
    slice through people) stays empty."""
    e1 = np.cross(n, [1.0, 0, 0] if abs(n[0]) < 0.9 else [0, 1.0, 0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    u, v = q @ e1, q @ e2
    (lo_u, hi_u), (lo_v, hi_v) = np.percentile(u, (2, 98)), np.percentile(v, (2, 98))
    short, long_ = sorted((hi_u - lo_u, hi_v - lo_v))
    floor_strip = strip is not None and abs(n[1]) > FLOOR_UP and short >= strip[0] \
        and long_ >= strip[1]
    if short < min_extent and not floor_strip:
        return False
    cu = ((u - lo_u) / CELL_M).astype(np.int64)
    cv = ((v - lo_v) / CELL_M).astype(np.int64)
    ok = (cu >= 0) & (cv >= 0) & (u <= hi_u) & (v <= hi_v)
    occupied = np.zeros((int((hi_u - lo_u) / CELL_M) + 1, int((hi_v - lo_v) / CELL_M) + 1),
                        bool)
    occupied[cu[ok], cv[ok]] = True
    cells = occupied.size
    if view is not None:
        cells -= np.count_nonzero(_unseen_cells(~occupied, float(np.mean(q @ n)), n, e1, e2,
                                                lo_u, lo_v, view))
    return occupied.sum() >= 0.35 * cells


def _unseen_cells(empty: np.ndarray, offset: float, n, e1, e2, lo_u: float, lo_v: float,
                  view) -> np.ndarray:
    """Of a plane's empty 10 cm cells (`empty`, indexed from (lo_u, lo_v) along e1, e2),
    those the camera cannot see: their centre projects outside the image or onto an
    invalid pixel, or lies more than OCCLUDER_M behind the surface seen there."""
    depth, K, s = view
    i, j = np.nonzero(empty)
    centre = offset * np.asarray(n) + np.outer(lo_u + (i + 0.5) * CELL_M, e1) + \
        np.outer(lo_v + (j + 0.5) * CELL_M, e2)
    z = centre[:, 2]
    front = z > 1e-3
    zs = np.where(front, z, 1.0)
    c = np.rint((K[0, 0] * centre[:, 0] / zs + K[0, 2]) / s).astype(np.int64)
    r = np.rint((K[1, 1] * centre[:, 1] / zs + K[1, 2]) / s).astype(np.int64)
    inside = front & (r >= 0) & (c >= 0) & (r < depth.shape[0]) & (c < depth.shape[1])
    seen = np.zeros(len(z), np.float64)
    seen[inside] = depth[r[inside], c[inside]]
    unseen = ~inside | ~(seen > 0) | (seen < z - OCCLUDER_M)
    out = np.zeros_like(empty)
    out[i[unseen], j[unseen]] = True
    return out


def _remove_planes(points: np.ndarray, rng: np.random.Generator, max_planes=2,
                   min_fraction=0.03, thresh=0.03, iters=1000, min_extent=1.0,
                   min_up=FLOOR_UP, sample=2000, presample=200, finalists=10,
                   local_k=16, planes: list | None = None, noise=None,
                   strip: tuple[float, float] | None = None, view=None) -> np.ndarray:
    """Boolean mask of points that belong to none of the dominant planes.

    RANSAC over `iters` point triples per plane (half of them local: a point and two of
    its `local_k` nearest neighbours); a floor-like patch too small for a scene plane is
    looked past (up to 3 of them); hypotheses are scored preemptively: all on
    `presample` random points, the best `finalists` on `sample` random points. The planes
    removed are appended to `planes` (when given) as (4,) arrays (n, offset), n . x =
    offset, unit n towards the camera (the side the scene is seen from). `noise`: an
    optional excess noise e(z) (sensor_noise.NoiseModel.excess): a point's inlier band
    is then thresh + 2 e(its depth). `strip`, `view`: see `_scene_sized`.
    """
    keep = np.ones(len(points), bool)
    if noise is not None and len(points):
        thresh = thresh + 2.0 * noise(points[:, 2])
    n_all = len(points)
    if n_all < 100:
        return keep
    # Points a hypothesis may come from: not removed, and not on a floor-like patch found
    # too small for a scene plane (a box top): the floor may hold fewer points than it,
    # and stopping there left the floor in, and the person standing on it merged with it
    # (val_s2 frame 86).
    avail = keep.copy()
    found = 0
    accepted: list[np.ndarray] = []  # the planes removed, (n, offset) facing the camera
    for _ in range(max_planes + 6):  # up to 3 patches looked past, 3 planes found again
        if found == max_planes:
            break
        idx = np.flatnonzero(avail)
        if len(idx) < 100:
            break
        pick_ = idx[rng.choice(len(idx), min(len(idx), sample), replace=False)]
        P = points[pick_]
        tP = thresh[pick_] if np.ndim(thresh) else thresh
        tri = rng.integers(0, len(P), (iters, 3))
        # Half the triples local (two of a point's nearest neighbours in the sample): a
        # floor that fills 10 % of the view gives an all-floor random triple once in a
        # thousand, a local one every ten or so.
        k = min(local_k, len(P) - 1)
        if k >= 2:
            h = iters // 2
            nb = cKDTree(P).query(P[tri[:h, 0]], k=k + 1)[1][:, 1:]
            pick = rng.integers(0, k, (h, 2))
            pick[:, 1] = (pick[:, 0] + 1 + rng.integers(0, k - 1, h)) % k
            tri[:h, 1:] = np.take_along_axis(nb, pick, 1)
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
        n, off = n[up], (a[up] * n[up]).sum(1)  # plane: x . n = off
        tpre = tP[:presample, None] if np.ndim(tP) else tP
        dist = P[:presample] @ n.T
        dist -= off
        pre = np.count_nonzero(np.abs(dist, out=dist) < tpre, axis=0)
        top = np.argsort(-pre)[:finalists]
        tfin = tP[:, None] if np.ndim(tP) else tP
        best = top[np.argmax((np.abs(P @ n[top].T - off[top]) < tfin).sum(0))]
        nb_, ob_ = n[best], off[best]
        near = np.abs(points @ nb_ - ob_) < thresh
        q = points[keep & near]
        if len(q) < min_fraction * n_all:
            break
        # Least squares on the inliers (a sample of them): three points fix a plane
        # only to their noise, centimetres over a floor's extent.
        qs = q[rng.choice(len(q), min(len(q), 4000), replace=False)]
        nl = np.linalg.svd(qs - qs.mean(0), full_matrices=False)[2][2]
        if abs(nl[1]) > min_up:
            nb_, ob_ = nl, float(qs.mean(0) @ nl)
            near = np.abs(points @ nb_ - ob_) < thresh
            q = points[keep & near]
        if not _scene_sized(q, nb_, min_extent, strip, view):
            avail &= ~near  # look past it
            continue
        keep &= ~near
        avail &= ~near
        n_b, off_b = (nb_, ob_) if ob_ < 0 else (-nb_, -ob_)
        if any(abs(float(n_b @ a[:3])) > SAME_PLANE_COS and
               abs(off_b - a[3]) < SAME_PLANE_M for a in accepted):
            # The noise beyond the inlier band of a plane already removed (a far wall
            # seen by a stereo camera): the same surface, which takes no further plane's
            # place (the floor a person stands on was left in their blob).
            continue
        found += 1
        accepted.append(np.array([*n_b, off_b]))
        if planes is not None:
            planes.append(accepted[-1])
    return keep


def _any_last(a: np.ndarray) -> np.ndarray:
    """`a.any(-1)` for a short last axis, as an OR of its slices (numpy's reduction
    over an axis of 2 or 3 is ~30x slower)."""
    out = a[..., 0].copy()
    for k in range(1, a.shape[-1]):
        out |= a[..., k]
    return out


def _depth_edges(depth: np.ndarray, s: int, noise=None) -> tuple[np.ndarray, np.ndarray]:
    """Edges at depth discontinuities on the image decimated by s: two (ceil(H/s),
    ceil(W/s)) maps, (far side, both sides).

    A jump of more than 6 cm (scaled with depth: Kinect quantisation grows with z^2;
    invalid pixels count as 0) between neighbouring full-image pixels, in a row or a
    column, lies between two decimated pixels. The first map marks the farther of the
    two (an invalid one counts as the farthest): every jump on the way between two
    decimated 4-neighbours cuts them apart, and the nearer surface, a person in front of
    the scene, keeps its border pixels. The second marks the decimated pixel nearer the
    jump in the image, both when as near (with s <= 2, the pixels on both sides of every
    jump): a blob's pixels off any jump, whose depths are the surface's own (no mixed or
    flying pixels at the silhouette). Person finding cuts components with the first
    (cut with the second, a limb two or three pixels wide, a person beyond 3.5 m at
    320x288, lost every pixel and the body fell into pieces too small to be a
    candidate) and measures a blob with the second (`_group_blob`).
    With an excess noise e(z) (`noise`: sensor_noise.NoiseModel.excess) the jump grows by
    3 e(z) (a noisier sensor's surfaces would otherwise fall apart into fragments).
    `depth`: metres, invalid pixels 0 (no NaN).
    """
    def marks(lines):  # (n, L) full-image lines -> 2 x (n, ceil(L / s)) edges on them
        n, length = lines.shape
        m = -(-length // s)
        jump = np.zeros((n, m * s), bool)  # [:, j]: between pixels j and j + 1
        step = np.abs(np.diff(lines, axis=1))
        thr = 0.06 * np.maximum(lines[:, 1:] / 3.0, 1.0) ** 2
        big = step > thr
        if noise is not None:
            # The noise only raises the threshold: it is needed where the jump passes
            # the noiseless one (a few per cent of the pixels), not everywhere.
            i, j = np.nonzero(big)
            far = np.maximum(lines[i, j + 1], lines[i, j])
            big[i, j] = step[i, j] > thr[i, j] + 3.0 * noise(far)
        jump[:, :length - 1] = big
        jump = jump.reshape(n, m, s)  # [:, c, i]: between pixels c * s + i and c * s + i + 1
        both = _any_last(jump[:, :, :(s + 1) // 2])  # i <= (s - 1) / 2: nearer to pixel c
        both[:, 1:] |= _any_last(jump[:, :-1, s // 2:])  # i >= (s - 1) / 2: nearer to c + 1
        cut = _any_last(jump[:, :-1])  # a jump between decimated pixels c and c + 1
        z = lines[:, ::s]
        z = np.where(z > 0, z, np.inf)
        c_farther = z[:, :-1] >= z[:, 1:]
        far_side = np.zeros((n, m), bool)
        far_side[:, :-1] = cut & c_farther
        far_side[:, 1:] |= cut & ~c_farther
        return far_side, both

    rows, cols = marks(depth[::s]), marks(depth[:, ::s].T)
    return rows[0] | cols[0].T, rows[1] | cols[1].T


def fill_small_holes(depth: np.ndarray, radius: int = 2) -> np.ndarray:
    """Invalid pixels inside the valid region's closing by a (2 radius + 1) square take
    their nearest valid pixel's depth: the speckle-filter holes and dropouts of a stereo
    camera (a few per cent of a body's pixels) would otherwise each make a depth edge and
    cut thin limbs off in person finding. Gaps wider than 2 radius stay."""
    valid = depth > 0
    # The closing by a square as two separable rank filters (outside the image counts as
    # valid, as binary_closing's border_value=1): the same pixels, 3x faster.
    k = 2 * radius + 1
    closed = ndimage.minimum_filter(ndimage.maximum_filter(
        valid.view(np.uint8), size=k, mode='constant', cval=1),
        size=k, mode='constant', cval=1).view(bool)
    holes = closed & ~valid
    if not holes.any():
        return depth
    idx = ndimage.distance_transform_edt(~valid, return_distances=False, return_indices=True)
    out = depth.copy()
    out[holes] = depth[idx[0][holes], idx[1][holes]]
    return out


def _label_medians(values: np.ndarray, labels: np.ndarray, sizes: np.ndarray) -> np.ndarray:
    """Median of `values` over each label, all labels in one sort (as ndimage.median).

    Args:
        values, labels: arrays of one shape; label 0 is ignored, labels 1..n all occur
            (as ndimage.label numbers them).
        sizes: (n + 1,) pixel count of each label 0..n (np.bincount of labels).

    Returns:
        (n + 1,) float64 medians (entry 0 meaningless).
    """
    fg = labels > 0
    v = values[fg].astype(np.float64)
    lo, span = v.min(), v.max() - v.min() + 1.0
    key = np.sort(labels[fg] + (v - lo) / span)  # label + value mapped into [0, 1)
    counts = sizes[1:]
    start = np.cumsum(counts) - counts
    middle = np.stack([key[start + (counts - 1) // 2], key[start + counts // 2]])
    medians = np.zeros(len(sizes))
    medians[1:] = lo + span * (middle - np.floor(middle)).mean(0)
    return medians


def enclosed_share(inner: np.ndarray, outer: np.ndarray) -> float:
    """The share of the pixels of mask `inner` in image rows where mask `outer` has pixels
    both left and right of all of inner's: a blob seen through a gap of a nearer one (the
    wall between a person's legs or between an arm and the torso) is enclosed, a person
    standing beside a nearer one, partly overlapping their outline, is not."""
    rows = np.flatnonzero(inner.any(1))
    if not len(rows):
        return 0.0
    a, b = inner[rows], outer[rows]
    w = a.shape[1]
    a_first, a_last = a.argmax(1), w - 1 - a[:, ::-1].argmax(1)
    has = b.any(1)
    b_first, b_last = b.argmax(1), w - 1 - b[:, ::-1].argmax(1)
    inside = has & (b_first < a_first) & (b_last > a_last)
    n = a.sum(1)
    return float(n[inside].sum() / max(int(n.sum()), 1))


BEHIND_GAP_M = 0.3  # a blob seen through a gap of a nearer one lies this far or more behind


def _mark_behind(crops: list[Crop], margin: float = 0.05, gap_m: float = BEHIND_GAP_M
                 ) -> None:
    """Flag candidates whose blob box lies inside a nearer candidate's box (grown by
    `margin` of its size) and `gap_m` or more behind it: the wall or floor seen between a
    person's legs, or between an arm and the torso, is a blob of its own, sometimes of a
    plausible size, and the network sees the person's outline around it."""
    boxes = []
    for c in crops:
        rows, cols = np.flatnonzero(c.mask.any(1)), np.flatnonzero(c.mask.any(0))
        boxes.append((rows[0], rows[-1], cols[0], cols[-1]))
    for i, c in enumerate(crops):
        r0, r1, c0, c1 = boxes[i]
        for j, o in enumerate(crops):
            if j == i or o.median_depth > c.median_depth - gap_m:
                continue
            R0, R1, C0, C1 = boxes[j]
            mr, mc = margin * (R1 - R0 + 1), margin * (C1 - C0 + 1)
            if r0 >= R0 - mr and r1 <= R1 + mr and c0 >= C0 - mc and c1 <= C1 + mc:
                c.behind = True
                break


def _keep(crops: list[Crop], n: int, nearest: int) -> list[Crop]:
    """The `n` first candidates (ordered most central first, those behind last) and the
    `nearest` nearest of the others (flagged `Crop.nearest`), in that order. Central
    alone, a far wall that noisy stereo depth breaks into person-sized pieces can fill
    every place, and a person near the camera at the image side is never looked at (a
    RealSense D435 scene of three people: one missed for 65 frames)."""
    if len(crops) <= n:
        return crops
    near = sorted(crops[n:], key=lambda c: (c.behind, c.median_depth))[:nearest]
    for c in near:
        c.nearest = True
    return crops[:n] + [c for c in crops[n:] if c.nearest]


def _stacked(a: tuple[slice, slice], b: tuple[slice, slice], min_overlap: float = 0.2
             ) -> bool:
    """Two component boxes (row, column slices) one above the other: their centres are
    further apart in rows than in columns, and their columns overlap by at least
    `min_overlap` of the narrower one."""
    def centre(x):
        return (x.start + x.stop) / 2
    cols = min(a[1].stop, b[1].stop) - max(a[1].start, b[1].start)
    narrow = min(a[1].stop - a[1].start, b[1].stop - b[1].start)
    return (abs(centre(a[0]) - centre(b[0])) > abs(centre(a[1]) - centre(b[1]))
            and cols >= min_overlap * narrow)


def _upper_is_nearer(a, b) -> bool:
    """Of two (box slices, median depth) components, the one whose box centre is higher
    in the image is the nearer one."""
    def centre_row(c):
        return (c[0][0].start + c[0][0].stop) / 2
    upper, lower = (a, b) if centre_row(a) < centre_row(b) else (b, a)
    return upper[1] < lower[1]


def _group_blob(group, lab, slices, d, n, grow, s, K, core=None):
    """The decimated blob of components `group`, when it has a person's 3D size
    (0.4-2.6 m tall, < 1.6 m wide; from at most 2000 of its pixels). `core`: the
    decimated pixels off any depth jump (`_depth_edges`); the blob is the group's pixels
    among them (all of them when none is).

    Returns None, or (blob over its box, rows, cols, depths of its pixels (decimated image),
    box r0, r1, c0, c1 with room for growing the mask)."""
    # The group's bounding box (merged components may reach out of the search box).
    r0 = max(min(slices[j - 1][0].start for j in group) - grow, 0)
    r1 = max(slices[j - 1][0].stop for j in group) + grow
    c0 = max(min(slices[j - 1][1].start for j in group) - grow, 0)
    c1 = max(slices[j - 1][1].stop for j in group) + grow
    in_group = np.zeros(n + 1, bool)
    in_group[group] = True
    blob = in_group[lab[r0:r1, c0:c1]]
    if core is not None:
        inner = blob & core[r0:r1, c0:c1]
        blob = inner if inner.any() else blob
    rr, cc = np.nonzero(blob)
    zz = d[r0:r1, c0:c1][rr, cc]
    rr, cc = rr + r0, cc + c0
    step = -(-len(zz) // 2000)
    lo, hi = np.percentile(pixel_points(rr[::step] * s, cc[::step] * s, zz[::step], K),
                           (2, 98), axis=0)
    height, width = hi[1] - lo[1], max(hi[0] - lo[0], hi[2] - lo[2])
    if not (0.4 <= height <= 2.6 and width <= 1.6):
        return None
    return blob, rr, cc, zz, r0, r1, c0, c1


def _within_reach(box: np.ndarray, k: int, pieces: np.ndarray, reach_px: float,
                  nearer: np.ndarray) -> np.ndarray:
    """The labels among `pieces` that component `k` reaches in the label image `box`
    through gaps of at most `reach_px` pixels, piece by piece, where the pixels of
    `nearer` things (an occluder in front; not the pieces) count as no gap. A piece of
    the same body is cut off by a depth jump (the torso's halves beside an arm held
    across it, the head above arms folded in front of the chest) or a stereo camera's
    invalid band, a few pixels from the rest; a person standing 0.2 m beside the edge of
    a nearer wall, the room seen between them, is not a piece of the wall (merged, the
    whole was person-sized and the person never a candidate)."""
    kept = np.zeros(len(pieces), bool)
    inside = (box == k) | nearer
    while not kept.all():
        gap = ndimage.minimum(ndimage.distance_transform_edt(~inside), labels=box,
                              index=pieces)
        new = (np.asarray(gap) <= reach_px) & ~kept
        if not new.any():
            break
        kept |= new
        inside |= np.isin(box, pieces[new])
    return pieces[kept]


def _candidates(fg, depth, d, K, s, min_px, max_persons, depth_min, depth_max,
                alone: bool = False, core=None):
    """Person candidates among the connected components of `fg` (decimated image `d`).
    `alone`: a component whose merged group is too big for a person is a candidate by
    itself when it is person-sized (the second look's rule; without it, only a component
    holding ALONE_SHARE of its group's pixels).

    Returns ([(distance to the image centre, Crop)], component labels, labels of the
    largest components that were not person-sized (at least 4 x min_px)).
    """
    H, W = depth.shape
    lab, n = ndimage.label(fg)
    if n == 0:
        return [], lab, []
    sizes = np.bincount(lab.ravel(), minlength=n + 1)  # by label; [0] is the background
    slices = ndimage.find_objects(lab)
    medians = _label_medians(d, lab, sizes)
    grow = math.ceil(GROW_PX / s)  # dilations of a decimated blob: >= GROW_PX full-image px
    crops, rejected = [], []
    used = np.zeros(n + 1, bool)
    for k in np.argsort(-sizes[1:]) + 1:
        if sizes[k] < min_px:
            break
        if used[k]:
            continue
        # Self-occlusion (an arm in front of the torso) cuts a person into several
        # components: merge the smaller ones inside the (expanded) box at a similar depth;
        # one big enough to be a body of its own (FAR_PIECE_SHARE) only when it comes
        # near (`_within_reach`).
        rows, cols = slices[k - 1]
        pad_r, pad_c = (rows.stop - rows.start) // 8 + 2, (cols.stop - cols.start) // 4 + 2
        win = np.s_[max(rows.start - pad_r, 0):rows.stop + pad_r,
                    max(cols.start - pad_c, 0):cols.stop + pad_c]
        box = lab[win]
        ids = np.flatnonzero(np.bincount(box.ravel(), minlength=n + 1))
        ids = ids[(ids > 0) & (ids != k) & ~used[ids]]
        gap = np.abs(medians[ids] - medians[k])
        small = ids[(sizes[ids] < 0.6 * sizes[k]) & (gap < 0.3)]
        big = small[sizes[small] >= FAR_PIECE_SHARE * sizes[k]]
        if len(big) and alone:
            # The second look: such a piece is a candidate of its own (a person touching
            # the edge of a nearer wall, merged into it in the first pass, which failed).
            small = small[~np.isin(small, big)]
        elif len(big):
            nearer = (box > 0) & (d[win] < medians[k] - OCCLUDER_M) & ~np.isin(box, small)
            near = _within_reach(box, k, small, MERGE_GAP_M * K[0, 0] /
                                 (max(float(medians[k]), 0.1) * s), nearer)
            small = small[~np.isin(small, big) | np.isin(small, near)]
        # An arm across the body cuts a person into an upper and a lower half of similar
        # size: a component as big, stacked above or below this one, is merged too when
        # the whole is still person-sized. Up to 0.5 m apart in depth only when the upper
        # one is nearer (bent forward towards the camera): a nearer lower one is more
        # likely a child or a seated person in front of a standing one. Side by side, it
        # is another person.
        stacked = [j for j, g in zip(ids, gap) if sizes[j] >= 0.6 * sizes[k]
                   and _stacked(slices[k - 1], slices[j - 1])
                   and (g < 0.2 or (g < 0.5 and _upper_is_nearer(
                       (slices[k - 1], medians[k]), (slices[j - 1], medians[j]))))]
        # Last, the component alone: a box or a piece of furniture beside a person at the
        # same depth is merged as a small piece, and the whole is too wide for one. On
        # the second look (`alone`) always; in the first only when the component is most
        # of its group (ALONE_SHARE: a hand or a foot resting on a box), since there a
        # smaller piece taken alone made a candidate of part of a person before the
        # whole (stereo frames of several people, whose invalid bands cut bodies into
        # pieces, lost persons).
        groups = [[k, *small, *stacked]] if stacked else []
        alone_too = alone or sizes[k] >= ALONE_SHARE * (sizes[k] + sizes[small].sum())
        groups += [[k, *small], [k]] if len(small) and alone_too else [[k, *small]]
        for group in groups:
            fit = _group_blob(group, lab, slices, d, n, grow, s, K, core)
            if fit is not None:
                break
        if fit is None:
            if sizes[k] >= 4 * min_px:
                rejected.append(k)
            continue
        blob, rr, cc, zz, r0, r1, c0, c1 = fit
        used[group] = True
        med = float(np.median(zz))
        # Full-image mask: the blob's s x s blocks, grown back over the edge pixels, where
        # the depth is valid and near the person's.
        grown = ndimage.binary_dilation(blob, iterations=grow)
        win = np.s_[r0 * s:r1 * s, c0 * s:c1 * s]
        z = depth[win]
        mask = np.zeros((H, W), bool)
        mask[win] = np.repeat(np.repeat(grown, s, 0), s, 1)[:z.shape[0], :z.shape[1]] & \
            (z >= depth_min) & (z <= depth_max) & (np.abs(z - med) < GROW_DEPTH)
        centre = (cc.mean() * s + (s - 1) / 2, rr.mean() * s + (s - 1) / 2)
        crops.append((float(np.hypot(centre[0] - W / 2, centre[1] - H / 2)),
                      square_crop(cc.min() * s, rr.min() * s, min(cc.max() * s + s - 1, W - 1),
                                  min(rr.max() * s + s - 1, H - 1), median_depth=med,
                                  mask=mask)))
        if len(crops) >= 3 * max_persons:
            break
    return crops, lab, rejected


def find_persons(depth: np.ndarray, K: np.ndarray, depth_min: float, depth_max: float,
                 min_pixels: int = 400, max_persons: int = 5, seed: int = 0,
                 peel: bool = False, noise=None, nearest: int = 0,
                 report: dict | None = None) -> list[Crop]:
    """Person candidates in a depth image, most central first (see the module doc).

    Args:
        depth: (H, W) float32 metres (0/NaN invalid).
        K: (3, 3) intrinsics.
        min_pixels: smallest candidate blob, in full-image pixels.
        peel: the second look of a frame whose candidates all proved not to be persons:
            peel planes off the blobs too big for a person even when other candidates
            were found (by default only when none was: a box beside a person at a wall),
            and take a component alone when its merged group is too big (`_candidates`).
        noise: optional excess sensor noise e(z) (sensor_noise.NoiseModel.excess): the
            depth-jump and plane-inlier thresholds widen with it (see those steps), and
            when it is above 0 at the frame's median depth, small holes are filled first
            (`fill_small_holes`).
        nearest: beyond the max_persons most central candidates, this many of the
            others, the nearest (step 5).
        report: when given, set report['too_big'] to the number of large blobs (at
            least 4 x min_pixels) left whole as not person-sized (a person may be merged
            into one: a second look with `peel` would look inside them).

    Returns:
        Crops (with `mask`, and `exclude` where a neighbour is big enough), at most
        max_persons + nearest.
    """
    H, W = depth.shape
    s = max(1, round(W / DETECT_WIDTH))
    depth = np.nan_to_num(depth, nan=0.0)
    if report is not None:
        report['too_big'] = 0
    if noise is not None:
        dz = depth[::s, ::s]
        dz = dz[dz > 0]
        if len(dz) and float(noise(float(np.median(dz)))) > 0:
            depth = fill_small_holes(depth)  # a noisy (stereo) sensor's holes
    d = depth[::s, ::s]  # pixel (r, c) is full-image (r * s, c * s)
    min_px = min_pixels / s ** 2
    valid = (d >= depth_min) & (d <= depth_max)
    r, c = np.nonzero(valid)
    if len(r) < min_px:
        return []
    rng = np.random.default_rng(seed)
    planes: list = []
    keep = _remove_planes(pixel_points(r * s, c * s, d[r, c], K), rng, planes=planes,
                          noise=noise, view=(d, K, s))
    fg = np.zeros_like(valid)
    fg[valid] = keep
    edges, jumps = _depth_edges(depth, s, noise)
    core = ~jumps  # decimated pixels off any depth jump: a blob is measured on these
    crops, lab, rejected = _candidates(fg & ~edges, depth, d, K, s, min_px, max_persons,
                                       depth_min, depth_max, alone=peel, core=core)
    peeled = None  # decimated pixels of the planes peeled off (hidden from the network)
    if rejected and (peel or not crops):
        # A person within the depth-jump threshold of a wall (or on a floor the first
        # pass kept) is one blob with it, too big to be a person: peel the scene-sized
        # planes of any orientation off the rejected blobs and look again.
        # Inliers within twice a structured-light sensor's noise at the blob's depth
        # (sigma = 1.2 mm + 1.9 mm (z - 0.4)^2, Nguyen et al. 2012), 3 cm at least.
        for k in rejected:
            rr, cc = np.nonzero(lab == k)
            z = float(np.median(d[rr, cc]))
            thresh = max(0.03, 2 * (0.0012 + 0.0019 * (z - 0.4) ** 2)) + (
                0.0 if noise is None else 2 * float(noise(z)))
            on_plane = ~_remove_planes(pixel_points(rr * s, cc * s, d[rr, cc], K), rng,
                                       max_planes=3, min_up=-1.0, thresh=thresh,
                                       planes=planes, strip=FLOOR_STRIP_M,
                                       view=(d, K, s))
            fg[rr[on_plane], cc[on_plane]] = False
            peeled = np.zeros_like(fg) if peeled is None else peeled
            peeled[rr[on_plane], cc[on_plane]] = True
        rejected = []
        crops, _, _ = _candidates(fg & ~edges, depth, d, K, s, min_px, max_persons,
                                  depth_min, depth_max, alone=peel, core=core)
    if report is not None:
        report['too_big'] = len(rejected)
    crops.sort(key=lambda t: t[0])
    crops = [c for _, c in crops]
    _mark_behind(crops)
    crops = _keep(sorted(crops, key=lambda c: c.behind), max_persons, nearest)  # stable
    sizes = [int(c.mask.sum()) for c in crops]
    # The wall a person was peeled off stays at their depth around them: hidden from the
    # network and the fit like a neighbour's blob (full-image pixels of its s x s blocks).
    wall = None if peeled is None else \
        peeled[np.minimum(np.arange(H) // s, peeled.shape[0] - 1)][
            :, np.minimum(np.arange(W) // s, peeled.shape[1] - 1)]
    for i, c in enumerate(crops):
        c.planes = tuple(planes)
        others = [crops[j].mask for j in range(len(crops))
                  if j != i and sizes[j] >= 0.5 * sizes[i]]
        if wall is not None:
            others.append(wall)
        if others:
            c.exclude = np.logical_or.reduce(others) & ~c.mask
    return crops
