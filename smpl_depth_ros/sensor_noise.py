"""Expected depth noise at run time, and the thresholds that scale with it (no ROS).

Person finding and fitting compare depths and residuals against thresholds (a depth jump
that cuts two blobs apart, a plane's inlier band, the robust scale of the data term, the
median residual that rejects a candidate, ...). Their defaults are right for a Kinect-v1
class sensor, whose noise at 3 m is ~1.5 cm; a D435 at 4 m has ~6 cm. `NoiseModel`
gives sigma(z), the expected axial noise (1 sigma, metres) at depth z, from one of:

* a sensor preset (`synth.sensors.SENSORS`, e.g. 'realsense_d435'), evaluated at the
  stream's own focal length (a stereo camera's error grows as its resolution drops);
* 'auto': estimated from the frames themselves (`estimate_noise`): planes fitted to
  small patches of the image (walls, floor, the body), the patches' residual scatter per
  0.5 m depth bin, averaged over frames (`AutoNoise`);
* 'none': the fixed defaults (sigma = 0).

The defaults were tuned on a Kinect v1, so what widens the thresholds is the *excess*
noise, `NoiseModel.excess(z)` = max(0, sigma(z) - EXCESS_OVER x sigma_KinectV1(z)): a
sensor as quiet as a Kinect v1 (or quieter: time of flight) keeps every default exactly,
and a noisier one (stereo far away) adds k x excess to each threshold (`scaled_*`).
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

BIN_M = 0.5           # depth bins of the estimate
PATCH = 8             # patch side (pixels of the decimated image)
MIN_PATCHES = 6       # patches a bin needs to count (over the frames averaged) ...
MIN_FRAME_PATCHES = 3  # ... and in one frame
EXCESS_OVER = 1.25   # noise up to this multiple of a Kinect v1's leaves the defaults
CLASS_HOLD = 1.15    # 'auto': a class, once held, is left only past its thresholds x this
CLASS_HOLD_FRAMES = 10  # ... once this many frames have been measured
CLASSES = ('tof', 'structured_light', 'stereo')
PATCH_QUANTILE = 0.3  # a bin's sigma: this quantile of its patches' scatter (curved and
                      # edge patches scatter more than the noise, never less)


def kinect_v1_sigma(z) -> np.ndarray:
    """Structured-light reference (Nguyen et al. 2012): 1.2 mm + 1.9 mm (z - 0.4)^2."""
    z = np.asarray(z, np.float64)
    return 0.0012 + 0.0019 * (z - 0.4) ** 2


@dataclass(frozen=True)
class NoiseModel:
    """sigma(z) as a table: `z` (metres, ascending) and `sigma` (metres) at those depths,
    linear in between and extrapolated as z^2 beyond (both structured light and stereo
    grow as z^2 far away; time of flight slower, which this overestimates a little).

    Attributes:
        z, sigma: the table (empty: no noise known, sigma = 0).
        kind: 'structured_light' | 'stereo' | 'tof' | 'unknown'.
        source: where it came from ('preset:NAME', 'estimated', 'none').
    """

    z: tuple = ()
    sigma: tuple = ()
    kind: str = 'unknown'
    source: str = 'none'

    def __call__(self, z) -> np.ndarray:
        z = np.asarray(z, np.float64)
        if not self.z:
            return np.zeros_like(z)
        zt, st = np.asarray(self.z), np.asarray(self.sigma)
        zz = z.reshape(-1)
        out = np.interp(zz, zt, st)
        hi = np.flatnonzero(zz > zt[-1])  # (few: the extrapolations only where needed)
        if len(hi):
            out[hi] = st[-1] * (zz[hi] / zt[-1]) ** 2
        lo = np.flatnonzero(zz < zt[0])
        if len(lo):
            out[lo] = st[0] * np.maximum(zz[lo] / zt[0], 0.0) ** 2
        return out.reshape(z.shape)

    def excess(self, z) -> np.ndarray:
        """Noise beyond what the defaults were tuned for (see the module doc), metres."""
        return np.maximum(0.0, self(z) - EXCESS_OVER * kinect_v1_sigma(z))

    def as_dict(self) -> dict:
        return dict(kind=self.kind, source=self.source,
                    sigma_mm_at={f'{z:.1f}': round(float(self(z)) * 1e3, 1)
                                 for z in (1.0, 2.0, 3.0, 4.0, 5.0)})


GRID = tuple(np.round(np.arange(0.5, 8.01, 0.25), 2))


def preset_noise(name: str, K: np.ndarray | None = None) -> NoiseModel:
    """The noise of a sensor preset, at the stream's focal length K[0, 0] when given."""
    from smpl_depth_ros.synth.sensors import SENSORS
    try:
        s = SENSORS[name]
    except KeyError:
        raise ValueError(f'unknown sensor {name!r}: a preset ({", ".join(sorted(SENSORS))}), '
                         "'auto' or 'none'") from None
    if K is not None and s.kind == 'stereo':
        s = s.with_camera(replace(s.camera, fx=float(K[0, 0]), fy=float(K[1, 1])))
    return NoiseModel(GRID, tuple(float(v) for v in s.sigma(np.asarray(GRID))), s.kind,
                      f'preset:{name}')


