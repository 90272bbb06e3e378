"""Depth-sensor classes for synthetic data: noise models and camera presets (no ROS).

Three classes of consumer depth sensor, each a noise model with a strength knob
(`strength`, 1 = nominal; training draws 0.5-2) that works at any intrinsics and
resolution (pixel-sized effects are given in the sensor's own pixels; `pixel_size` says
how many sensor pixels one image pixel spans, e.g. a network crop's scale):

* **structured light** (Kinect v1, Orbbec Astra): `synth.noise` (Nguyen, Izadi and
  Lovell, 3DIMPVT 2012; projector shadows, edge erosion, grazing dropouts).
* **active stereo** (RealSense D4xx, OAK-D / OAK-D Pro, ZED-like): the depth error comes
  from the disparity error, sigma_z = z^2 sigma_d / (f b) (Intel, "Tuning depth cameras
  for best performance", Grunnet-Jepsen et al., 2019, and the D400 datasheet's RMS error
  formula; Luxonis' OAK depth-accuracy notes give the same form). Block matching over a
  window makes the error spatially correlated (wavy surfaces, Gaussian-correlated with
  `correlation_px`, plus a white share); disparity is quantised to 1/`subpixel_levels`
  px (D4xx: 1/32; OAK-D's 3-bit subpixel: 1/8); the left-right check invalidates the
  pixels the second imager cannot see (a band left of foreground objects, the projector
  shadow geometry of `noise.shadow_mask`) plus a few more at edges; block matching
  fattens foreground objects across depth edges by up to half a window (Scharstein and
  Szeliski, IJCV 2002); the speckle filter removes small blobs; the valid share falls
  with range as disparity runs out (`range_50_m`: half the pixels invalid).
* **time of flight** (Kinect v2, Azure Kinect / Orbbec Femto, binned modes): small axial
  noise growing with depth and with the incidence angle (Tölgyessy et al., "Evaluation
  of the Azure Kinect and its comparison to Kinect V1 and Kinect V2", Sensors 2021;
  Fankhauser et al., "Kinect v2 for mobile robot navigation", ICAR 2015); flying pixels
  (mixed foreground/background phase) in a band at depth edges, valid but on no surface;
  a multipath bias pushing concave corners away (Fuchs, "Multipath interference
  compensation in time-of-flight camera images", ICPR 2010); dropouts on dark, low-albedo
  regions (hair, `dark` mask) and where the returned signal (cos / z^2) is weak; the
  mode's hard range limits (the camera preset's range: the device invalidates beyond it).

`SENSORS` maps a preset name to its camera (`synth.camera.CAMERAS`) and noise model;
`Sensor.sigma(z)` is the expected axial noise at depth z, which the pipeline uses to
scale its thresholds (`pipeline` `sensor` parameter).
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from scipy import ndimage

from smpl_depth_ros.synth import noise as sl
from smpl_depth_ros.synth.camera import CAMERAS, Camera

KINDS = ('structured_light', 'stereo', 'tof')


@dataclass(frozen=True)
class StereoParams:
    """Active stereo noise (defaults: RealSense D435 at 848x480).

    Attributes:
        baseline_m: distance between the two imagers.
        subpixel_sigma_px: RMS disparity error (sensor pixels); D4xx 0.05-0.1 typical.
        correlation_px: spatial correlation length (Gaussian sigma, sensor pixels) of the
            disparity error: about a third of the block-matching window.
        white_share: share of the disparity error's variance that is per pixel.
        subpixel_levels: disparity is quantised to 1 / subpixel_levels pixel (0: off).
        lr_band_px: pixels beyond the occluded band the left-right check also drops
            (mean, at foreground edges).
        fattening_px: foreground fattening across depth edges (largest, sensor pixels).
        fattening_prob: share of the pixels in that band taking the foreground depth.
        speckle_share: share of the image lost to speckle-filtered blobs at 1 m; it
            grows with (z / 1 m).
        speckle_px: blob size (Gaussian sigma of the random field, sensor pixels).
        range_50_m: range at which half of the pixels are invalid ...
        range_width_m: ... over a logistic of this width.
        grazing_cos: pixels with |cos| below this drop out (no texture match).
        quantise_m: final depth step (0.001: the 16UC1 millimetre grid).
    """

    baseline_m: float = 0.05
    subpixel_sigma_px: float = 0.08
    correlation_px: float = 3.0
    white_share: float = 0.25
    subpixel_levels: int = 32
    lr_band_px: float = 1.5
    fattening_px: float = 3.0
    fattening_prob: float = 0.6
    speckle_share: float = 0.003
    speckle_px: float = 2.5
    range_50_m: float = 8.0
    range_width_m: float = 0.8
    grazing_cos: float = 0.12
    quantise_m: float = 0.001


@dataclass(frozen=True)
class TofParams:
    """Time-of-flight noise (defaults: Azure Kinect NFOV unbinned).

    Attributes:
        sigma_base_m, sigma_rel: axial sigma = base + rel * z at normal incidence ...
        sigma_angle: ... times (1 + sigma_angle * tan(theta)^2) off it.
        flying_band_px: half-width of the edge band with flying pixels (sensor pixels).
        flying_prob: share of the band's pixels that fly (a mix of both sides' depths).
        multipath_gain: depth bias per metre of concavity (the depth above its local
            mean over `multipath_px`) in concave corners.
        multipath_px: the local mean's Gaussian sigma (sensor pixels).
        multipath_max_m: largest bias.
        dark_dropout: share of dark (`dark` mask) pixels lost ...
        dark_px: ... in patches of this size (sensor pixels).
        signal_falloff: invalid probability = signal_falloff * (z / max_range)^2 / cos,
            clipped (weak returns; far and grazing).
        edge_drop_prob: share of edge pixels invalidated (mixed pixels the device
            recognises).
        quantise_m: final depth step.
    """

    sigma_base_m: float = 0.0012
    sigma_rel: float = 0.0008
    sigma_angle: float = 0.3
    flying_band_px: float = 1.0
    flying_prob: float = 0.5
    multipath_gain: float = 0.25
    multipath_px: float = 8.0
    multipath_max_m: float = 0.03
    dark_dropout: float = 0.5
    dark_px: float = 2.0
    signal_falloff: float = 0.08
    edge_drop_prob: float = 0.3
    quantise_m: float = 0.001


NoiseModel = sl.NoiseParams | StereoParams | TofParams


@dataclass(frozen=True)
class Sensor:
    """A depth-sensor preset: camera intrinsics and range, and its noise model.

    Attributes:
        name: preset name (the camera preset's).
        kind: 'structured_light' | 'stereo' | 'tof'.
        camera: intrinsics, image size and valid range.
        params: the noise model's parameters (`noise.NoiseParams`, `StereoParams` or
            `TofParams`, matching `kind`).
    """

    name: str
    kind: str
    camera: Camera
    params: NoiseModel = field(default_factory=sl.NoiseParams)

    def __post_init__(self):
        if self.kind not in KINDS:
            raise ValueError(f'unknown sensor kind {self.kind!r}; kinds: {KINDS}')

    def with_camera(self, camera: Camera) -> 'Sensor':
        """The same noise model on other intrinsics (another resolution or unit)."""
        return replace(self, camera=camera)

    def with_noise(self, **fields) -> 'Sensor':
        """The same camera with some of its noise model's fields set (those it has; the
        others are ignored, so one set of overrides serves every class of preset)."""
        own = {k: v for k, v in fields.items() if hasattr(self.params, k)}
        return replace(self, params=replace(self.params, **own)) if own else self

    def sigma(self, z, theta=0.0, strength: float = 1.0) -> np.ndarray:
        """Expected axial noise (metres, 1 sigma) at depth z (m), incidence theta (rad),
        for this preset's own resolution."""
        z = np.asarray(z, np.float64)
        p = self.params
        if self.kind == 'structured_light':
            return strength * sl.axial_sigma(z, theta, p)
        if self.kind == 'stereo':
            fb = self.camera.fx * p.baseline_m
            q = 0.0 if not p.subpixel_levels else 1.0 / p.subpixel_levels / np.sqrt(12)
            sd = np.hypot(strength * p.subpixel_sigma_px, q)
            return z ** 2 * sd / fb
        th = np.minimum(np.asarray(theta, np.float64), np.deg2rad(80))
        return (strength * (p.sigma_base_m + p.sigma_rel * z)
                * (1 + p.sigma_angle * np.tan(th) ** 2))

    def apply(self, depth: np.ndarray, normals_cos: np.ndarray, rng: np.random.Generator,
              strength: float = 1.0, fx: float | None = None, pixel_size: float = 1.0,
              dark: np.ndarray | None = None) -> sl.NoiseResult:
        """Corrupt a clean rendered depth image as this sensor would.

        Args:
            depth: (H, W) float metres (z), 0 = no surface.
            normals_cos: (H, W) |cos| between pixel ray and surface normal.
            rng: random generator (the result is a deterministic function of its state).
            strength: noise strength (1 = nominal): scales sigmas, dropout shares and
                artefact widths.
            fx: the image's focal length in pixels (default: the preset's, i.e. an image
                at the preset's resolution).
            pixel_size: sensor pixels per image pixel (a crop rendered at 1 / scale of
                the sensor's resolution: its scale; 1 for a full sensor image).
            dark: (H, W) bool low-albedo pixels (hair), used by time of flight.

        Returns:
            noise.NoiseResult; `source` is -1 where the pixel is invalid or (time of
            flight) a flying pixel that lies on no surface.
        """
        if depth.ndim != 2 or normals_cos.shape != depth.shape:
            raise ValueError(f'depth (H, W) and normals_cos of the same shape expected, got '
                             f'{depth.shape} and {normals_cos.shape}')
        fx = self.camera.fx / pixel_size if fx is None else float(fx)
        if self.kind == 'structured_light':
            return sl.apply_noise(depth, normals_cos, rng,
                                  structured_light_params(self.params, strength, pixel_size,
                                                          fx), fx=fx * pixel_size)
        if self.kind == 'stereo':
            return _stereo(depth, normals_cos, rng, self.params, strength, fx, pixel_size,
                           self.camera)
        return _tof(depth, normals_cos, rng, self.params, strength, pixel_size, self.camera,
                    dark)


