"""Luxonis OAK cameras through depthai 3.x: the adapter between depthai and our arrays.

No rclpy here: the `oak_camera` node (`ros.oak_camera_node`) wires this module to topics.

* `OakConfig`: the camera settings (frozen; each field declares one of the node's
  parameters);
* `build_pipeline`: CAM_B/CAM_C mono pair -> StereoDepth (preset, subpixel, filters, depth
  range; optionally aligned to CAM_A) -> a host output queue of depth `ImgFrame`s;
* `frame_to_depth`: a depth `ImgFrame` (RAW16, millimetres) -> `DepthFrame` (uint16 array,
  stamp mapped to ROS time by a `ClockMapper`);
* `intrinsics`: `CalibrationHandler` -> K (3, 3) at the published resolution, D;
* `ClockMapper`: depthai timestamps -> ROS time. depthai's `ImgFrame.getTimestamp()` is
  the capture time on the host steady clock (`dai.Clock.now()`, synchronised with the
  device clock by depthai); the mapper adds the measured offset between the ROS clock and
  that steady clock;
* `make_host_frame`: a host-made depth `ImgFrame` like StereoDepth's (tests, replay).

Finding, opening and running devices (connections, the reconnecting driver) is
`ros.oak_device`'s.

Geometry: without alignment the depth image is the rectified right (CAM_C) view, published
with CAM_C's calibrated K (depthai's rectification keeps the right camera's K); aligned, it
is CAM_A's view with CAM_A's K. Either way the depth image is undistorted, so D is zero.
Device frames also carry their own intrinsics (`frame_intrinsics`); the node warns once
when those disagree with the calibration's.
"""
from __future__ import annotations

import datetime
import math
import threading
import time
from dataclasses import asdict, dataclass, fields
from typing import Any, Callable

import depthai as dai
import numpy as np

from smpl_depth_ros.config import param
from smpl_depth_ros.params import build_schema, check_declared

# -- configuration ---------------------------------------------------------------------
# Preset name -> dai.node.StereoDepth.PresetMode member.
PRESETS = {
    'default': 'DEFAULT', 'high_accuracy': 'ACCURACY', 'high_density': 'DENSITY',
    'fast_accuracy': 'FAST_ACCURACY', 'fast_density': 'FAST_DENSITY',
    'robotics': 'ROBOTICS', 'high_detail': 'HIGH_DETAIL', 'face': 'FACE',
}
MEDIAN = {'off': 'MEDIAN_OFF', '3x3': 'KERNEL_3x3', '5x5': 'KERNEL_5x5', '7x7': 'KERNEL_7x7'}
SWITCH = ('preset', 'on', 'off')
PERSISTENCY = {name.lower(): name for name in (
    'PERSISTENCY_OFF', 'VALID_8_OUT_OF_8', 'VALID_2_IN_LAST_3', 'VALID_2_IN_LAST_4',
    'VALID_2_OUT_OF_8', 'VALID_1_IN_LAST_2', 'VALID_1_IN_LAST_5', 'VALID_1_IN_LAST_8',
    'PERSISTENCY_INDEFINITELY')}
LEFT_SOCKET = dai.CameraBoardSocket.CAM_B
RIGHT_SOCKET = dai.CameraBoardSocket.CAM_C
COLOR_SOCKET = dai.CameraBoardSocket.CAM_A
MAX_RANGE_M = 65.535  # uint16 millimetres


_R = dict(restart=True)  # every camera setting needs a restart (reopens the device)