@dataclass
class NoiseEstimate:
    """One frame's measurement: per depth bin centre, the noise and the patch count, and
    the correlation ratio: the scatter of full-resolution patches over that of patches
    as many pixels across on the decimated image (1 for per-pixel noise; block-matching
    stereo noise, correlated over a few pixels, is partly absorbed by the small patches'
    planes and scatters less there)."""

    z: np.ndarray
    sigma: np.ndarray
    count: np.ndarray
    corr_ratio: float
    corr_count: int


_V, _U = np.mgrid[0:PATCH, 0:PATCH]
_A = np.stack([np.ones(PATCH * PATCH), _U.ravel(), _V.ravel()], 1).astype(np.float64)
MIN_VALID = 0.85  # share of a patch's pixels that must be valid


def _patch_bins(d: np.ndarray, every: int) -> dict[int, tuple[float, int]]:
    """Depth bin -> (PATCH_QUANTILE of the patches' plane-residual scatter, patches) for
    the PATCH x PATCH patches of `d` (every `every`-th one each way) that are mostly
    valid (MIN_VALID) and span a small depth range (no depth edge in them); the plane
    z = a + b u + c v is fitted to each patch's valid pixels."""
    h, w = (d.shape[0] // PATCH) * PATCH, (d.shape[1] // PATCH) * PATCH
    if h == 0 or w == 0:
        return {}
    p = d[:h, :w].reshape(h // PATCH, PATCH, w // PATCH, PATCH).swapaxes(1, 2)
    p = p[::every, ::every].reshape(-1, PATCH * PATCH)
    m = p > 0
    n = m.sum(1)
    ok = n >= MIN_VALID * PATCH * PATCH
    if not ok.any():
        return {}
    p, m, n = p[ok], m[ok].astype(np.float64), n[ok]
    big = np.where(m > 0, p, np.nan)
    zmed = np.nanmedian(big, axis=1)
    ok = np.nanmax(big, 1) - np.nanmin(big, 1) < np.maximum(0.1, 0.1 * zmed)
    if not ok.any():
        return {}
    p, m, n, zmed = p[ok], m[ok], n[ok], zmed[ok]
    M = np.einsum('nk,ki,kj->nij', m, _A, _A)
    rhs = np.einsum('nk,ki,nk->ni', m, _A, p)
    coef = np.linalg.solve(M + 1e-9 * np.eye(3), rhs[..., None])[..., 0]
    r = (p - coef @ _A.T) * m  # residuals about each patch's plane, 0 where invalid
    sig = np.sqrt((r ** 2).sum(1) / np.maximum(n - 3, 1))
    b = np.floor(zmed / BIN_M).astype(np.int64)
    out = {}
    for k in np.unique(b):
        sel = b == k
        if sel.sum() >= MIN_FRAME_PATCHES:
            out[int(k)] = (float(np.quantile(sig[sel], PATCH_QUANTILE)), int(sel.sum()))
    return out


def estimate_noise(depth: np.ndarray, step: int | None = None) -> NoiseEstimate:
    """Measure the depth noise of one frame (see the module doc).

    Args:
        depth: (H, W) metres, 0 invalid.
        step: decimation of the patches that measure the noise (default: about 320
            pixels across, as person finding, and at least 2).
    """
    H, W = depth.shape
    s = step or max(2, round(W / 320))
    d = np.nan_to_num(np.asarray(depth, np.float64), nan=0.0)
    coarse = _patch_bins(d[::s, ::s], 1)
    fine = _patch_bins(d, s)
    ks = sorted(coarse)
    z = np.array([(k + 0.5) * BIN_M for k in ks])
    sg = np.array([coarse[k][0] for k in ks])
    cnt = np.array([coarse[k][1] for k in ks], int)
    both = [k for k in ks if k in fine and coarse[k][0] > 1e-4]
    corr = float(np.median([fine[k][0] / coarse[k][0] for k in both])) if both else 1.0
    return NoiseEstimate(z, sg, cnt, corr, int(sum(fine[k][1] for k in both)))


def classify(sigma_at_z: np.ndarray, z: np.ndarray, corr_ratio: float,
             held: str | None = None) -> str:
    """A sensor class from measured noise (a heuristic; the thresholds use sigma(z),
    not the class): time of flight when the noise is well below a structured-light
    sensor's at the same depths (level < 0.6 of Nguyen et al.'s), stereo when it is
    well above (> 1.3) or strongly correlated in space (ratio < 0.7; a real Kinect v1,
    block matching too, measures 0.73 at level 1.0), else structured light. The level
    is the median over the depth bins from 1.5 to 4.5 m, where people are measured (a
    stereo camera's noise over a Kinect v1's falls with depth, both growing as z^2: the
    far walls alone can measure an OAK-D Pro below 1.3).

    `held`: the class so far. Leaving it takes the noise level past the thresholds
    by a factor CLASS_HOLD (a camera does not change class)."""
    z = np.asarray(z, np.float64)
    if not len(z):
        return 'unknown'
    far = (z >= 1.5) & (z <= 4.5)
    if not far.any():
        far = z >= 1.5 if (z >= 1.5).any() else np.ones(len(z), bool)
    level = float(np.median(np.asarray(sigma_at_z)[far] / kinect_v1_sigma(z[far])))
    # h > 1 makes a class easier to stay in, 1 / h harder to enter from another
    h = {c: 1.0 if held not in CLASSES else CLASS_HOLD if c == held else 1.0 / CLASS_HOLD
         for c in CLASSES}
    if level < 0.6 * h['tof']:
        return 'tof'
    if level > 1.3 / h['stereo'] or (corr_ratio < 0.7 and level > 0.8 / h['stereo']):
        return 'stereo'
    return 'structured_light'


class AutoNoise:
    """The 'auto' sensor: `update` with frames, `model` the running estimate.

    Per depth bin, a running mean of the frames' measurements weighted by their patch
    counts (at most `memory` frames' worth: a changed scene or camera settles within a
    few seconds); the correlation ratio likewise. Bins never measured follow the nearest
    measured ones as z^2 (NoiseModel's extrapolation). The class of each estimate is held
    into the next once CLASS_HOLD_FRAMES frames have been measured (`classify`).
    """

    def __init__(self, memory: int = 30):
        self.memory = memory
        self._sum: dict[int, list[float]] = {}  # bin -> [sum sigma * w, sum w]
        self._corr = [0.0, 0.0]
        self.frames = 0
        self._model: NoiseModel | None = None  # the estimate, until the next update
        self._kind: str | None = None  # the class of the last estimate

    def update(self, depth: np.ndarray) -> None:
        e = estimate_noise(depth)
        self.frames += 1
        self._model = None
        decay = 1.0 - 1.0 / self.memory
        for k in self._sum:
            self._sum[k][0] *= decay
            self._sum[k][1] *= decay
        for z, sgm, c in zip(e.z, e.sigma, e.count):
            k = int(round(z / BIN_M - 0.5))
            acc = self._sum.setdefault(k, [0.0, 0.0])
            acc[0] += sgm * c
            acc[1] += c
        self._corr[0] = self._corr[0] * decay + e.corr_ratio * e.corr_count
        self._corr[1] = self._corr[1] * decay + e.corr_count

    def model(self) -> NoiseModel:
        if self._model is None:
            self._model = self._estimate()
        return self._model

    def _estimate(self) -> NoiseModel:
        ks = sorted(k for k, (_, w) in self._sum.items() if w >= MIN_PATCHES)
        if not ks:
            return NoiseModel(source='estimated')
        z = np.array([(k + 0.5) * BIN_M for k in ks])
        sg = np.array([self._sum[k][0] / self._sum[k][1] for k in ks])
        corr = self._corr[0] / self._corr[1] if self._corr[1] > 0 else 1.0
        held = self._kind if self.frames > CLASS_HOLD_FRAMES else None
        self._kind = classify(sg, z, corr, held)
        return NoiseModel(tuple(float(v) for v in z), tuple(float(v) for v in sg),
                          self._kind, 'estimated')


def sensor_choices() -> tuple[str, ...]:
    """Valid values of the `sensor` parameter."""
    from smpl_depth_ros.synth.sensors import SENSORS
    return ('auto', 'none', *sorted(SENSORS))


def check_sensor(sensor: str) -> str | None:
    """Why `sensor` is not a valid `sensor` parameter value, or None."""
    if sensor in sensor_choices():
        return None
    return f'sensor must be one of {", ".join(sensor_choices())}; got {sensor!r}'


def noise_model(sensor: str, K: np.ndarray | None = None) -> NoiseModel | None:
    """The NoiseModel of a `sensor` parameter: a preset's, None for 'auto' (estimate
    from the frames), the zero model for 'none'."""
    if sensor == 'auto':
        return None
    if sensor == 'none':
        return NoiseModel()
    return preset_noise(sensor, K)


# -- thresholds ---------------------------------------------------------------------

def scaled_fit_config(fit, excess: float):
    """FitConfig with the noise-dependent thresholds widened for an excess noise
    (metres, `NoiseModel.excess` at the person's depth): the robust scale (+1x), its
    cold-start value (+2x), the track-lost and flip residuals (+1x), the ICP margin
    (+1.5x) and the free-space margin (+3x). Unchanged for excess 0."""
    e = float(excess)
    if e <= 0:
        return fit
    return replace(fit, gm_sigma=fit.gm_sigma + e, gm_sigma_start=fit.gm_sigma_start + 2 * e,
                   lost_residual_m=fit.lost_residual_m + e,
                   flip_residual_m=fit.flip_residual_m + e,
                   icp_margin_m=fit.icp_margin_m + 1.5 * e if fit.icp_margin_m > 0 else 0.0,
                   free_space_margin=fit.free_space_margin + 3 * e)


def scaled_reject_residual(base: float, excess: float) -> float:
    """The median residual above which a fit is no person, widened by the excess noise
    (the median |noise| is 0.67 sigma; the rest is room for the noisier fit)."""
    return base + max(float(excess), 0.0)


def scaled_spread(base: float, excess: float) -> float:
    """Per-vertex target coherence scale (fit.aggregate_by_vertex spread_m)."""
    return base + 0.7 * max(float(excess), 0.0)