def structured_light_params(p: sl.NoiseParams, strength: float, pixel_size: float,
                            fx_image: float) -> sl.NoiseParams:
    """`noise.NoiseParams` at a strength, for an image of pixel_size sensor pixels.

    `noise.apply_noise` scales pixel-sized effects by fx / 525 (its fx is the sensor's);
    an image coarser than the sensor shrinks them by 1 / pixel_size on top.
    """
    k = 1.0 / max(pixel_size, 1.0)
    s = float(strength)
    return replace(
        p, sigma_base=p.sigma_base * s, sigma_quad=p.sigma_quad * s,
        sigma_angle=p.sigma_angle * s, lateral_base_px=p.lateral_base_px * k * s,
        lateral_angle_px=p.lateral_angle_px * k * s,
        lateral_max_px=max(p.lateral_max_px * k, 1.0),
        lateral_band_px=int(round(p.lateral_band_px * k)),
        edge_drop_prob=min(p.edge_drop_prob * s, 0.9), edge_erode_px=int(p.edge_erode_px * k),
        hole_radius_px=(1, max(1, int(round(p.hole_radius_px[1] * k)))),
        holes_per_frame=p.holes_per_frame * k * k * s,
        pixel_dropout=min(p.pixel_dropout * s, 0.05),
        # shadow geometry in image pixels: apply_noise multiplies the baseline by its fx
        shadow_baseline_m=p.shadow_baseline_m / max(pixel_size, 1e-6))


