"""Depth images as a lens-distorted camera gives them, made pinhole (no ROS).

Some drivers publish the depth image as the sensor sees it, bent by its lens, with the
lens model in camera_info (the Azure Kinect's and Orbbec Femto's `depth/image_raw`,
rational_polynomial), while the pipeline back-projects pixels through a pinhole K. A
pixel near the image side of such a camera lies up to a tenth of its distance from the
optical axis off where K puts it, bending bodies there. `Rectifier` resamples the image
onto the pinhole image of the same K and size and maps the outputs drawn on that image
(labels, person masks) back onto the raw image's pixels, so that they stay aligned with
the image the user gave.

Both maps are nearest-neighbour: a depth value is never blended across an edge (as
depth_image_proc asks of rectified depth), and a pixel's value, the depth along the
optical axis, does not change with the lens. Rectified pixels whose ray falls outside
the raw image get no depth.

Models (ROS camera_info names; OpenCV's formulas on normalised coordinates x = X / Z):
`plumb_bob` (D = k1, k2, p1, p2, k3), `rational_polynomial` (k1, k2, p1, p2, k3, k4, k5,
k6) and `equidistant` (k1, k2, k3, k4: the fisheye model).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

MODELS = ('plumb_bob', 'rational_polynomial', 'equidistant')
NEWTON_ITERATIONS = 12  # inverse of the lens model (raw pixel -> pinhole ray)
INVERSE_TOL_PX = 0.05   # a raw pixel whose inverse misses by more has no pinhole pixel
MAX_GROWTH = 1.6        # the pinhole image reaches at most this far past the raw one's sides


def distort(x: np.ndarray, y: np.ndarray, model: str, D) -> tuple[np.ndarray, np.ndarray]:
    """Ideal normalised image coordinates -> the lens's (distorted) ones."""
    D = np.asarray(D, np.float64).reshape(-1)
    if model == 'equidistant':
        k = np.zeros(4)
        k[:min(len(D), 4)] = D[:4]
        r = np.hypot(x, y)
        th = np.arctan(r)
        t2 = th * th
        thd = th * (1 + t2 * (k[0] + t2 * (k[1] + t2 * (k[2] + t2 * k[3]))))
        s = np.where(r > 1e-12, thd / np.maximum(r, 1e-12), 1.0)
        return x * s, y * s
    if model not in MODELS:
        raise ValueError(f'distortion model {model!r} is not supported '
                         f'(supported: {", ".join(MODELS)})')
    k = np.zeros(8)
    k[:min(len(D), 8)] = D[:8]
    k1, k2, p1, p2, k3, k4, k5, k6 = k
    r2 = x * x + y * y
    radial = (1 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1 + r2 * (k4 + r2 * (k5 + r2 * k6)))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return xd, yd


def undistort(xd: np.ndarray, yd: np.ndarray, model: str, D
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The lens's normalised coordinates -> the ideal ones (Newton's method on `distort`,
    from the distorted point). Returns (x, y, error): error is how far `distort` of the
    result lands from the input (normalised units)."""
    x, y = np.array(xd, np.float64), np.array(yd, np.float64)
    h = 1e-6
    for _ in range(NEWTON_ITERATIONS):
        fx, fy = distort(x, y, model, D)
        ex, ey = fx - xd, fy - yd
        ax, ay = distort(x + h, y, model, D)
        bx, by = distort(x, y + h, model, D)
        j11, j21 = (ax - fx) / h, (ay - fy) / h
        j12, j22 = (bx - fx) / h, (by - fy) / h
        det = j11 * j22 - j12 * j21
        det = np.where(np.abs(det) > 1e-12, det, 1e-12)
        x = x - (j22 * ex - j12 * ey) / det
        y = y - (-j21 * ex + j11 * ey) / det
    fx, fy = distort(x, y, model, D)
    return x, y, np.hypot(fx - xd, fy - yd)


def named_rectified(topic: str) -> bool:
    """Whether a depth topic's name says its images are rectified (the ROS convention:
    `image_rect`, `image_rect_raw`; `image_raw` is the lens's own image)."""
    return 'rect' in str(topic).rstrip('/').rsplit('/', 1)[-1]


@dataclass(frozen=True)
class Lens:
    """A depth camera's lens as its camera_info gives it, and what the depth topic's name
    says of its images.

    Attributes:
        model: camera_info's distortion_model; D: its coefficients.
        P: (3, 3) the rectified image's intrinsics (camera_info's P, left block).
        rectified: the depth topic's name says rectified (`named_rectified`).
    """

    model: str
    D: np.ndarray
    P: np.ndarray
    rectified: bool = False

    @property
    def distorted(self) -> bool:
        return bool(np.size(self.D)) and bool(np.any(np.asarray(self.D) != 0))

    def undo(self, mode: str) -> bool:
        """Whether the images are the lens's own, to be made pinhole, under
        PipelineConfig.undistort `mode` ('auto': unless the topic's name says rect)."""
        if not self.distorted or mode == 'never':
            return False
        return mode == 'always' or not self.rectified

    def notice(self, frame_id: str, mode: str) -> str:
        """What is done with this lens's images under `mode`, for the log."""
        return (f"camera_info for '{frame_id}' has lens distortion ({self.model}): depth "
                'images ' + (f"are made pinhole before use (undistort '{mode}')"
                             if self.undo(mode) else
                             f"are taken as rectified, seen through P (undistort '{mode}'; "
                             "'always' if they are the lens's own)"))


