"""The Reconstructor: depth (H, W) metres + K -> FrameResult (no ROS).

preprocess (find persons, crop) -> double U-Net -> Eq. 2 correspondences -> fit
(warm-started from the previous frame while the track holds) -> ICP refinement (refine)
-> labels from the fitted mesh (segmentation) -> result. The live node and offline
processing are two thin drivers of this class. `process` runs a frame's two stages:
`detect` (the frame checked, its sensor noise, its person candidates; no track read) and
`reconstruct` (the rest), which the live node runs on two threads, one frame apart.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import numpy as np
import torch

from smpl_depth_ros.body import load_body_model
from smpl_depth_ros.config import (EXTRA_CANDIDATES, GIVE_UP, HELD_BODY_GAIN, MAX_CLAIMED,
                                   MAX_SEE_THROUGH, MIN_BEHIND, MIN_BODY_PIXELS, MIN_ENCLOSED,
                                   MIN_BODY_SHARE, MIN_COLD_SCORE, MIN_PART_SHARE,
                                   NEAREST_CANDIDATES, NOT_PERSON_FRAMES, NOT_PERSON_IOU,
                                   RANK_AREA_M2, SECOND_LOOK_CANDIDATES, SECOND_LOOK_EVERY,
                                   SEE_THROUGH_GAP_M, PipelineConfig)
from smpl_depth_ros.denoise import smooth
from smpl_depth_ros.fit import Fitter, backproject  # noqa: F401  (re-exported)
from smpl_depth_ros.fit.freespace import FreeSpace, see_through_share, supporting_planes
from smpl_depth_ros.net.infer import CorrespondenceNet, broad_weights
from smpl_depth_ros.net.preprocess import (BEHIND_GAP_M, crop_depth, enclosed_share,
                                           find_persons, network_input, pixel_points,
                                           split_side_by_side)
from smpl_depth_ros.rectify import Lens, Rectifier
from smpl_depth_ros.refine import (SurfaceParts, depth_gap, facing_camera, near_surface_pixels,
                                   refine_correspondences, rigid_icp)
from smpl_depth_ros.segmentation import (LabelSurface, label_window,
                                         paste_model_labels, paste_network_labels)
from smpl_depth_ros.sensor_noise import (AutoNoise, NoiseModel, check_sensor, noise_model,
                                         scaled_reject_residual, scaled_spread)
from smpl_depth_ros.tracking import MIN_OVERLAP, Tracker, candidate_centre
from smpl_depth_ros.types import FrameResult, InputError, PersonResult

MAX_FOV_DEG = 170.0  # intrinsics implying a wider field of view are rejected ...
MAX_FOCAL_PER_PIXEL = 1e4  # ... and so are focal lengths above this many image sides
MIN_FOV_DEG = round(float(np.degrees(2 * np.arctan(0.5 / MAX_FOCAL_PER_PIXEL))), 4)
CONF_POINTS = 15.0  # joint_confidence: pixels for a joint's support to count as ample
CONF_RESIDUAL_M = 0.06  # joint_confidence: residual scale (widened for sensor noise)
AUTO_FIRST = 10  # sensor 'auto': the noise is measured on each of the first frames ...
AUTO_EVERY = 10  # ... then on every AUTO_EVERY-th (a few ms each)
BROAD_NETWORK_FOR = ('stereo',)  # sensor classes whose frames use the broad network (with
                                # weights_path ''): chosen on the validation sweep, where
                                # it found 6-18 points more of the stereo frames and was
                                # 0-1 mm worse on time of flight, 3-5 mm on structured light


@dataclass
class Detection:
    """A frame after `Reconstructor.detect`: what `Reconstructor.reconstruct` needs.

    Attributes:
        depth: (H, W) float32 metres, invalid pixels 0 (validated).
        K: (3, 3) float64 intrinsics.
        stamp_ns: capture time (None: frames counted at 30 Hz).
        index: the frame's number since the core was loaded or restarted (from 1).
        noise: the sensor noise model for this frame (None: default thresholds).
        net: the correspondence network for this frame (the sensor class decides).
        crops: the person candidates (net.preprocess.Crop), most central first, then the
            nearest of the others (`Crop.nearest`).
        ms: time the detection took.
        passes: id(crop) -> (crop, network input, labels, coords, Eq. 2 vertex ids of its
            body pixels, the network that made it): the network passes made ahead
            (`Reconstructor.look_ahead`); `reconstruct` makes the others.
        ahead_ms: time those passes and lookups took (counted as the network's).
        rectifier: the lens's maps when the frame was resampled from a lens's own image
            (`undistort`; `depth` and `K` are then the pinhole image's), else None.
        too_big: large blobs person finding left whole as not person-sized (a person
            may be merged into one: `reconstruct`'s second look peels them).
    """

    depth: np.ndarray
    K: np.ndarray
    stamp_ns: int | None
    index: int
    noise: NoiseModel | None
    net: CorrespondenceNet
    crops: list
    ms: float
    passes: dict = field(default_factory=dict)
    ahead_ms: float = 0.0
    rectifier: Rectifier | None = None
    too_big: int = 0


def resolve_device(name: str) -> torch.device:
    if name == 'auto':
        return torch.device('cuda' if torch.cuda.is_available() else 'cpu')
    if name == 'cuda' and not torch.cuda.is_available():
        raise RuntimeError("device 'cuda' requested but torch.cuda.is_available() is False")
    if name not in ('cpu', 'cuda'):
        raise ValueError(f"device must be 'auto', 'cpu' or 'cuda', got {name!r}")
    return torch.device(name)


def validate_input(depth: np.ndarray, K: np.ndarray, max_pixels: int) -> np.ndarray:
    """Check a frame; returns depth as float32 with invalid pixels = 0.

    Raises:
        InputError with reason 'bad_depth', 'too_large', 'bad_intrinsics' or
        'no_valid_depth'.
    """
    depth = np.asarray(depth)
    if depth.ndim != 2 or depth.size == 0:
        raise InputError('bad_depth', f'depth must be a non-empty (H, W) image, got shape '
                         f'{depth.shape}')
    if depth.size > max_pixels:
        raise InputError('too_large', f'depth image {depth.shape[1]}x{depth.shape[0]} exceeds '
                         f'max_image_pixels={max_pixels}')
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise InputError('bad_intrinsics', f'camera matrix K is unusable (fx, fy must be > 0): '
                         f'{K.reshape(-1).tolist() if K.size == 9 else K.shape}')
    if not np.allclose(K[2], (0.0, 0.0, 1.0), atol=1e-6):
        raise InputError('bad_intrinsics', f'camera matrix K has last row {K[2].tolist()}, '
                         'expected [0, 0, 1]')
    side = max(depth.shape)
    lo, hi = side / (2 * np.tan(np.radians(MAX_FOV_DEG / 2))), side * MAX_FOCAL_PER_PIXEL
    for name, f in (('fx', K[0, 0]), ('fy', K[1, 1])):
        if not lo <= f <= hi:
            fov = np.degrees(2 * np.arctan(side / (2 * f)))
            raise InputError('bad_intrinsics', f'camera matrix {name}={f:g} px gives a '
                             f'{depth.shape[1]}x{depth.shape[0]} image a field of view of '
                             f'{fov:.3g} deg (a depth camera: {MIN_FOV_DEG}-{MAX_FOV_DEG} deg, '
                             f'{name} in [{lo:.3g}, {hi:.3g}])')
    for name, c, n in (('cx', K[0, 2], depth.shape[1]), ('cy', K[1, 2], depth.shape[0])):
        if abs(c - n / 2) > 5 * n:
            raise InputError('bad_intrinsics', f'camera matrix {name}={c:g} lies far outside '
                             f'the {n}-pixel image')
    d = np.nan_to_num(depth.astype(np.float32, copy=False), nan=0.0, posinf=0.0, neginf=0.0)
    if not np.any(d > 0):
        raise InputError('no_valid_depth', 'depth image has no valid pixel (all zero/NaN)')
    return d


def body_score(crop, valid: np.ndarray, labels: np.ndarray, image_shape) -> float:
    """How much of a body the network sees in a candidate: the share of the candidate's
    own blob pixels (those of `valid`, its crop's valid input pixels, that map into its
    full-image mask) labelled body, times the number of parts covering >= 2 % of them
    (MIN_PART_SHARE).
    The blob's share, not the crop's: a crop's background grows with a person's reach,
    while a person-sized box fills its crop (and outranked a person in front of a wall)."""
    blob = valid
    if crop.mask is not None:
        rr, cc, inside = crop.sample_indices(image_shape)
        blob = blob & inside & crop.mask[rr, cc]
    fg = (labels > 0) & blob
    n = max(int(fg.sum()), 1)
    parts = int((np.bincount(labels[fg], minlength=2)[1:] >= MIN_PART_SHARE * n).sum())
    return n / max(int(blob.sum()), 1) * parts


def seen_area(crop, d: np.ndarray, K: np.ndarray) -> float:
    """The area (m^2) of the surface a candidate's blob shows the camera: each pixel of
    its mask covers (z / fx) (z / fy). Unlike its pixel count, it does not shrink with
    distance: a whole person shows 0.18 m^2 or more (seated on a chair the least)."""
    z = d[crop.mask]
    return float((z.astype(np.float64) ** 2).sum() / (K[0, 0] * K[1, 1]))


def known_blob(mask: np.ndarray, blobs) -> bool:
    """Whether a candidate's `mask` is one of `blobs` ((mask, frame) pairs, the blobs
    found to be no person): intersection over union >= NOT_PERSON_IOU."""
    return any(m.shape == mask.shape and (m & mask).sum() >= NOT_PERSON_IOU *
               (m | mask).sum() for m, _ in blobs)


def shared_pixels(crops, masks) -> np.ndarray:
    """(len(crops), len(masks)): the pixels each crop's mask shares with each of `masks`."""
    return np.array([[int((c.mask & m).sum()) for m in masks] for c in crops],
                    np.int64).reshape(len(crops), len(masks))


def by_overlap(crops, masks, shared: np.ndarray | None = None) -> list:
    """`crops` ordered by the most pixels they share with any of `masks` (the tracks'
    last pixels), most first; ties keep their order. `shared`: `shared_pixels(crops,
    masks)` when already counted."""
    shared = shared_pixels(crops, masks) if shared is None else shared
    order = np.argsort(-shared.max(1), kind='stable')
    return [crops[i] for i in order]


def _enclosed(crop, persons: list[PersonResult], gap_m: float = BEHIND_GAP_M) -> float:
    """The largest share of a candidate's blob that the pixels of a person found at least
    `gap_m` nearer enclose (`net.preprocess.enclosed_share`)."""
    return max([enclosed_share(crop.mask, p.mask) for p in persons
                if p.crop.median_depth <= crop.median_depth - gap_m], default=0.0)


def body_pixels(x: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """(S, S) bool: the crop pixels with depth (network input `x`) labelled body."""
    return (labels > 0) & (x[1] > 0)


def on_raw_pixels(result: FrameResult, rect: Rectifier) -> FrameResult:
    """A result reconstructed on a lens-distorted frame's pinhole image (`undistort`)
    with its labels, masks and pixels moved onto the raw image's pixels (the 3D outputs
    are the same in both: the camera frame does not change)."""
    persons = []
    for p in result.persons:
        pixels = p.pixels
        if pixels is not None:
            r, c = rect.raw_pixels(pixels[:, 0], pixels[:, 1])
            pixels = np.stack([r, c], 1)
        persons.append(replace(p, mask=rect.to_raw(p.mask), pixels=pixels))
    net = result.network_labels
    return replace(result, persons=persons, labels=rect.to_raw(result.labels),
                   network_labels=None if net is None else rect.to_raw(net))


@dataclass
class Unfinished:
    """What `Reconstructor.finish` does to a result of `reconstruct(..., finish=False)`:
    paste the model labels of each person (`labels`: (person index, LabelWindow, fitted
    vertices, the crop's scene planes)) with the frame's `depth` and `K` and the
    segmentation settings of the frame (`margin_m`, `keep_network_m`), then move the
    result onto the raw pixels of a lens-distorted frame (`rectifier`)."""

    depth: np.ndarray
    K: np.ndarray
    labels: list
    margin_m: float
    keep_network_m: float
    rectifier: Rectifier | None = None


def joint_adjacency(parents) -> np.ndarray:
    """(J, J) 0/1: the segments that observe each joint: its own and its parent's (the
    two bones meeting at it), the root's own and its children's."""
    parents = np.asarray(parents)
    A = np.eye(len(parents))
    for j, p in enumerate(parents):
        if p >= 0:
            A[j, p] = 1
            if p == 0:
                A[0, j] = 1
    return A


def joint_confidence(segment_of_vertex: np.ndarray, vids: np.ndarray,
                     residuals: np.ndarray, adjacency: np.ndarray,
                     scale: float = 0.06) -> np.ndarray:
    """(J,) float32 in [0, 1]: how well each fitted joint is supported by observed
    pixels: (1 - exp(-n / CONF_POINTS)) times the mean of exp(-(r / scale)^2) over the
    n fitted pixels on the segments that observe the joint (`joint_adjacency`; r: their
    distance to their vertex, which a good fit keeps at 1-3 cm on a mesh whose vertices
    are 2-4 cm apart). 0 for a joint no pixel saw (its pose is the prior's)."""
    J = len(adjacency)
    seg = segment_of_vertex[vids]
    good = np.exp(-(np.asarray(residuals, np.float64) / scale) ** 2)
    n = adjacency @ np.bincount(seg, minlength=J)[:J].astype(np.float64)
    s = adjacency @ np.bincount(seg, weights=good, minlength=J)[:J]
    return ((1 - np.exp(-n / CONF_POINTS)) * s / np.maximum(n, 1)).astype(np.float32)


class Reconstructor:
    """Loads the body model and network once; `process` reconstructs one frame.

    Args:
        config: PipelineConfig.
        body: optional pre-built body model (else built from config.backend/model_path).
    """

    def __init__(self, config: PipelineConfig = PipelineConfig(), body=None):
        self.config = config
        if check_sensor(config.sensor):
            raise ValueError(check_sensor(config.sensor))
        self.device = resolve_device(config.device)
        self.body = body if body is not None else load_body_model(
            config.backend, config.model_path or None, device=self.device)
        self._net = CorrespondenceNet(self.body, config.weights_path, device=self.device,
                                      precision=config.net_precision)
        broad = None if config.weights_path else broad_weights(self.body.name)
        self._broad_net = (CorrespondenceNet(self.body, broad, device=self.device,
                                             precision=config.net_precision)
                           if broad else None)
        self.fitter = Fitter(self.body, config.fit)
        self.faces = self.body.faces_numpy()
        self.surface = SurfaceParts.from_body(self.body)  # for the ICP refinement
        self.label_surface = LabelSurface.from_body(self.body)  # for segmentation 'model'
        self.tracker = Tracker(config.track_timeout_s, config.track_gate_m)
        self._joint_adjacency = joint_adjacency(self.body.joint_parents)
        self._auto = AutoNoise() if config.sensor == 'auto' else None
        self._preset: tuple | None = None  # (fx, NoiseModel) of a sensor preset
        self._frames = 0  # frames detected (`detect`) ...
        self._frame = 0  # ... and the number of the one being reconstructed ...
        self._frame_net: CorrespondenceNet | None = None  # ... and its network
        self._ahead: dict = {}  # ... and its network passes made ahead (`look_ahead`)
        self._not_persons: list = []  # (blob mask, frame) found to be no person
        self._lens: tuple | None = None  # (camera key, Rectifier) of the last lens undone

    @property
    def net(self) -> CorrespondenceNet:
        """The correspondence network for the frames now: the given `weights_path`, or
        of the shipped ones the broad network (every sensor class and the broad poses in
        training) for the sensor classes of BROAD_NETWORK_FOR (`sensor`: a preset's
        class, or the class 'auto' measures), the original one (Kinect v1 noise and the
        activity templates) otherwise."""
        if self._broad_net is not None and self.noise.kind in BROAD_NETWORK_FOR:
            return self._broad_net
        return self._net

    @property
    def net_precision(self) -> str:
        """The networks' arithmetic in use: 'float32' or 'bfloat16' (`net_precision`)."""
        return str(self._net.dtype).removeprefix('torch.')

    @property
    def other_net(self) -> CorrespondenceNet | None:
        """The shipped network `net` is not (None with a given `weights_path`, or a
        backend with one network): `second_network`'s fallback."""
        return self._other(self.net)

    def _other(self, net: CorrespondenceNet) -> CorrespondenceNet | None:
        """The shipped network `net` is not (None without a second one)."""
        if self._broad_net is None:
            return None
        return self._net if net is self._broad_net else self._broad_net

    @property
    def noise(self) -> NoiseModel:
        """The sensor noise model in use (a preset's at the last frame's focal length, the
        'auto' estimate so far, or the zero model for 'none')."""
        if self._auto is not None:
            return self._auto.model()
        return self._preset[1] if self._preset else noise_model(self.config.sensor)

    def _noise_for(self, d, K) -> NoiseModel | None:
        """The noise model for this frame (see `noise`); None when it leaves every
        threshold at its default (sensor 'none', or nothing measured yet)."""
        self._frames += 1
        if self._auto is not None:
            if self._frames <= AUTO_FIRST or self._frames % AUTO_EVERY == 0:
                self._auto.update(d)
            m = self._auto.model()
            return m if m.z else None
        if self.config.sensor == 'none':
            return None
        if self._preset is None or self._preset[0] != K[0, 0]:
            self._preset = (K[0, 0], noise_model(self.config.sensor, K))
        return self._preset[1]

    def reset(self) -> None:
        """Forget the tracks (the next frame is fitted cold; persons get new IDs)."""
        self.tracker.clear()
        self._not_persons = []

    def restart(self) -> None:
        """Back to the state just after loading: no tracks and IDs from 1 again, the 'auto'
        sensor noise measured afresh, the fitter's random stream from its start. What
        follows then depends only on the frames given from now on (a chunk of a bag on
        a worker, the next bag of a batch)."""
        self.tracker = Tracker(self.config.track_timeout_s, self.config.track_gate_m)
        self._auto = AutoNoise() if self.config.sensor == 'auto' else None
        self._preset = None
        self._frames = self._frame = 0
        self._not_persons = []
        self.fitter.reseed()

    def set_config(self, config: PipelineConfig) -> None:
        """Change the configuration between frames (the node's run-time parameters; a
        new device or body model needs a new Reconstructor). A changed `sensor` starts
        its noise model afresh."""
        if check_sensor(config.sensor):
            raise ValueError(check_sensor(config.sensor))
        old, self.config = self.config, config
        self.tracker.timeout_s = config.track_timeout_s
        self.tracker.gate_m = config.track_gate_m
        if config.fit != old.fit:
            self.fitter = Fitter(self.body, config.fit)
        if config.net_precision != old.net_precision:
            for net in (self._net, self._broad_net):
                if net is not None:
                    net.set_precision(config.net_precision)
        if config.sensor != old.sensor:
            self._auto = AutoNoise() if config.sensor == 'auto' else None
            self._preset = None

    def set_fit_config(self, fit_cfg) -> None:
        self.config = self.config.with_overrides(**{f: getattr(fit_cfg, f) for f in
                                                     fit_cfg.__dataclass_fields__})
        self.fitter = Fitter(self.body, fit_cfg)

    def process(self, depth: np.ndarray, K: np.ndarray, stamp_ns: int | None = None,
                lens: Lens | None = None) -> FrameResult:
        """Reconstruct the persons in one depth frame: `reconstruct(detect(...))`.

        Args:
            depth: (H, W) metres (float; 0/NaN invalid).
            K: (3, 3) intrinsics of this image.
            stamp_ns: capture time, for tracking gaps (None: treat as consecutive).
            lens: the camera's lens (`rectify.Lens`, from its camera_info), or None (a
                pinhole camera). With a non-zero D the image is either the lens's own,
                resampled to pinhole first (`rectify.Rectifier`), or a rectified one,
                seen through the lens's P: `undistort` says which.

        Returns:
            FrameResult (persons most central first; labels, masks and pixels on the
            input image's pixels).

        Raises:
            InputError for unusable frames, with reason 'no_person' when nobody is found.
        """
        return self.reconstruct(self.detect(depth, K, stamp_ns, lens))

    def detect(self, depth: np.ndarray, K: np.ndarray, stamp_ns: int | None = None,
               lens: Lens | None = None) -> Detection:
        """The first stage of `process`: the frame checked, its sensor noise and its
        person candidates. It reads no track and no fit, so a live node may run it on the
        next frame while `reconstruct` runs on this one: as long as each stage takes the
        frames in order, the results are those of `process`.

        Raises:
            InputError for unusable frames (not for frames without candidates: their
            `reconstruct` says so, after the tracks have seen the frame).
        """
        cfg = self.config
        t0 = time.perf_counter()
        d = validate_input(depth, K, cfg.max_image_pixels)
        K = np.asarray(K, np.float64)
        rect = None
        if lens is not None and lens.distorted:
            if lens.undo(cfg.undistort):
                rect = self._rectifier(K, lens, d.shape)
                d, K = rect.rectify(d), rect.K
            else:
                K = np.asarray(lens.P, np.float64)
        noise = self._noise_for(d, K)
        if cfg.denoise:
            d = smooth(d, noise)
        report: dict = {}
        crops = find_persons(d, K, cfg.depth_min, cfg.depth_max, cfg.min_person_pixels,
                             max_persons=max(cfg.max_persons, 1) + EXTRA_CANDIDATES,
                             nearest=NEAREST_CANDIDATES,
                             noise=None if noise is None else noise.excess, report=report)
        return Detection(d, K, stamp_ns, self._frames, noise, self.net, crops,
                         (time.perf_counter() - t0) * 1e3, rectifier=rect,
                         too_big=report.get('too_big', 0))

    def _rectifier(self, K: np.ndarray, lens: Lens, shape) -> Rectifier:
        """The lens maps of a camera (made once per camera: the last one is kept)."""
        model, D = str(lens.model), np.asarray(lens.D, np.float64).reshape(-1)
        key = (K.tobytes(), model, D.tobytes(), tuple(shape))
        if self._lens is None or self._lens[0] != key:
            try:
                rect = Rectifier.for_camera(K, model, D, (shape[1], shape[0]))
            except ValueError as e:
                raise InputError('distortion', f'undistort: {e}') from None
            self._lens = (key, rect)
        return self._lens[1]

    def look_ahead(self, det: Detection) -> None:
        """Between `detect` and `reconstruct`: the network passes `reconstruct` will most
        likely make and their Eq. 2 lookups, made now (into `det.passes`), so that a live
        node can run them on its detecting thread beside the reconstruction of the frame
        before (both let go of the interpreter lock). Only the time changes:
        `reconstruct` uses a pass made here as one of its own (each is one crop's, from
        the same network), and makes those missing.

        Which candidates: while persons are tracked, as many as there are tracks with a
        fit, those covering most of the tracks' last pixels first, not those seen
        through a gap of a nearer one nor those found to be no person of late
        (`_maybe_persons`; what the tracks and that memory say may be a frame old, which
        only costs the odd pass made twice or in vain); else those `reconstruct` would
        run first (all of them when there are more than max_persons to rank). Not with
        flip_tta (its ranking uses the plain pass only).
        """
        cfg = self.config
        if cfg.flip_tta or not det.crops:
            return
        t0 = time.perf_counter()
        crops = det.crops
        tracks = [tr for tr in list(self.tracker.tracks)
                  if tr.fit is not None and tr.mask is not None
                  and tr.mask.shape == det.depth.shape]
        nets = {}  # id(crop) -> the network of the track whose pixels it covers most
        if cfg.tracking and tracks:
            known = list(self._not_persons)
            crops = [c for c in crops if not c.behind and c.mask is not None
                     and not known_blob(c.mask, known)]
            prev = [tr.mask for tr in tracks]
            shared = shared_pixels(crops, prev)
            for c, row in zip(crops, shared):
                nets[id(c)] = self._track_net(tracks[int(np.argmax(row))], det.net)
            crops = by_overlap(crops, prev, shared)[:min(len(prev), cfg.max_persons)]
        else:
            central = [c for c in crops if not c.nearest]
            if len(central) <= cfg.max_persons:
                crops = (central + [c for c in crops if c.nearest])[:cfg.max_persons]
            else:
                crops = central
        for c in crops:
            net = nets.get(id(c), det.net)
            ((x, lab, coords),) = self._network(det.depth, [c], net)
            det.passes[id(c)] = (c, x, lab, coords, net.lookup(lab, coords, body_pixels(x, lab)),
                                 net)
        det.ahead_ms = (time.perf_counter() - t0) * 1e3

    def _network(self, d, crops, net, passes: dict | None = None) -> list:
        """The plain network passes of `crops` by `net` (one crop each: a pass is the
        same made ahead or not), [(input, labels, coords)], taken from `passes`
        (`Detection.passes`) where there."""
        out = []
        for c in crops:
            hit = (passes or {}).get(id(c))
            if hit is not None and hit[0] is c and hit[5] is net:
                out.append(hit[1:4])
                continue
            x = network_input(crop_depth(d, c), c.median_depth)
            (lab,), (coords,) = net.predict(x[None], flip_tta=False)
            out.append((x, lab, coords))
        return out

    def reconstruct(self, det: Detection, finish: bool = True) -> FrameResult:
        """The second stage of `process`: the persons of a frame `detect`ed (see there).
        With `finish` False the last step, the persons' labels from their fitted meshes
        (segmentation 'model') and the move onto a lens's raw pixels, is left to
        `finish`, which needs no state of the reconstructor: a live node runs it on a
        third thread beside the next frame's fits. The result is the same either way.

        Raises:
            InputError with reason 'no_person' when nobody is found.
        """
        cfg = self.config
        t0 = time.perf_counter()
        d, K, stamp_ns, noise, crops = det.depth, det.K, det.stamp_ns, det.noise, det.crops
        excess = None if noise is None else noise.excess
        self._frame, self._frame_net, self._ahead = det.index, det.net, det.passes
        t = self._clock(stamp_ns)
        self.tracker.expire(t)
        t1 = time.perf_counter()
        labels_full = np.zeros(d.shape, np.uint8)
        network_full = (np.zeros(d.shape, np.uint8) if cfg.segmentation == 'model'
                        else labels_full)
        timings = dict(preprocess=det.ms + (t1 - t0) * 1e3, network=det.ahead_ms,
                       correspondence=0.0, fit=0.0, labels=0.0)
        if not crops:
            self.tracker.forget_fits()
            raise InputError('no_person', f'no person found between {cfg.depth_min:.2f} and '
                             f'{cfg.depth_max:.2f} m')
        rejected = []  # (test, value, limit) of the fits rejected as no person (`_persons`)
        seen: set[int] = set()  # ids of the tracks seen in this frame
        todo = Unfinished(d, K, [], cfg.model_label_margin_m, cfg.model_label_keep_network_m,
                          det.rectifier)
        warm = {id(tr) for tr in self.tracker.tracks if tr.fit is not None}
        persons = self._persons(d, K, self._maybe_persons(crops), stamp_ns, timings,
                                network_full, todo, rejected, noise, seen)
        if not persons or (len(persons) < cfg.max_persons and det.too_big and (
                warm - seen or det.index % SECOND_LOOK_EVERY == 1)):
            # Second look: none of the candidates was a person, but a person standing
            # against a wall may be hidden in a blob too big for one: peel its planes;
            # and the person may be a less central blob than those tried: take more.
            # Also when fewer persons than wanted were found and such a blob was left
            # whole, if a person tracked in the frame before is missing, and on the
            # first frame and every SECOND_LOOK_EVERY-th after: a person joined to the
            # floor, a box or a wall by the sensor's noise (stereo), or to another person.
            tp = time.perf_counter()
            again = find_persons(d, K, cfg.depth_min, cfg.depth_max, cfg.min_person_pixels,
                                 max_persons=max(cfg.max_persons, 1) + SECOND_LOOK_CANDIDATES,
                                 nearest=NEAREST_CANDIDATES, peel=True, noise=excess)
            tried = [(int(o.mask.sum()), o.mask) for o in crops]
            sizes = [int(c.mask.sum()) for c in again]
            new = [c for c, n in zip(again, sizes) if not any(
                n == k and np.array_equal(c.mask, m) for k, m in tried)]
            if persons:  # not the persons found again (a limb, a piece cut off them)
                found = np.logical_or.reduce([p.mask for p in persons])
                new = [c for c in new if (c.mask & found).sum() <= MAX_CLAIMED * c.mask.sum()]
            timings['preprocess'] += (time.perf_counter() - tp) * 1e3
            new = self._maybe_persons(new)
            if new:
                persons = self._persons(d, K, new, stamp_ns, timings, network_full, todo,
                                        rejected, noise, seen, found=persons)
                crops = crops + new
        other = self._other(det.net)
        if not persons and rejected and cfg.second_network and other is not None:
            # Third look: a body was seen but no fit explained it. The other shipped
            # network (broad poses and every sensor class, or the original) gets the same
            # candidates: a frame one network fails on, the other often gets.
            persons = self._persons(d, K, list(crops), stamp_ns, timings, network_full,
                                    todo, rejected, noise, seen, net=other)
        self.tracker.forget_fits(keep=seen)  # warm starts come from the previous frame only
        if not persons:
            residuals = [r for r in rejected if r[0] == 'residual']
            if residuals:
                _, best, limit = min(residuals)
                why = (f'reject_residual_m {limit * 1e3:.0f} mm'
                       if limit == cfg.reject_residual_m else
                       f'{limit * 1e3:.0f} mm: reject_residual_m '
                       f'{cfg.reject_residual_m * 1e3:.0f} mm widened for the sensor noise')
                raise InputError('no_person', 'person candidates found, but no body fit '
                                 f'explained them (best median residual {best * 1e3:.0f} '
                                 f'mm > {why})')
            if rejected:
                kind, value, limit = min(rejected)
                raise InputError('no_person', 'person candidates found, but no body fitted to '
                                 'them was a person: ' + (
                                     f'the sensor sees through {value:.0%} of the fitted '
                                     f'body\'s visible side (> {limit:.0%})'
                                     if kind == 'see_through' else
                                     f'a new person in whom the network sees too few '
                                     f'body parts (body score {-value:.1f} < '
                                     f'{limit:.1f})'))
            raise InputError('no_person', 'person candidates found, but the network '
                             'segmented no body in them')
        result = FrameResult(persons=persons, labels=labels_full, timings_ms=timings,
                             network_labels=network_full, unfinished=todo)
        timings['total'] = det.ms + det.ahead_ms + (time.perf_counter() - t0) * 1e3
        return self.finish(result) if finish else result

    def finish(self, result: FrameResult) -> FrameResult:
        """The last step of `reconstruct` (see there), on its result; reads nothing the
        next frame's `detect` or `reconstruct` changes. A finished result is returned
        as it is."""
        todo = result.unfinished
        if todo is None:
            return result
        t0 = time.perf_counter()
        persons = list(result.persons)
        for k, win, vertices, planes in todo.labels:
            persons[k] = replace(persons[k], mask=paste_model_labels(
                result.labels, win, todo.depth, todo.K, vertices, self.label_surface,
                planes, margin_m=todo.margin_m, keep_network_m=todo.keep_network_m))
        result = replace(result, persons=persons, unfinished=None)
        if todo.rectifier is not None:
            result = on_raw_pixels(result, todo.rectifier)
        ms = (time.perf_counter() - t0) * 1e3
        result.timings_ms['labels'] += ms
        result.timings_ms['total'] += ms
        return result

    def _maybe_persons(self, crops) -> list:
        """The candidates of this frame to look at: with tracking, those that are not a
        blob found to be no person (`_not_a_person`) during the last
        NOT_PERSON_FRAMES frames (intersection over union >= NOT_PERSON_IOU): a box
        beside the person costs a network pass once every NOT_PERSON_FRAMES frames, not
        in every frame (`max_persons` > 1 on a single-person stream)."""
        self._not_persons = [(m, f) for m, f in self._not_persons
                             if 0 <= self._frame - f <= NOT_PERSON_FRAMES]
        if not self.config.tracking or not self._not_persons:
            return list(crops)
        return [c for c in crops if c.mask is None or not known_blob(c.mask, self._not_persons)]

    def _not_a_person(self, crop, net, K, t: float) -> None:
        """Remember (`_maybe_persons`) a candidate matching no track in which the
        frame's network saw no body, or too little of one for a new person, or, beside a
        person found in the frame, whose body fit was rejected; not one
        near where a live track is expected or on its last pixels (MIN_OVERLAP of the
        blob): a tracked person lost for a moment, half hidden, must be found again as
        soon as it shows."""
        if not (self.config.tracking and net is self._frame_net and crop.mask is not None):
            return
        m = crop.mask
        if self.tracker.near(candidate_centre(crop, K), t) or any(
                tr.mask is not None and tr.mask.shape == m.shape and
                (tr.mask & m).sum() > MIN_OVERLAP * m.sum() for tr in self.tracker.tracks):
            return
        self._not_persons.append((m, self._frame))

    def _clock(self, stamp_ns: int | None) -> float:
        """The tracks' time (s) of a frame: its stamp, or frames counted at 30 Hz."""
        return stamp_ns * 1e-9 if stamp_ns is not None else self._frame / 30.0

    def _persons(self, d, K, crops, stamp_ns, timings, network_full, todo: Unfinished,
                 rejected: list, noise: NoiseModel | None = None,
                 seen: set | None = None, net: CorrespondenceNet | None = None,
                 found: list | None = None) -> list[PersonResult]:
        """Run the network on the candidates and fit them, until max_persons are found
        (see `process`); writes their network labels into network_full, adds their model
        labels (segmentation 'model') to `todo` (`finish`), and appends (test, value,
        limit) of every fit rejected as no person to `rejected` (test 'residual': its
        median residual above the limit; 'see_through': a further person's share of its
        visible side the sensor sees through, above MAX_SEE_THROUGH; 'score': minus its
        body score, a new person's (no track) below MIN_COLD_SCORE). `noise`: the sensor
        noise model; each candidate's noise-dependent thresholds are widened for the
        excess noise at its median depth (sensor_noise). Each candidate is matched to
        its track (tracking) before it is fitted; `seen` collects the ids of the tracks
        of accepted persons. `net`: the network to use (default: the frame's, `Detection.net`).
        `found`: the persons found in the frame so far (a second look): returned with those
        added, their pixels claimed, their tracks in `seen`."""
        cfg = self.config
        net = net or self._frame_net
        third = net is not self._frame_net  # the third look: the other network
        seen = set() if seen is None else seen
        t = self._clock(stamp_ns)
        persons = list(found or [])
        claimed = np.zeros(d.shape, bool)  # pixels of the persons reconstructed so far
        for p in persons:
            claimed |= p.mask
        split_done: set[int] = set()  # halves of split candidates are not split again
        plain_retried: set[int] = set()  # flip_tta: candidates retried on the plain pass
        x, lab, coords = [], [], []  # network inputs and outputs, per candidate so far
        plain = {}  # candidate -> its plain network pass, when the mirrored one is pending
        if len(crops) > cfg.max_persons or (cfg.tracking and len(crops) > 1):
            crops, x, lab, coords, plain = self._rank_candidates(d, K, crops, timings, net)
        made_by = [net] * len(x)  # the network of each candidate's labels and coords
        track_of = dict(zip(map(id, crops), self.tracker.match(
            np.array([candidate_centre(c, K) for c in crops]).reshape(-1, 3),
            [c.mask for c in crops], t, exclude=seen)))
        for i, crop in enumerate(crops):
            if len(persons) >= cfg.max_persons:
                break
            tr = track_of.get(id(crop))
            if crop.behind and persons and (tr is None or tr.mask is None or
                                            crop.mask.sum() < MIN_BEHIND * tr.mask.sum()) \
                    and _enclosed(crop, persons) >= MIN_ENCLOSED:
                # Seen through a gap of a nearer candidate that is a person: the background
                # between its legs, or a part of someone it hides; fitted alone, a crouching
                # body would be made up for it. Unless it is a tracked person, most of
                # whom is still in view: someone walking behind another; or no found
                # person's pixels enclose it (a person beside a nearer one, in the box of
                # their blob: it goes on to the tests of a new person).
                if i == len(x):  # no network pass for it
                    x.append(None)
                    lab.append(None)
                    coords.append(None)
                    made_by.append(None)
                continue
            if i == len(x):
                # The network runs on as many candidates as persons are still missing (one,
                # in the common case); further ones only when these are rejected. With
                # tracks, one at a time: the tracked persons come first, and a further
                # candidate may be skipped (behind a person, or too much of one).
                tn = time.perf_counter()
                n = 1 if cfg.tracking and self.tracker.tracks else cfg.max_persons - len(persons)
                batch = crops[i:i + n]
                bnet = self._track_net(tr, net, third) if n == 1 else net  # (n>1: no tracks)
                if cfg.flip_tta:
                    xb = np.stack([network_input(crop_depth(d, c), c.median_depth)
                                   for c in batch])
                    lb, cb = bnet.predict(xb, flip_tta=True)
                else:
                    xb, lb, cb = zip(*self._network(d, batch, bnet, self._ahead))
                x.extend(xb)
                lab.extend(lb)
                coords.extend(cb)
                made_by.extend([bnet] * len(batch))
                timings['network'] += (time.perf_counter() - tn) * 1e3
            if i in plain:  # ranked on the plain pass: add the mirrored one (flip_tta)
                tn = time.perf_counter()
                (lb,), (cb,) = net.combine(
                    plain.pop(i), made_by[i].raw(x[i][None], mirrored=True))
                lab[i], coords[i] = lb, cb
                timings['network'] += (time.perf_counter() - tn) * 1e3
            fg = body_pixels(x[i], lab[i])
            # A candidate is a person when the network sees a body in most of it.
            if fg.sum() < MIN_BODY_PIXELS or fg.sum() < MIN_BODY_SHARE \
                    * max(int(x[i][1].sum()), 1) * self._blob_fraction(crop, x[i][1]):
                if track_of.get(id(crop)) is None:
                    self._not_a_person(crop, made_by[i], K, t)
                continue
            excess = 0.0 if noise is None else float(noise.excess(crop.median_depth))
            fitter = self.fitter.for_noise(excess)
            reject = scaled_reject_residual(cfg.reject_residual_m, excess)
            tc = time.perf_counter()
            hit = self._ahead.get(id(crop))
            vids = (hit[4] if hit is not None and hit[0] is crop and hit[2] is lab[i]
                    else made_by[i].lookup(lab[i], coords[i], fg))
            rr, cc, _ = crop.sample_indices(d.shape)
            r, c = rr[fg], cc[fg]
            if persons and np.mean(claimed[r, c]) > MAX_CLAIMED:
                # Mostly pixels of a person already reconstructed (another blob of the
                # same body: a limb split off, the far side of a gap): not a new person.
                continue
            pts = pixel_points(r, c, d[r, c], K).astype(np.float32)
            tf = time.perf_counter()
            timings['correspondence'] += (tf - tc) * 1e3
            centre = candidate_centre(crop, K)
            track = track_of.get(id(crop))
            if track is None:  # a new person, a split half, or its track was released
                taken = seen | {id(tr) for c, tr in track_of.items()
                                if tr is not None and c != id(crop)}
                track = self.tracker.match(centre[None], [crop.mask], t, exclude=taken)[0]
            use = self._track_net(track, net, third)
            if use is not made_by[i]:  # a track found by its place: its own network
                tn = time.perf_counter()
                (lb,), (cb,) = use.predict(x[i][None], flip_tta=cfg.flip_tta)
                lab[i], coords[i], made_by[i] = lb, cb, use
                fg = body_pixels(x[i], lb)
                if fg.sum() < MIN_BODY_PIXELS:
                    continue
                vids = use.lookup(lb, cb, fg)
                r, c = rr[fg], cc[fg]
                pts = pixel_points(r, c, d[r, c], K).astype(np.float32)
                dt = time.perf_counter() - tn
                timings['network'] += dt * 1e3
                tf += dt
            score = body_score(crop, x[i][1] > 0, lab[i], d.shape)
            if track is None and score < MIN_COLD_SCORE:
                # A new person in whom the network sees few body parts: a box or a piece of
                # wall it labels as one or two (a tracked person found again half hidden
                # may show few, and keeps its chance).
                rejected.append(('score', -score, MIN_COLD_SCORE))
                self._not_a_person(crop, made_by[i], K, t)
                continue
            free = None
            if cfg.fit.free_space_weight > 0:  # looked for around the crop (+1/4 a side)
                side = crop.scale * crop.size
                box = (crop.u0 - side / 4, crop.v0 - side / 4, crop.u0 + 1.25 * side,
                       crop.v0 + 1.25 * side)
                zmed = float(np.median(d[r, c].astype(np.float64)))
                free = FreeSpace(d, K, zmed, fitter.cfg.free_space_margin, box=box,
                                 planes=supporting_planes(crop.planes, pts), own=crop.mask)
            fit, vids, tracked = self._fit(pts, vids, stamp_ns, track, free, fitter,
                                           give_up_m=GIVE_UP * reject
                                           if track is None and persons else None)
            moved = False
            if track is not None and not tracked:
                # A tracked person whose warm fit failed (half hidden: the network's
                # correspondences on part of a body are poor, and a cold fit is often
                # far off): their last tracked body, moved into place, when it explains
                # the pixels clearly better (HELD_BODY_GAIN) and passes the test.
                held = self._move_held_body(pts, track, t, fitter)
                if held is not None and held[0].median_residual <= min(
                        reject, HELD_BODY_GAIN * fit.median_residual):
                    (fit, vids), tracked, moved = held, True, True
            if fit.median_residual > reject:
                # The body model cannot explain this blob: not a person (or a failed fit),
                # or two people side by side in one blob: then try its two halves last.
                timings['fit'] += (time.perf_counter() - tf) * 1e3
                rejected.append(('residual', float(fit.median_residual), reject))
                if track is not None:  # released for the other candidates
                    track.fit = None
                    track_of[id(crop)] = None
                elif persons:
                    # A new blob beside a person found: a piece of the scene. Neither
                    # retried on the plain pass nor split: on the validation bags
                    # (multi_s31, multi_s35, seq_s5, val_s2, and the sample bag) no
                    # such blob of 59 ever gave a person that way, and each try is a
                    # network pass and a cold fit.
                    self._not_a_person(crop, made_by[i], K, t)
                    continue
                if cfg.flip_tta and id(crop) not in plain_retried:
                    # The averaged plain and mirrored passes can mislead a fit the plain
                    # pass alone gets right (a side view whose left and right the two
                    # passes disagree on; val_s2 frame 63: 0.108 m median residual, plain
                    # 0.045): retry the candidate on the plain pass, right away.
                    plain_retried.add(id(crop))
                    tn = time.perf_counter()
                    (lb,), (cb,) = made_by[i].predict(x[i][None], flip_tta=False)
                    timings['network'] += (time.perf_counter() - tn) * 1e3
                    for seq, item in ((crops, crop), (x, x[i]), (lab, lb), (coords, cb),
                                      (made_by, made_by[i])):
                        seq.insert(i + 1, item)
                    plain = {k + (k > i): v for k, v in plain.items()}
                    continue
                if id(crop) not in split_done:
                    halves = split_side_by_side(crop, K)
                    split_done.update(id(h) for h in halves)
                    crops.extend(halves)
                continue
            fit, vids = self._refine(fit, pts, vids, d, K, r, c, crop, fitter, free,
                                     0 if moved else cfg.fit.tracking_icp_rounds if tracked
                                     else cfg.fit.icp_rounds)
            other = self._other(made_by[i]) if cfg.both_networks else None
            if other is not None and not cfg.tracking:
                # Single frames: the other shipped network's correspondences are fitted
                # too, and the fit whose mesh lies nearer the blob's points and less where
                # the sensor looked through it is kept (`_other_fit`): each network gets
                # some poses and sensors right that the other gets wrong. Not with
                # tracking: there a person's first fit starts their track, which keeps its
                # network (`_track_net`; the third look gives the other one a person the
                # first fails on), and on the three-person validation sequences the score
                # picked worse fits of people half hidden, whose tracks kept them
                # (EXPERIMENTS.md, 2026-12-07).
                tn = time.perf_counter()
                (lb,), (cb,) = other.predict(x[i][None], flip_tta=cfg.flip_tta)
                dt = time.perf_counter() - tn
                timings['network'] += dt * 1e3
                tf += dt  # (the fit's time leaves the network pass out)
                alt = self._other_fit(d, K, crop, rr, cc, x[i], lb, cb, other, fitter, free,
                                      reject, fit)
                if alt is not None:
                    fit, vids, pts, r, c = alt
                    lab[i], coords[i], made_by[i] = lb, cb, other
            seen_through = (see_through_share(fit.vertices, self.faces, d, K,
                                              fitter.cfg.free_space_margin)
                            if persons else 0.0)
            if seen_through > MAX_SEE_THROUGH:
                # Beside a person found already, a body made up for a box or a piece of
                # wall: the sensor sees through it where it would stand. (Not asked of the
                # frame's first person: a folded pose fitted roughly can fail it, and
                # losing it loses the frame.)
                timings['fit'] += (time.perf_counter() - tf) * 1e3
                rejected.append(('see_through', seen_through, MAX_SEE_THROUGH))
                if track is not None:
                    track.fit = None
                    track_of[id(crop)] = None
                continue
            if track is None:
                track = self.tracker.new(centre, t)
            if cfg.tracking:
                track.keep_fit(fit, t, stamp_ns, tracked, moved)
                track.net = made_by[i]
            else:
                track.fit = None
            timings['fit'] += (time.perf_counter() - tf) * 1e3
            tl = time.perf_counter()
            # The person's pixels for this frame's claims and their track: their body
            # pixels in the network's labels (the model labels come last, `finish`).
            win = label_window(crop, lab[i], d)
            mask = paste_network_labels(network_full, win)
            if cfg.segmentation == 'model':
                todo.labels.append((len(persons), win, fit.vertices, crop.planes))
            timings['labels'] += (time.perf_counter() - tl) * 1e3
            seen.add(id(track))
            Tracker.seen(track, fit.joints[0], t, mask)
            claimed |= mask
            conf = joint_confidence(self.fitter.rig.segment_of_vertex, vids,
                                    np.linalg.norm(fit.vertices[vids] - pts, axis=1),
                                    self._joint_adjacency,
                                    scaled_spread(CONF_RESIDUAL_M, excess))
            persons.append(PersonResult(
                params=fit.params, vertices=fit.vertices, joints=fit.joints,
                bbox=(int(crop.u0), int(crop.v0), int(crop.u0 + crop.scale * crop.size),
                      int(crop.v0 + crop.scale * crop.size)),
                mask=mask, residual_m=fit.median_residual, num_points=int(len(pts)),
                tracked=tracked, pixels=np.stack([r, c], 1), vertex_ids=vids, crop=crop,
                crop_labels=np.where(x[i][1] > 0, lab[i], 0).astype(np.uint8),
                track_id=track.id, joint_confidence=conf, score=score))
        return persons

    def _track_net(self, track, net: CorrespondenceNet, third: bool = False
                   ) -> CorrespondenceNet:
        """The network a tracked person's correspondences come from: the one whose
        correspondences gave its last cold fit (`Track.net`), else `net`, the frame's;
        in the third look (`third`), the other one than that. A person the original
        network takes for a template pose it is not in, found by the third look, is
        fitted from the broad one's labels frame after frame, not only in the frame it was
        found (validation, a Kinect v1 broad-pose sequence: EXPERIMENTS.md)."""
        if not self.config.tracking or track is None or track.net is None:
            return net
        return (self._other(track.net) or net) if third else track.net

    def _rank_candidates(self, d, K, crops, timings, net):
        """Order person candidates (with tracking, or when there are more than persons
        wanted).

        While a person is tracked, the candidate that covers most of its previous pixels
        comes first (no network needed). Otherwise the network runs on every candidate
        (but the nearest ones kept beyond the most central, `Crop.nearest`, which follow
        them unranked) and they are ordered by how much of a body it sees: the share of
        the blob's own pixels it labels as body times the number of parts covering >= 2 %
        of them (background objects get few parts), times the share of a whole person's
        area it shows when it shows less (`seen_area` under RANK_AREA_M2: a leg a depth
        jump cut off the body fills its crop and the network sees a body in it); the most
        central candidate is not always the person.

        Returns (crops, network inputs, labels, coords, plain): the outputs are filled for
        the candidates the network already ran on; ranking uses the plain pass only, so
        with flip_tta `plain` maps each candidate to that pass (the mirrored one is added
        for the candidates actually used).
        """
        prev = [tr.mask for tr in self.tracker.tracks
                if tr.fit is not None and tr.mask is not None]
        if self.config.tracking and prev:
            if all(m.shape == d.shape for m in prev):
                return by_overlap(crops, prev), [], [], [], {}
            return crops, [], [], [], {}
        # The nearest candidates kept beyond the most central ones come after those,
        # unranked (a piece of a near person split off by a depth jump would otherwise
        # outrank their main blob).
        extra = [c for c in crops if c.nearest]
        crops = [c for c in crops if not c.nearest]
        if len(crops) <= self.config.max_persons:  # each will be tried: no ranking needed
            return crops + extra, [], [], [], {}
        tn = time.perf_counter()
        tta = self.config.flip_tta
        if tta:  # keep the plain pass's probabilities for the mirrored one added later
            x = np.stack([network_input(crop_depth(d, c), c.median_depth) for c in crops])
            probs, rc = net.raw(x)
            lab, coords = net.combine((probs, rc))
        else:
            x, lab, coords = zip(*self._network(
                d, crops, net, self._ahead))
        timings['network'] += (time.perf_counter() - tn) * 1e3
        score = [-body_score(c, xi[1] > 0, li, d.shape)
                 * min(1.0, seen_area(c, d, K) / RANK_AREA_M2)
                 for c, xi, li in zip(crops, x, lab)]
        # A blob seen through a gap of a nearer candidate goes after every other one.
        order = np.lexsort((score, [c.behind for c in crops]))
        plain = ({k: (probs[i:i + 1], rc[i:i + 1]) for k, i in enumerate(order)}
                 if tta else {})
        return ([crops[i] for i in order] + extra, [x[i] for i in order],
                [lab[i] for i in order], [coords[i] for i in order], plain)

    def _refine(self, fit, pts, vids, d, K, r, c, crop, fitter, free, rounds: int):
        """ICP inside the predicted parts on the fitted mesh, then a refit, to which the
        pixels the network left out join where they lie on the mesh; `rounds` times.
        Returns (FitResult, the points' vertices)."""
        cfg = self.config
        for _ in range(rounds):
            front = facing_camera(fit.vertices, self.faces, cfg.fit.icp_front_cos)
            vids = refine_correspondences(pts, vids, fit.vertices, self.surface, front)
            xp, xv = near_surface_pixels(d, K, fit.vertices, r, c, crop, self.surface,
                                         front, fitter.cfg.icp_margin_m)
            fit = fitter.fit(np.concatenate([pts, xp]), np.concatenate([vids, xv]),
                             init=fit.params, fix_shape=False,
                             iterations=cfg.fit.tracking_iterations, free_space=free,
                             tangent_weight=cfg.fit.icp_tangent_weight)
        return fit, vids

    def _other_fit(self, d, K, crop, rr, cc, x, lab, coords, net, fitter, free, reject, fit):
        """`both_networks`: the cold fit, refined, of a candidate's network input `x` (its
        pixels `rr`, `cc` in the image: `Crop.sample_indices`) with
        another network's labels and coordinates (`lab`, `coords` of `net`), when its
        mesh lies nearer the blob's points than `fit`'s (`refine.depth_gap`, on the
        pixels of the network input, plus SEE_THROUGH_GAP_M times its
        `see_through_share`: a limb standing where the sensor looked through it) and its
        median residual is within `reject`.
        Returns (FitResult, vertex ids, points, rows, cols) or None."""
        fg = body_pixels(x, lab)
        if fg.sum() < MIN_BODY_PIXELS:
            return None
        r, c = rr[fg], cc[fg]
        pts = pixel_points(r, c, d[r, c], K).astype(np.float32)
        vids = net.lookup(lab, coords, fg)
        alt = fitter.fit(pts, vids, free_space=free)
        if alt.median_residual > reject:
            return None
        alt, vids = self._refine(alt, pts, vids, d, K, r, c, crop, fitter, free,
                                 self.config.fit.icp_rounds)
        blob = (x[1] > 0) & (d[rr, cc] > 0)
        rb, cb = rr[blob], cc[blob]
        seen = pixel_points(rb, cb, d[rb, cb], K)
        margin = fitter.cfg.free_space_margin

        def worse(f):  # metres: how far the points lie from it, and how much it is seen through
            return depth_gap(seen, f.vertices, self.faces) + SEE_THROUGH_GAP_M * \
                see_through_share(f.vertices, self.faces, d, K, margin)
        return None if worse(alt) >= worse(fit) else (alt, vids, pts, r, c)

    def _fit(self, pts, vids, stamp_ns, track=None, free=None, fitter=None, give_up_m=None):
        """Fit one person: warm-started from the previous frame while the track holds
        (refining the correspondences on the previous, moved mesh was measured to lock
        onto wrong poses; `process` refines them on this frame's warm fit instead), else
        cold.

        `free`: the frame's FreeSpace (or None), passed to the fitter; `fitter`: the
        fitter to use (default self.fitter; `Fitter.for_noise` widens its thresholds);
        `give_up_m`: passed to the cold fit (`Fitter.fit`).

        Returns (FitResult, correspondences used, tracked).
        """
        cfg = self.config
        fitter = fitter or self.fitter
        init = (track.warm_start(stamp_ns, cfg.tracking_max_gap_s)
                if cfg.tracking and track is not None else None)
        if init is not None:
            fit = fitter.fit(pts, vids, init=init, free_space=free,
                             temporal_weight=cfg.fit.lambda_temporal)
            if fit.median_residual <= fitter.cfg.lost_residual_m:
                self._sample_shape(pts, vids, fit, track, fitter)
                return fit, vids, True
        fit = fitter.fit(pts, vids, free_space=free, give_up_m=give_up_m)
        return fit, vids, False

    def _move_held_body(self, pts, track, t: float, fitter):
        """The track's last tracked body (`Track.held_body`, at most tracking_max_gap_s
        old), pose and shape held, moved rigidly onto the points `pts` from where its
        velocity puts it now (`refine.rigid_icp`, its camera-facing vertices). Returns
        (FitResult, each point's vertex) or None."""
        held = track.held_body(t, self.config.tracking_max_gap_s)
        if held is None:
            return None
        params, t_held = held
        verts = fitter.vertices(params)
        front = facing_camera(verts, self.faces, self.config.fit.icp_front_cos)
        R, shift, vids = rigid_icp(pts, verts, front,
                                   start=track.velocity * max(0.0, t - t_held))
        return fitter.fit(pts, vids, init=fitter.moved(params, R, shift), solver='none'), vids

    def _sample_shape(self, pts, vids, fit, track, fitter=None) -> None:
        """Every `shape_sample_every`-th tracked frame, a short warm fit with the shape
        free adds a sample to the track's mean shape. One frame's shape is only as good as
        its correspondences; averaged over the track it is measured better (val seq_s5
        tracking 28.7 -> 25.9 mm; a shape oracle gains about as much). The cold fit's shape
        is not a sample: counted in, it measured 27.3 mm."""
        if not track.shape_sample_due(self.config.shape_sample_every):
            return
        s = (fitter or self.fitter).fit(pts, vids, init=fit.params, fix_shape=False,
                                        iterations=2)
        track.add_shape_sample(s.params.shape)

    @staticmethod
    def _blob_fraction(crop, valid) -> float:
        """Share of the crop's valid pixels that belong to the candidate's blob."""
        if crop.mask is None:
            return 1.0
        return min(1.0, float(crop.mask.sum()) / max(float(valid.sum()) * crop.scale ** 2, 1.0))