def correlated_field(shape, sigma_px: float, rng: np.random.Generator) -> np.ndarray:
    """Unit-variance Gaussian random field with a Gaussian correlation of sigma_px."""
    w = rng.normal(0.0, 1.0, shape)
    if sigma_px < 0.3:
        return w
    f = ndimage.gaussian_filter(w, sigma_px, mode='reflect')
    sd = f.std()
    return f / sd if sd > 0 else f


def _window_extreme(z: np.ndarray, valid: np.ndarray, radius: int, largest: bool):
    """Per pixel, the smallest (or largest) valid depth within `radius` (square window)
    and the flat index of the pixel holding it; inf / -1 where none."""
    H, W = z.shape
    idx = np.arange(H * W).reshape(H, W)
    best = np.where(valid, -z if largest else z, np.inf)
    src = np.where(valid, idx, -1)
    pad = radius
    zp = np.pad(np.where(valid, -z if largest else z, np.inf), pad, constant_values=np.inf)
    ip = np.pad(np.where(valid, idx, -1), pad, constant_values=-1)
    for dv in range(-radius, radius + 1):
        for du in range(-radius, radius + 1):
            if dv == 0 and du == 0:
                continue
            c = zp[pad + dv:pad + dv + H, pad + du:pad + du + W]
            better = c < best
            best = np.where(better, c, best)
            src = np.where(better, ip[pad + dv:pad + dv + H, pad + du:pad + du + W], src)
    return (-best if largest else best), src