@dataclass(frozen=True)
class OakConfig:
    """Camera, stereo and connection settings: the `oak_camera` node's parameters, each
    declared here (`config.param`).

    Filter settings named 'preset' keep what the stereo preset chose; 'on' / 'off' (and the
    numeric settings of an 'on' filter) override it. Decimation is always applied, so
    `width` x `height` is the published size unless `decimation` > 1.
    """

    device_id: str = param('', "device to open: MxID / device ID, IP (PoE) or USB name; '' "
                           '= the first one found', **_R)
    connect_timeout_s: float = param(5.0, 'how long to look for the device at start-up (s)',
                                     range=(0.0, 3600.0), **_R)
    wait_for_device: bool = param(False, 'at start-up, keep looking (with backoff) instead '
                                  'of exiting', **_R)
    width: int = param(640, 'depth width (pixels; the mono outputs are requested at this '
                       'size)', range=(16, 4096), **_R)
    height: int = param(400, 'depth height (pixels)', range=(16, 4096), **_R)
    fps: float = param(30.0, 'camera frame rate', range=(1.0, 120.0), **_R)
    preset: str = param('default', 'stereo preset', choices=tuple(PRESETS), **_R)
    subpixel: bool = param(True, 'subpixel disparity (finer depth steps far away)', **_R)
    extended_disparity: bool = param(False, 'extended disparity (closer minimum range, at '
                                     'some cost)', **_R)
    confidence_threshold: int = param(-1, "stereo confidence threshold 0..255 (-1 = the "
                                      "preset's)", range=(-1, 255), **_R)
    decimation: int = param(1, 'decimation factor (1 = publish width x height)',
                            range=(1, 4), **_R)
    median_filter: str = param('preset', 'median filter', choices=('preset', *MEDIAN), **_R)
    spatial_filter: str = param('preset', "spatial filter: 'preset', 'on' (with the "
                                "spatial_* values) or 'off'", choices=SWITCH, **_R)
    spatial_alpha: float = param(0.5, 'spatial filter smoothing alpha', range=(0.0, 1.0),
                                 **_R)
    spatial_delta: int = param(0, 'spatial filter edge threshold (0 = auto: 3 disparity '
                               'levels)', range=(0, 255), **_R)
    spatial_hole_filling_radius: int = param(2, 'spatial filter hole-filling radius '
                                             '(pixels)', range=(0, 255), **_R)
    spatial_iterations: int = param(1, 'spatial filter iterations', range=(1, 10), **_R)
    temporal_filter: str = param('preset', "temporal filter: 'preset', 'on' (with the "
                                 "temporal_* values) or 'off'", choices=SWITCH, **_R)
    temporal_alpha: float = param(0.4, 'temporal filter alpha', range=(0.0, 1.0), **_R)
    temporal_delta: int = param(0, 'temporal filter edge threshold (0 = auto)',
                                range=(0, 255), **_R)
    temporal_persistency: str = param('valid_2_in_last_4', 'temporal filter persistency',
                                      choices=tuple(PERSISTENCY), **_R)
    min_range: float = param(0.2, 'nearest depth published (m); nearer pixels are 0 '
                             '(invalid)', range=(0.0, MAX_RANGE_M), **_R)
    max_range: float = param(10.0, 'farthest depth published (m); farther pixels are 0',
                             range=(0.0, MAX_RANGE_M), **_R)
    align_to_color: bool = param(False, 'align depth to the colour camera (CAM_A) instead '
                                 'of the rectified right camera (CAM_C)', **_R)
    frame_timeout_s: float = param(2.0, 'no frame for this long while running = device lost '
                                   '(s)', range=(0.1, 3600.0), **_R)
    reconnect_backoff_s: float = param(0.5, 'first reconnection delay (s); doubles up to the '
                                       'maximum', range=(0.01, 3600.0), **_R)
    reconnect_backoff_max_s: float = param(10.0, 'longest reconnection delay (s)',
                                           range=(0.01, 3600.0), **_R)


SCHEMA = build_schema({'camera': OakConfig})


def validate(cfg: OakConfig) -> str | None:
    """Why `cfg` is invalid, or None."""
    reason = check_declared(SCHEMA, asdict(cfg))
    if reason:
        return reason
    if not cfg.min_range < cfg.max_range:
        return f'min_range ({cfg.min_range}) must be smaller than max_range ({cfg.max_range})'
    if cfg.reconnect_backoff_s > cfg.reconnect_backoff_max_s:
        return (f'reconnect_backoff_s ({cfg.reconnect_backoff_s}) must not exceed '
                f'reconnect_backoff_max_s ({cfg.reconnect_backoff_max_s})')
    return None


def config_from_dict(values: dict[str, Any]) -> OakConfig:
    """OakConfig from a dict that may hold other keys too (e.g. all node parameters)."""
    return OakConfig(**{f.name: values[f.name] for f in fields(OakConfig) if f.name in values})


# -- pipeline --------------------------------------------------------------------------
def preset_mode(name: str) -> dai.node.StereoDepth.PresetMode:
    """The depthai preset for one of PRESETS' names."""
    return getattr(dai.node.StereoDepth.PresetMode, PRESETS[name])