@dataclass(frozen=True)
class Rectifier:
    """Nearest-neighbour maps between a lens-distorted image and a pinhole image with the
    same focal lengths that holds all of it (`for_camera`): the pinhole image is larger
    than the raw one where the lens compresses the image side (at most MAX_GROWTH times
    each side, about the principal point), so nobody at the image side is cut off.

    Attributes:
        K: (3, 3) the pinhole image's intrinsics (the raw K, its principal point moved).
        shape: (H', W') the pinhole image's size.
        source: (H', W') int64, the flat raw pixel each pinhole pixel takes (-1: none).
        back: (H, W) int64, the flat pinhole pixel each raw pixel lies on (-1: none).
    """

    K: np.ndarray
    shape: tuple[int, int]
    source: np.ndarray
    back: np.ndarray

    @classmethod
    def for_camera(cls, K: np.ndarray, model: str, D, size: tuple[int, int]
                   ) -> 'Rectifier | None':
        """The maps of a camera (K (3, 3), camera_info's distortion_model and D, size
        (width, height)); None when D is all zeros (nothing to do).

        Raises:
            ValueError: a model other than MODELS, or a lens no pixel can be undone of.
        """
        D = np.asarray(D, np.float64).reshape(-1)
        if not D.size or not np.any(D):
            return None
        if model not in MODELS:
            raise ValueError(f'distortion model {model!r} is not supported '
                             f'(supported: {", ".join(MODELS)})')
        K = np.asarray(K, np.float64)
        w, h = int(size[0]), int(size[1])
        fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
        vv, uu = np.mgrid[0:h, 0:w].astype(np.float64)
        # raw pixel -> its ray -> where a pinhole camera of the same focal lengths puts it
        x, y, err = undistort((uu - cx) / fx, (vv - cy) / fy, model, D)
        ok = err * max(fx, fy) <= INVERSE_TOL_PX
        if not ok.any():
            raise ValueError(f'the {model} lens D={D.tolist()} cannot be undone at any pixel')
        u, v = x * fx + cx, y * fy + cy
        lo_u = max(np.floor(u[ok].min()), cx - MAX_GROWTH * cx)
        hi_u = min(np.ceil(u[ok].max()), cx + MAX_GROWTH * (w - cx))
        lo_v = max(np.floor(v[ok].min()), cy - MAX_GROWTH * cy)
        hi_v = min(np.ceil(v[ok].max()), cy + MAX_GROWTH * (h - cy))
        W, H = int(hi_u - lo_u) + 1, int(hi_v - lo_v) + 1
        Kp = K.copy()
        Kp[0, 2], Kp[1, 2] = cx - lo_u, cy - lo_v
        back = _flat_index(u - lo_u, v - lo_v, W, H)
        back[~ok] = -1
        # pinhole pixel -> its ray -> where the lens puts it in the raw image
        pv, pu = np.mgrid[0:H, 0:W].astype(np.float64)
        xd, yd = distort((pu - Kp[0, 2]) / fx, (pv - Kp[1, 2]) / fy, model, D)
        source = _flat_index(xd * fx + cx, yd * fy + cy, w, h)
        # rays beyond where the lens model holds (it folds back outside the raw image's
        # field of view) take nothing
        far = np.hypot((pu - Kp[0, 2]) / fx, (pv - Kp[1, 2]) / fy) > np.hypot(x, y)[ok].max()
        source[far] = -1
        # A raw pixel that pinhole pixels took goes back to the one of them nearest its
        # ray (so that a label drawn on a pinhole pixel returns to the raw pixel whose
        # depth it was drawn on); the others (where the lens magnifies) to the nearest.
        q = np.flatnonzero(source.reshape(-1) >= 0)
        s = source.reshape(-1)[q]
        dist = np.hypot(pu.reshape(-1)[q] - (u - lo_u).reshape(-1)[s],
                        pv.reshape(-1)[q] - (v - lo_v).reshape(-1)[s])
        order = np.argsort(-dist, kind='stable')  # the nearest written last
        flat_back = back.reshape(-1)
        flat_back[s[order]] = q[order]
        return cls(Kp, (H, W), source, back)

    def rectify(self, depth: np.ndarray) -> np.ndarray:
        """(H, W) raw depth -> the pinhole image's (0 where no raw pixel lies)."""
        return _gather(depth, self.source, self.back.shape)

    def to_raw(self, image: np.ndarray) -> np.ndarray:
        """(H', W') image on the pinhole grid (labels, a mask) -> on the raw image's
        pixels (zero / False where no pinhole pixel lies)."""
        return _gather(image, self.back, self.shape)

    def raw_pixels(self, rows: np.ndarray, cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pinhole pixels (rows, cols) -> the raw pixels they took (-1 for none)."""
        flat = self.source[rows, cols]
        w = self.back.shape[1]
        return np.where(flat >= 0, flat // w, -1), np.where(flat >= 0, flat % w, -1)


def _flat_index(u: np.ndarray, v: np.ndarray, w: int, h: int) -> np.ndarray:
    """Flat index of the pixel nearest each (u, v); -1 outside the image."""
    ui, vi = np.rint(u), np.rint(v)
    ok = np.isfinite(ui) & np.isfinite(vi) & (ui >= 0) & (ui < w) & (vi >= 0) & (vi < h)
    out = np.full(u.shape, -1, np.int64)
    out[ok] = vi[ok].astype(np.int64) * w + ui[ok].astype(np.int64)
    return out


def _gather(image: np.ndarray, index: np.ndarray, shape: tuple) -> np.ndarray:
    """`image` (of size `shape`) sampled at the flat `index` (zero where -1)."""
    if image.shape[:2] != tuple(shape):
        raise ValueError(f'image {image.shape[:2]} does not match the camera {tuple(shape)}')
    out = np.zeros(index.shape + image.shape[2:], image.dtype)
    ok = index >= 0
    out[ok] = image.reshape(-1, *image.shape[2:])[index[ok]]
    return out