def _start(depth, strength):
    """(H, W, strength, clean depth float64, valid mask, source map) of a noise model."""
    H, W = depth.shape
    z0 = np.asarray(depth, np.float64)
    valid = z0 > 0
    return H, W, float(strength), z0, valid, np.where(valid, np.arange(H * W).reshape(H, W), -1)


def _stereo(depth, normals_cos, rng, p: StereoParams, strength, fx, pixel_size,
            camera: Camera) -> sl.NoiseResult:
    H, W, s, z0, valid, source = _start(depth, strength)
    z = z0.copy()
    px = 1.0 / pixel_size  # image pixels per sensor pixel

    # 1. Foreground fattening: background pixels beside a nearer edge take its depth.
    r = int(round(p.fattening_px * px * min(s, 1.5)))
    if r >= 1:
        zmin, smin = _window_extreme(z0, valid, r, largest=False)
        jump = valid & np.isfinite(zmin) & (z0 - zmin > np.maximum(0.05, 0.03 * z0))
        jump |= ~valid & np.isfinite(zmin)
        take = jump & (rng.random((H, W)) < p.fattening_prob)
        # only on the occluded (left) side a matcher confuses, and the right side too
        z = np.where(take, zmin, z)
        source = np.where(take, smin, source)
        valid = valid | take

    # 2. Left-right check: what the second imager (at +x) cannot see, and a band beyond.
    occ = sl.shadow_mask(np.where(valid, z, 0.0), fx, p.baseline_m)
    if p.lr_band_px > 0:
        grow = int(round(p.lr_band_px * px * s))
        if grow >= 1:
            band = ndimage.binary_dilation(occ, iterations=grow) & ~occ
            occ |= band & (rng.random((H, W)) < 0.6)
    valid &= ~occ

    # 3. Disparity error: correlated + white, then subpixel quantisation.
    fb = fx * pixel_size * p.baseline_m  # sensor focal length x baseline
    corr = correlated_field((H, W), p.correlation_px * px, rng)
    white = rng.normal(0.0, 1.0, (H, W))
    e = s * p.subpixel_sigma_px * (np.sqrt(1 - p.white_share) * corr
                                   + np.sqrt(p.white_share) * white)
    with np.errstate(divide='ignore', invalid='ignore'):
        disp = np.where(valid, fb / np.where(valid, z, 1.0), 0.0) + e
        if p.subpixel_levels:
            disp = np.rint(disp * p.subpixel_levels) / p.subpixel_levels
        z = np.where(valid & (disp > 0), fb / np.where(disp > 0, disp, 1.0), 0.0)
    valid &= z > 0

    # 4. Dropouts: speckle blobs (more with range), grazing angles, range running out.
    cos = np.clip(np.asarray(normals_cos, np.float64).reshape(-1)[np.maximum(source, 0)]
                  .reshape(H, W), 0, 1)
    if p.speckle_share > 0:
        f = correlated_field((H, W), p.speckle_px * px, rng)
        share = np.clip(s * p.speckle_share * np.maximum(z, 1.0), 0, 0.5)
        from scipy.special import ndtri
        valid &= f < ndtri(1 - np.where(share > 0, share, 1e-9))
    if p.grazing_cos > 0:
        pg = np.clip(1.0 - cos / (p.grazing_cos * s), 0.0, 1.0)
        valid &= ~(rng.random((H, W)) < pg)
    with np.errstate(over='ignore'):
        pr = 1.0 / (1.0 + np.exp(-(z - p.range_50_m / max(s, 0.25) ** 0.5)
                                 / p.range_width_m))
    valid &= ~(rng.random((H, W)) < pr)

    if p.quantise_m > 0:
        z = np.rint(z / p.quantise_m) * p.quantise_m
    valid &= (z > 0) & (z >= camera.min_range) & (z <= camera.max_range)
    return sl.NoiseResult(np.where(valid, z, 0.0).astype(np.float32),
                          np.where(valid, source, -1))