def configure_stereo(config: dai.StereoDepthConfig, cfg: OakConfig) -> dai.StereoDepthConfig:
    """Apply `cfg` on top of a preset's StereoDepthConfig (in place; returned too).

    Depth unit millimetres; threshold filter = [min_range, max_range]; subpixel, extended
    disparity and decimation always; confidence, median, spatial and temporal filters only
    where `cfg` overrides the preset.
    """
    pp = config.postProcessing
    config.setDepthUnit(dai.StereoDepthConfig.AlgorithmControl.DepthUnit.MILLIMETER)
    config.setSubpixel(bool(cfg.subpixel))
    config.setExtendedDisparity(bool(cfg.extended_disparity))
    if cfg.confidence_threshold >= 0:
        config.setConfidenceThreshold(int(cfg.confidence_threshold))
    pp.decimationFilter.decimationFactor = int(cfg.decimation)
    if cfg.median_filter != 'preset':
        config.setMedianFilter(getattr(dai.StereoDepthConfig.MedianFilter,
                                       MEDIAN[cfg.median_filter]))
    if cfg.spatial_filter != 'preset':
        sf = pp.spatialFilter
        sf.enable = cfg.spatial_filter == 'on'
        if sf.enable:
            sf.alpha = float(cfg.spatial_alpha)
            sf.delta = int(cfg.spatial_delta)
            sf.holeFillingRadius = int(cfg.spatial_hole_filling_radius)
            sf.numIterations = int(cfg.spatial_iterations)
    if cfg.temporal_filter != 'preset':
        tf = pp.temporalFilter
        tf.enable = cfg.temporal_filter == 'on'
        if tf.enable:
            tf.alpha = float(cfg.temporal_alpha)
            tf.delta = int(cfg.temporal_delta)
            tf.persistencyMode = getattr(type(tf.persistencyMode),
                                         PERSISTENCY[cfg.temporal_persistency])
    pp.thresholdFilter.minRange = int(round(cfg.min_range * 1000))
    pp.thresholdFilter.maxRange = int(round(min(cfg.max_range, MAX_RANGE_M) * 1000))
    return config


def depth_socket(cfg: OakConfig) -> dai.CameraBoardSocket:
    """The camera whose view (and intrinsics) the depth image has."""
    return COLOR_SOCKET if cfg.align_to_color else RIGHT_SOCKET


def build_pipeline(pipeline: dai.Pipeline, cfg: OakConfig) -> dai.MessageQueue:
    """CAM_B/CAM_C -> StereoDepth in `pipeline` (not started); the depth output queue.

    The queue is non-blocking and short: a slow host drops old frames on the device side
    of the queue instead of building up latency.
    """
    size = (int(cfg.width), int(cfg.height))
    fps = float(cfg.fps)
    left = pipeline.create(dai.node.Camera).build(LEFT_SOCKET, sensorFps=fps)
    right = pipeline.create(dai.node.Camera).build(RIGHT_SOCKET, sensorFps=fps)
    stereo = pipeline.create(dai.node.StereoDepth)
    stereo.setDefaultProfilePreset(preset_mode(cfg.preset))
    crop = dai.ImgResizeMode.CROP  # what `intrinsics` assumes
    left.requestOutput(size, resizeMode=crop, fps=fps).link(stereo.left)
    right.requestOutput(size, resizeMode=crop, fps=fps).link(stereo.right)
    stereo.setRectification(True)
    if cfg.align_to_color:
        stereo.setDepthAlign(COLOR_SOCKET)
        stereo.setOutputSize(*size)
    else:
        stereo.setDepthAlign(dai.StereoDepthConfig.AlgorithmControl.DepthAlign.RECTIFIED_RIGHT)
    configure_stereo(stereo.initialConfig, cfg)
    return stereo.depth.createOutputQueue(maxSize=2, blocking=False)


# -- calibration -----------------------------------------------------------------------
def sensor_preset(cfg: OakConfig, description: str = '') -> str:
    """The depth-noise preset (synth.sensors) of this camera and its settings, which
    `reconstruct_oak` gives the reconstructor's `sensor` parameter: an OAK-D Pro (IR dot
    projector) or an OAK-D; without subpixel disparity, integer disparity steps."""
    if not cfg.subpixel:
        return 'oak_d_no_subpixel'
    return 'oak_d_pro' if 'PRO' in description.upper() else 'oak_d'


class CalibrationError(RuntimeError):
    """The device calibration lacks what the published depth needs."""


