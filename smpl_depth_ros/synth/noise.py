"""Structured-light / stereo depth-sensor noise for synthetic depth (no ROS).

The axial and lateral models are Nguyen, Izadi and Lovell, "Modeling Kinect Sensor
Noise for Improved 3D Reconstruction and Tracking" (3DIMPVT 2012), with theta the angle
between the pixel ray and the surface normal:

* axial (metres):  sigma_z(z, theta) = 0.0012 + 0.0019 (z - 0.4)^2
                                      + 0.0001 / sqrt(z) * theta^2 / (pi/2 - theta)^2
* lateral (pixels): sigma_L(theta) = 0.8 + 0.035 theta / (pi/2 - theta)

Lateral noise only shows where depth is discontinuous, so it is applied there: a pixel
within a couple of pixels of a discontinuity takes the depth (and the ground truth) of a
randomly shifted neighbour. On top of that the artefacts real sensors show:

* projector / stereo shadows: surfaces the projector (assumed `shadow_baseline_m` to
  the camera's +x, Kinect v1 layout; a stereo pair's right camera likewise) cannot see,
  an invalid band on the left of foreground objects;
* dropouts eroding a few random pixels inwards from depth discontinuities;
* dropouts at grazing angles (|cos| below ~0.2, more likely the more grazing);
* small random holes and single-pixel dropouts;
* optional Kinect-v1-like disparity quantisation (1/8 pixel), then millimetre
  quantisation (the 16UC1 encoding).

`apply_noise` returns the noisy depth and, per pixel, which clean pixel its value came
from, so ground truth (labels, vertex ids) follows the depth and is 0 / -1 where dropped.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage


@dataclass(frozen=True)
class NoiseParams:
    """Noise model parameters (defaults: Kinect v1 at 640x480).

    Attributes:
        axial: add Gaussian axial noise sigma_z(z, theta).
        sigma_base, sigma_quad, sigma_z0, sigma_angle: the axial model's coefficients
            (metres): base + quad (z - z0)^2 + angle / sqrt(z) * theta^2 / (pi/2 - theta)^2.
        theta_max_deg: theta is clipped to this in both models (the formulas diverge at
            90 degrees).
        lateral: shift pixels near discontinuities by N(0, sigma_L(theta)) pixels.
        lateral_base_px, lateral_angle_px: sigma_L = base + angle theta / (pi/2 - theta).
        lateral_max_px: shifts are clipped to this many pixels.
        lateral_band_px: how far from a discontinuity pixels are shifted.
        discontinuity_m, discontinuity_rel: a neighbour step larger than
            max(discontinuity_m, discontinuity_rel * z) (or valid next to invalid) is a
            discontinuity.
        shadow_baseline_m: projector-camera baseline for the shadow model (0: off;
            needs `fx`).
        edge_drop_prob: probability that a discontinuity pixel is dropped.
        edge_erode_px: the dropped band grows inwards up to this many more pixels ...
        edge_grow_prob: ... each step taking a neighbouring pixel with this probability.
        grazing_cos: pixels with |cos| below this may drop ...
        grazing_drop_prob: ... with probability grazing_drop_prob * (1 - cos / grazing_cos).
        holes_per_frame: mean number of small round holes per 640x480 pixels (Poisson).
        hole_radius_px: (min, max) hole radius.
        pixel_dropout: independent per-pixel dropout probability.
        disparity_quantisation: quantise disparity fx * baseline / z to
            1 / disparity_subpixel pixel (Kinect v1: 1/8), needs `fx`.
        disparity_baseline_m, disparity_subpixel: that quantisation's parameters.
        quantise_m: final depth step in metres (0.001 = the 16UC1 millimetre grid; 0: off).
    """

    axial: bool = True
    sigma_base: float = 0.0012
    sigma_quad: float = 0.0019
    sigma_z0: float = 0.4
    sigma_angle: float = 0.0001
    theta_max_deg: float = 85.0
    lateral: bool = True
    lateral_base_px: float = 0.8
    lateral_angle_px: float = 0.035
    lateral_max_px: float = 3.0
    lateral_band_px: int = 2
    discontinuity_m: float = 0.05
    discontinuity_rel: float = 0.02
    shadow_baseline_m: float = 0.075
    edge_drop_prob: float = 0.3
    edge_erode_px: int = 2
    edge_grow_prob: float = 0.3
    grazing_cos: float = 0.2
    grazing_drop_prob: float = 0.9
    holes_per_frame: float = 4.0
    hole_radius_px: tuple[int, int] = (1, 3)
    pixel_dropout: float = 0.0005
    disparity_quantisation: bool = False
    disparity_baseline_m: float = 0.075
    disparity_subpixel: int = 8
    quantise_m: float = 0.001


@dataclass
class NoiseResult:
    """Noisy depth and where each pixel's value came from.

    Attributes:
        depth: (H, W) float32 metres, 0 = invalid.
        source: (H, W) int64 flat index (v * W + u) of the clean pixel whose surface this
            pixel shows (itself, or a neighbour after a lateral shift); -1 where invalid.
    """

    depth: np.ndarray
    source: np.ndarray

    def take(self, image: np.ndarray, fill) -> np.ndarray:
        """Carry a (H, W) ground-truth image along: image at `source`, `fill` where invalid."""
        if image.shape != self.depth.shape:
            raise ValueError(f'image must be {self.depth.shape}, got {image.shape}')
        out = image.reshape(-1)[np.maximum(self.source, 0)].reshape(image.shape)
        out[self.source < 0] = fill
        return out


def axial_sigma(z: np.ndarray, theta: np.ndarray | float = 0.0,
                params: NoiseParams = NoiseParams()) -> np.ndarray:
    """Nguyen et al. axial standard deviation (metres) at depth z (m), angle theta (rad)."""
    z = np.asarray(z, np.float64)
    th = np.minimum(np.asarray(theta, np.float64), np.deg2rad(params.theta_max_deg))
    return (params.sigma_base + params.sigma_quad * (z - params.sigma_z0) ** 2
            + params.sigma_angle / np.sqrt(np.maximum(z, 1e-6)) * th ** 2
            / (np.pi / 2 - th) ** 2)


def lateral_sigma_px(theta: np.ndarray | float, params: NoiseParams = NoiseParams()):
    """Nguyen et al. lateral standard deviation in pixels at angle theta (rad)."""
    th = np.minimum(np.asarray(theta, np.float64), np.deg2rad(params.theta_max_deg))
    return params.lateral_base_px + params.lateral_angle_px * th / (np.pi / 2 - th)


def discontinuities(depth: np.ndarray, params: NoiseParams = NoiseParams()) -> np.ndarray:
    """(H, W) bool: pixels with a 4-neighbour across a depth step or a valid/invalid
    border (both sides are marked; the image border is not a discontinuity)."""
    valid = depth > 0
    z = depth.astype(np.float64)
    out = np.zeros(depth.shape, bool)
    for sl_a, sl_b in (((slice(None), slice(1, None)), (slice(None), slice(None, -1))),
                       ((slice(1, None), slice(None)), (slice(None, -1), slice(None)))):
        a, b, va, vb = z[sl_a], z[sl_b], valid[sl_a], valid[sl_b]
        thr = np.maximum(params.discontinuity_m, params.discontinuity_rel * np.maximum(a, b))
        jump = (va != vb) | (va & vb & (np.abs(a - b) > thr))
        out[sl_a] |= jump
        out[sl_b] |= jump
    return out


def shadow_mask(depth: np.ndarray, fx: float, baseline_m: float) -> np.ndarray:
    """(H, W) bool: valid pixels the projector (at +x, `baseline_m` away) cannot see.

    A point at column u with depth z is lit by projector column q = u - fx b / z; it is in
    shadow when a point further right maps to a smaller projector column (something
    closer covers it). Gives an invalid band of width fx b (1/z_near - 1/z_far) pixels on
    the left of foreground objects.
    """
    valid = depth > 0
    u = np.arange(depth.shape[1], dtype=np.float64)[None, :]
    with np.errstate(divide='ignore'):
        q = np.where(valid, u - fx * baseline_m / np.where(valid, depth, 1.0), np.inf)
    runmin = np.minimum.accumulate(q[:, ::-1], axis=1)[:, ::-1]
    right = np.concatenate([runmin[:, 1:], np.full((len(q), 1), np.inf)], axis=1)
    return valid & (q > right + 1e-6)


def apply_noise(depth: np.ndarray, normals_cos: np.ndarray, rng: np.random.Generator,
                params: NoiseParams = NoiseParams(), fx: float | None = None) -> NoiseResult:
    """Make a clean rendered depth image look like a real sensor's.

    Args:
        depth: (H, W) float metres (z), 0 = no surface.
        normals_cos: (H, W) |cos| between pixel ray and surface normal (render output).
        rng: random generator (the result is a deterministic function of its state).
        params: noise parameters.
        fx: focal length in pixels; needed for shadows and disparity quantisation, which
            are skipped when it is None. Pixel-sized parameters (lateral sigma, band,
            erosion, hole radii) are for fx = 525 (Kinect v1 VGA) and scale with fx / 525.

    Returns:
        NoiseResult (depth float32 and the source-pixel map for the ground truth).
    """
    if depth.ndim != 2 or normals_cos.shape != depth.shape:
        raise ValueError(f'depth (H, W) and normals_cos of the same shape expected, got '
                         f'{depth.shape} and {normals_cos.shape}')
    H, W = depth.shape
    z0 = np.asarray(depth, np.float64)
    cos0 = np.clip(np.asarray(normals_cos, np.float64), 0.0, 1.0)
    theta0 = np.arccos(cos0)
    idx = np.arange(H * W).reshape(H, W)
    source = idx.copy()

    # Pixel-sized parameters are for a 525 px focal length (Kinect v1 VGA).
    px = 1.0 if fx is None else float(fx) / 525.0
    edges0 = discontinuities(z0, params)

    # 1. Lateral noise: pixels near discontinuities take a shifted neighbour's surface.
    band_px = int(round(params.lateral_band_px * px))
    if params.lateral and band_px >= 0:
        band = edges0
        if band_px > 0:
            band = ndimage.binary_dilation(band, iterations=band_px)
        rr, cc = np.nonzero(band)
        th = np.where(z0[rr, cc] > 0, theta0[rr, cc], 0.0)
        sig = lateral_sigma_px(th, params) * px
        m = params.lateral_max_px * px
        dv = np.rint(np.clip(rng.normal(0.0, 1.0, len(rr)) * sig, -m, m)).astype(np.int64)
        du = np.rint(np.clip(rng.normal(0.0, 1.0, len(rr)) * sig, -m, m)).astype(np.int64)
        source[rr, cc] = (np.clip(rr + dv, 0, H - 1) * W + np.clip(cc + du, 0, W - 1))
    z = z0.reshape(-1)[source]
    theta = theta0.reshape(-1)[source]
    cos = cos0.reshape(-1)[source]
    valid = z > 0

    # 2. Projector shadows (geometry of the clean image, shifted like the depth).
    if fx is not None and params.shadow_baseline_m > 0:
        valid &= ~shadow_mask(z0, fx, params.shadow_baseline_m).reshape(-1)[source]

    # 3. Random erosion at the (clean) discontinuities.
    if params.edge_drop_prob > 0:
        drop = edges0 & valid & (rng.random((H, W)) < params.edge_drop_prob)
        for _ in range(int(round(params.edge_erode_px * px))):
            grow = ndimage.binary_dilation(drop) & valid & ~drop
            drop |= grow & (rng.random((H, W)) < params.edge_grow_prob)
        valid &= ~drop

    # 4. Grazing angles.
    if params.grazing_cos > 0 and params.grazing_drop_prob > 0:
        p = params.grazing_drop_prob * np.clip(1.0 - cos / params.grazing_cos, 0.0, 1.0)
        valid &= ~(rng.random((H, W)) < p)

    # 5. Small holes and single-pixel dropouts.
    n_holes = rng.poisson(params.holes_per_frame * H * W / (640 * 480))
    if n_holes:
        cy, cx = rng.integers(0, H, n_holes), rng.integers(0, W, n_holes)
        rad = np.rint(rng.integers(params.hole_radius_px[0], params.hole_radius_px[1] + 1,
                                   n_holes) * px).astype(int)
        vv, uu = np.ogrid[0:H, 0:W]
        for y, x, r in zip(cy, cx, rad):
            y0, y1, x0, x1 = max(y - r, 0), min(y + r + 1, H), max(x - r, 0), min(x + r + 1, W)
            valid[y0:y1, x0:x1] &= (vv[y0:y1] - y) ** 2 + (uu[:, x0:x1] - x) ** 2 > r * r
    if params.pixel_dropout > 0:
        valid &= rng.random((H, W)) >= params.pixel_dropout

    # 6. Axial noise, then quantisation.
    if params.axial:
        z = z + rng.normal(0.0, 1.0, (H, W)) * axial_sigma(np.where(valid, z, 1.0), theta,
                                                          params)
    if params.disparity_quantisation and fx is not None:
        fb = fx * params.disparity_baseline_m
        s = params.disparity_subpixel
        disp = np.rint(fb / np.where(valid & (z > 0), z, np.inf) * s) / s
        with np.errstate(divide='ignore'):
            z = np.where(disp > 0, fb / np.where(disp > 0, disp, 1.0), 0.0)
    if params.quantise_m > 0:
        z = np.rint(z / params.quantise_m) * params.quantise_m
    valid &= z > 0
    out = np.where(valid, z, 0.0).astype(np.float32)
    return NoiseResult(out, np.where(valid, source, -1))