def _tof(depth, normals_cos, rng, p: TofParams, strength, pixel_size, camera: Camera,
         dark) -> sl.NoiseResult:
    H, W, s, z0, valid, source = _start(depth, strength)
    px = 1.0 / pixel_size
    cos = np.clip(np.asarray(normals_cos, np.float64), 1e-3, 1.0)
    theta = np.arccos(cos)

    # 1. Multipath: concave corners measured too far (local depth above its mean).
    z = z0.copy()
    if p.multipath_gain > 0:
        g = max(p.multipath_px * px, 0.5)
        wsum = ndimage.gaussian_filter(valid.astype(np.float64), g)
        zmean = ndimage.gaussian_filter(np.where(valid, z0, 0.0), g) / np.maximum(wsum, 1e-6)
        c = z0 - zmean
        c = np.where(valid & (c > 0) & (c < 0.15), c, 0.0)
        z = z + np.minimum(s * p.multipath_gain * c, p.multipath_max_m)

    # 2. Axial noise.
    sig = s * (p.sigma_base_m + p.sigma_rel * z0) * (1 + p.sigma_angle
                                                     * np.tan(np.minimum(theta, 1.4)) ** 2)
    z = z + rng.normal(0.0, 1.0, (H, W)) * sig

    # 3. Flying pixels: in a band at depth edges, a mix of the depths on both sides.
    edges = sl.discontinuities(z0) & valid
    rad = max(1, int(round(p.flying_band_px * px)))
    near = ndimage.binary_dilation(edges, iterations=max(rad - 1, 0)) if rad > 1 else edges
    zmin, _ = _window_extreme(z0, valid, rad, largest=False)
    zmax, _ = _window_extreme(z0, valid, rad, largest=True)
    fly = near & valid & np.isfinite(zmin) & (zmax - zmin > 0.05) & \
        (rng.random((H, W)) < min(p.flying_prob * s, 0.95))
    a = rng.random((H, W))
    with np.errstate(invalid='ignore'):
        z = np.where(fly, zmin + a * (zmax - zmin), z)
    source = np.where(fly, -2, source)  # valid depth on no surface
    if p.edge_drop_prob > 0:
        valid &= ~(edges & ~fly & (rng.random((H, W)) < min(p.edge_drop_prob * s, 0.9)))

    # 4. Dropouts: dark regions (hair) in patches, weak returns (far, grazing).
    if dark is not None and p.dark_dropout > 0:
        f = correlated_field((H, W), p.dark_px * px, rng)
        from scipy.special import ndtri
        valid &= ~(dark & (f < ndtri(min(p.dark_dropout * s, 0.98))))
    pw = np.clip(s * p.signal_falloff * (z0 / camera.max_range) ** 2 / cos, 0, 1)
    valid &= ~(rng.random((H, W)) < pw)

    if p.quantise_m > 0:
        z = np.rint(z / p.quantise_m) * p.quantise_m
    valid &= (z > 0) & (z >= camera.min_range) & (z <= camera.max_range)
    src = np.where(valid, np.where(source == -2, -1, source), -1)
    return sl.NoiseResult(np.where(valid, z, 0.0).astype(np.float32), src)


def _sl(name, **kw) -> Sensor:
    return Sensor(name, 'structured_light', CAMERAS[name], sl.NoiseParams(**kw))


def _st(name, **kw) -> Sensor:
    return Sensor(name, 'stereo', CAMERAS[name], StereoParams(**kw))


def _tf(name, **kw) -> Sensor:
    return Sensor(name, 'tof', CAMERAS[name], TofParams(**kw))