def intrinsics(calibration: dai.CalibrationHandler, socket: dai.CameraBoardSocket,
               size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """K (3, 3) float64 of `socket` at `size` = (width, height), and D (5,) zeros.

    The camera outputs are requested with ImgResizeMode.CROP: the calibrated image is
    centre-cropped to the aspect ratio of `size`, then scaled. So K is depthai's
    `getCameraIntrinsics` at the calibrated aspect ratio scaled to cover `size`, with the
    principal point shifted by the crop (for a size of the calibrated aspect ratio, e.g.
    640x400 from 1280x800, that is `getCameraIntrinsics(socket, w, h)` itself; depthai's
    own keepAspectRatio would letterbox other ratios instead). Decimation by k is a scale
    by 1/k of the same. The depth image is rectified / reprojected, so D is zero.

    Raises:
        CalibrationError: no intrinsics for `socket` in the calibration.
    """
    w, h = int(size[0]), int(size[1])
    try:
        _, w0, h0 = calibration.getDefaultIntrinsics(socket)
        scale = max(w / w0, h / h0)
        ws, hs = max(w, int(round(w0 * scale))), max(h, int(round(h0 * scale)))
        K = np.array(calibration.getCameraIntrinsics(socket, ws, hs), np.float64)
    except RuntimeError as e:
        raise CalibrationError(f'the device calibration has no intrinsics for {socket.name} '
                               f'({e})') from None
    if K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise CalibrationError(f'the device calibration gives invalid intrinsics for '
                               f'{socket.name}: {K.tolist()}')
    K[0, 2] -= (ws - w) / 2.0
    K[1, 2] -= (hs - h) / 2.0
    return K, np.zeros(5)


def frame_intrinsics(frame: dai.ImgFrame) -> np.ndarray | None:
    """K (3, 3) the device attached to `frame` (its ImgTransformation), or None when the
    frame carries none (host-made frames) or it is for another size."""
    tr = frame.getTransformation()
    if not tr.isValid() or tuple(tr.getSize()) != (frame.getWidth(), frame.getHeight()):
        return None
    K = np.asarray(tr.getIntrinsicMatrix(), np.float64)
    if K.shape != (3, 3) or np.allclose(K, np.eye(3)):
        return None
    return K


# -- time ------------------------------------------------------------------------------
def timedelta_to_ns(td: datetime.timedelta) -> int:
    """A depthai timestamp (datetime.timedelta, microsecond resolution) in nanoseconds."""
    return (td.days * 86_400 + td.seconds) * 1_000_000_000 + td.microseconds * 1_000


def dai_now_ns() -> int:
    """dai.Clock.now() (host steady clock, the base of ImgFrame.getTimestamp()) in ns."""
    return timedelta_to_ns(dai.Clock.now())


class ClockMapper:
    """Maps depthai timestamps onto a target clock (ROS time) by a measured offset.

    The offset target - source is measured by bracketing one source reading between two
    target readings (the tightest of `samples` tries wins) and re-measured every
    `resync_period_s`, so steps of the target clock (NTP, a ROS time jump) are followed
    within one period.

    Args:
        target_now_ns: the target clock, e.g. ``lambda: node.get_clock().now().nanoseconds``.
        source_now_ns: the source clock (default `dai_now_ns`).
        resync_period_s: how often the offset is re-measured (monotonic seconds).
    """

    def __init__(self, target_now_ns: Callable[[], int],
                 source_now_ns: Callable[[], int] = dai_now_ns,
                 resync_period_s: float = 1.0, samples: int = 3,
                 monotonic: Callable[[], float] = time.monotonic):
        self._target = target_now_ns
        self._source = source_now_ns
        self._period = float(resync_period_s)
        self._samples = max(1, int(samples))
        self._monotonic = monotonic
        self._lock = threading.Lock()
        self._offset: int | None = None
        self._uncertainty = 0
        self._last = -math.inf

    def measure(self) -> tuple[int, int]:
        """(offset ns, half-width of its bracket ns), measured now."""
        best = None
        for _ in range(self._samples):
            t0 = int(self._target())
            s = int(self._source())
            t1 = int(self._target())
            width = abs(t1 - t0)
            if best is None or width < best[1]:
                best = ((t0 + t1) // 2 - s, width)
        return best[0], best[1] // 2

    def resync(self, force: bool = False) -> int:
        """Re-measure the offset when due (or `force`); the current offset in ns."""
        now = self._monotonic()
        with self._lock:
            if force or self._offset is None or now - self._last >= self._period:
                self._offset, self._uncertainty = self.measure()
                self._last = now
            return self._offset

    @property
    def offset_ns(self) -> int:
        return self.resync()

    @property
    def uncertainty_ns(self) -> int:
        return self._uncertainty

    def to_target_ns(self, source_stamp) -> int:
        """A source stamp (timedelta or int ns) in the target clock, ns."""
        if isinstance(source_stamp, datetime.timedelta):
            source_stamp = timedelta_to_ns(source_stamp)
        return int(source_stamp) + self.resync()


# -- frames ----------------------------------------------------------------------------
class FrameError(ValueError):
    """An ImgFrame that is not a depth frame we can publish."""


@dataclass(frozen=True)
class DepthFrame:
    """One depth frame off the device.

    Attributes:
        depth_mm: (H, W) uint16 millimetres, 0 = invalid (out of range included).
        stamp_ns: capture time in the target clock (ROS time) when a mapper was given,
            else the source stamp.
        source_stamp_ns: capture time on depthai's host steady clock.
        sequence: the device's frame counter.
    """

    depth_mm: np.ndarray
    stamp_ns: int
    source_stamp_ns: int
    sequence: int

    @property
    def size(self) -> tuple[int, int]:
        """(width, height)."""
        return int(self.depth_mm.shape[1]), int(self.depth_mm.shape[0])

    def depth_m(self) -> np.ndarray:
        """(H, W) float32 metres, 0 = invalid."""
        return self.depth_mm.astype(np.float32) * np.float32(0.001)


def frame_to_depth(frame: dai.ImgFrame, mapper: ClockMapper | None = None,
                   min_range: float = 0.0, max_range: float = MAX_RANGE_M) -> DepthFrame:
    """A depth ImgFrame (RAW16 millimetres) -> DepthFrame, values outside
    [min_range, max_range] metres set to 0.

    Raises:
        FrameError: another type, or data that does not match the frame's size.
    """
    typ = frame.getType()
    if typ != dai.ImgFrame.Type.RAW16:
        raise FrameError(f'expected a RAW16 depth frame (millimetres), got {typ.name}')
    w, h = int(frame.getWidth()), int(frame.getHeight())
    if w <= 0 or h <= 0:
        raise FrameError(f'empty depth frame ({w}x{h})')
    data = np.asarray(frame.getData()).reshape(-1).view(np.uint8)
    stride = int(frame.getStride()) or 2 * w
    if stride < 2 * w or data.size < stride * (h - 1) + 2 * w:
        raise FrameError(f'depth frame {w}x{h} stride {stride} has only {data.size} bytes')
    rows = np.ndarray((h, w), dtype='<u2', buffer=data, strides=(stride, 2))
    mm = np.array(rows, dtype=np.uint16)  # own copy: the frame's buffer is reused
    lo, hi = int(round(min_range * 1000)), int(round(min(max_range, MAX_RANGE_M) * 1000))
    if lo > 0 or hi < 65535:
        mm[(mm < lo) | (mm > hi)] = 0
    src = timedelta_to_ns(frame.getTimestamp())
    stamp = mapper.to_target_ns(src) if mapper is not None else src
    return DepthFrame(mm, stamp, src, int(frame.getSequenceNum()))


def make_host_frame(depth_mm: np.ndarray, timestamp: datetime.timedelta | None = None,
                    sequence: int = 0,
                    socket: dai.CameraBoardSocket = RIGHT_SOCKET) -> dai.ImgFrame:
    """A host-made depth ImgFrame like StereoDepth's output (RAW16 mm), for tests and
    replay. `timestamp` defaults to dai.Clock.now()."""
    mm = np.ascontiguousarray(depth_mm, dtype=np.uint16)
    if mm.ndim != 2:
        raise ValueError(f'depth_mm must be (H, W), got {mm.shape}')
    f = dai.ImgFrame()
    f.setType(dai.ImgFrame.Type.RAW16)
    f.setWidth(mm.shape[1])
    f.setHeight(mm.shape[0])
    f.setFrame(mm)
    f.setInstanceNum(int(socket))
    f.setSequenceNum(int(sequence))
    f.setTimestamp(dai.Clock.now() if timestamp is None else timestamp)
    return f