SENSORS: dict[str, Sensor] = {
    'kinect_v1': _sl('kinect_v1'),
    # Astra: the same PrimeSense-style projector geometry, a slightly longer focal length.
    'astra': _sl('astra'),
    # D435: 50 mm baseline; 1/32 px disparity; range limited by its 0.08 px RMS.
    'realsense_d435': _st('realsense_d435'),
    'realsense_d435_640x480': _st('realsense_d435_640x480'),
    # D455: 95 mm baseline, the same sensors: about half the D435's error at a depth.
    'realsense_d455': _st('realsense_d455', baseline_m=0.095, range_50_m=10.0),
    # OAK-D / OAK-D Pro at 400P: 75 mm baseline, 3-bit subpixel (1/8 px), larger
    # matching windows (7x7 census + aggregation) and more speckle without a projector.
    'oak_d': _st('oak_d', baseline_m=0.075, subpixel_sigma_px=0.1, subpixel_levels=8,
                 correlation_px=3.5, speckle_share=0.006, range_50_m=9.0),
    # Subpixel disparity off: whole-pixel steps (the error is the step's, ~1/sqrt(12) px).
    'oak_d_no_subpixel': Sensor('oak_d_no_subpixel', 'stereo', CAMERAS['oak_d'],
                                StereoParams(baseline_m=0.075, subpixel_sigma_px=0.1,
                                             subpixel_levels=1, correlation_px=3.5,
                                             speckle_share=0.006, range_50_m=9.0)),
    'oak_d_pro': _st('oak_d_pro', baseline_m=0.075, subpixel_sigma_px=0.08,
                     subpixel_levels=8, correlation_px=3.0, range_50_m=10.0),
    'kinect_v2': _tf('kinect_v2', sigma_base_m=0.0015, sigma_rel=0.001),
    'azure_kinect_nfov': _tf('azure_kinect_nfov'),
    # 2x2 binned NFOV: longer range (to 5.46 m), each pixel averages four: less noise.
    'azure_kinect_nfov_binned': _tf('azure_kinect_nfov_binned', sigma_base_m=0.0009,
                                    sigma_rel=0.0006, flying_band_px=1.0),
}


# Lenses of cameras whose drivers publish the lens's own depth image: name ->
# (camera_info distortion_model, D in its order), on normalised coordinates (any mode's K).
LENSES: dict[str, tuple[str, tuple[float, ...]]] = {
    # An Azure Kinect depth camera's factory calibration (Brown-Conrady with six radial
    # terms, i.e. OpenCV's rational polynomial; k1 k2 p1 p2 k3 k4 k5 k6) as one device
    # reports it (github.com/microsoft/Azure-Kinect-Sensor-SDK, #1617): its image side
    # (x = 0.63) lies 11 % nearer the centre than a pinhole camera would put it.
    'azure_kinect': ('rational_polynomial', (4.7247, 3.2092, 5.88e-6, 1.238e-4, 0.1706,
                                             5.0559, 4.7758, 0.8865)),
}


def get_sensor(name: str, width: int | None = None, height: int | None = None) -> Sensor:
    """A sensor preset by name, its camera optionally resampled (`camera.get_camera`)."""
    from smpl_depth_ros.synth.camera import get_camera
    try:
        s = SENSORS[name]
    except KeyError:
        raise ValueError(f'unknown sensor {name!r}; presets: {sorted(SENSORS)}') from None
    if width is None and height is None:
        return s
    base = name[:-len('_640x480')] if name.endswith('_640x480') else name
    return s.with_camera(get_camera(base, width, height))


def hair_vertices(body) -> np.ndarray:
    """(V,) bool: the head's upper back (scalp: the dark, low-albedo region a time-of-
    flight sensor loses), from the canonical template: head vertices above the eyes'
    height or behind the head's centre."""
    from smpl_depth_ros.body.parts import PART_NAMES
    v = body.canonical_vertices()
    v = v.cpu().numpy() if hasattr(v, 'cpu') else np.asarray(v)
    head = body.part_labels.cpu().numpy() == PART_NAMES.index('head')
    if not head.any():
        return head
    hv = v[head]
    y0 = np.percentile(hv[:, 1], 55)
    zc = np.median(hv[:, 2])
    return head & ((v[:, 1] > y0) | (v[:, 2] < zc - 0.02))
