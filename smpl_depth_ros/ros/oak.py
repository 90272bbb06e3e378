"""Luxonis OAK cameras through depthai 3.x: the adapter between depthai and our arrays.

No rclpy here: the `oak_camera` node (`ros.oak_camera_node`) wires this module to topics.

* `OakConfig`: the camera settings (frozen; the node's parameters mirror it);
* `build_pipeline`: CAM_B/CAM_C mono pair -> StereoDepth (preset, subpixel, filters, depth
  range; optionally aligned to CAM_A) -> a host output queue of depth `ImgFrame`s;
* `frame_to_depth`: a depth `ImgFrame` (RAW16, millimetres) -> `DepthFrame` (uint16 array,
  stamp mapped to ROS time by a `ClockMapper`);
* `intrinsics`: `CalibrationHandler` -> K (3, 3) at the published resolution, D;
* `ClockMapper`: depthai timestamps -> ROS time. depthai's `ImgFrame.getTimestamp()` is
  the capture time on the host steady clock (`dai.Clock.now()`, synchronised with the
  device clock by depthai); the mapper adds the measured offset between the ROS clock and
  that steady clock;
* `find_device`, `OakConnection`, `OakDriver`: open a device by MxID / IP / name (or the first
  available), run the pipeline, and keep it running across unplugging (reconnect with
  exponential backoff); `QueueConnection` + `make_host_frame` feed the same path from the
  host (tests, replay).

Geometry: without alignment the depth image is the rectified right (CAM_C) view, published
with CAM_C's calibrated K (depthai's rectification keeps the right camera's K); aligned, it
is CAM_A's view with CAM_A's K. Either way the depth image is undistorted, so D is zero.
Device frames also carry their own intrinsics (`frame_intrinsics`); the node warns once
when those disagree with the calibration's.
"""
from __future__ import annotations

import datetime
import ipaddress
import math
import threading
import time
from dataclasses import dataclass, fields
from typing import Any, Callable

import depthai as dai
import numpy as np

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


@dataclass(frozen=True)
class OakConfig:
    """Camera, stereo and connection settings (defaults of the `oak_camera` node).

    Filter settings named 'preset' keep what the stereo preset chose; 'on' / 'off' (and the
    numeric settings of an 'on' filter) override it. Decimation is always applied, so
    `width` x `height` is the published size unless `decimation` > 1.
    """

    device_id: str = ''                 # MxID / device ID, IP or USB name; '' = first found
    connect_timeout_s: float = 5.0      # how long to look for the device at start-up
    wait_for_device: bool = False       # at start-up: keep looking instead of failing
    width: int = 640                    # mono outputs and depth (pixels)
    height: int = 400
    fps: float = 30.0
    preset: str = 'default'             # see PRESETS
    subpixel: bool = True
    extended_disparity: bool = False    # closer minimum range, at some cost
    confidence_threshold: int = -1      # 0..255; -1 = the preset's
    decimation: int = 1                 # 1 = off (publish width x height); 2..4
    median_filter: str = 'preset'       # preset | off | 3x3 | 5x5 | 7x7
    spatial_filter: str = 'preset'      # preset | on | off
    spatial_alpha: float = 0.5
    spatial_delta: int = 0              # 0 = auto (3 disparity levels)
    spatial_hole_filling_radius: int = 2
    spatial_iterations: int = 1
    temporal_filter: str = 'preset'     # preset | on | off
    temporal_alpha: float = 0.4
    temporal_delta: int = 0             # 0 = auto
    temporal_persistency: str = 'valid_2_in_last_4'  # see PERSISTENCY
    min_range: float = 0.2              # metres; depth outside [min, max] is 0 (invalid)
    max_range: float = 10.0
    align_to_color: bool = False        # depth in CAM_A's view instead of rectified CAM_C
    frame_timeout_s: float = 2.0        # no frame for this long = device lost
    reconnect_backoff_s: float = 0.5    # first retry delay; doubles up to the max
    reconnect_backoff_max_s: float = 10.0


# Allowed ranges of the numeric settings, inclusive.
RANGES: dict[str, tuple[float, float]] = {
    'connect_timeout_s': (0.0, 3600.0), 'width': (16, 4096), 'height': (16, 4096),
    'fps': (1.0, 120.0), 'confidence_threshold': (-1, 255), 'decimation': (1, 4),
    'spatial_alpha': (0.0, 1.0), 'spatial_delta': (0, 255),
    'spatial_hole_filling_radius': (0, 255), 'spatial_iterations': (1, 10),
    'temporal_alpha': (0.0, 1.0), 'temporal_delta': (0, 255),
    'min_range': (0.0, MAX_RANGE_M), 'max_range': (0.0, MAX_RANGE_M),
    'frame_timeout_s': (0.1, 3600.0), 'reconnect_backoff_s': (0.01, 3600.0),
    'reconnect_backoff_max_s': (0.01, 3600.0),
}
CHOICES: dict[str, tuple[str, ...]] = {
    'preset': tuple(PRESETS), 'median_filter': ('preset',) + tuple(MEDIAN),
    'spatial_filter': SWITCH, 'temporal_filter': SWITCH,
    'temporal_persistency': tuple(PERSISTENCY),
}


def validate(cfg: OakConfig) -> str | None:
    """Why `cfg` is invalid, or None."""
    for name, choices in CHOICES.items():
        if getattr(cfg, name) not in choices:
            return f"{name} must be one of {', '.join(choices)}; got '{getattr(cfg, name)}'"
    for name, (lo, hi) in RANGES.items():
        v = getattr(cfg, name)
        if not lo <= v <= hi:
            return f'{name} must be in [{lo}, {hi}], got {v}'
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


# -- devices ---------------------------------------------------------------------------
class DeviceNotFoundError(RuntimeError):
    """No (matching, free) OAK device."""


class DeviceLostError(RuntimeError):
    """A running device stopped delivering frames."""


def _describe(info: dai.DeviceInfo) -> str:
    state = info.state.name.replace('X_LINK_', '').lower()
    proto = info.protocol.name.replace('X_LINK_', '').lower()
    return f'{info.deviceId or "?"} ({info.name or "?"}, {proto}, {state})'


def _matches(info: dai.DeviceInfo, wanted: str) -> bool:
    return not wanted or wanted in (info.deviceId, info.name)


def _is_ip(text: str) -> bool:
    try:
        ipaddress.ip_address(text)
        return True
    except ValueError:
        return False


def find_device(device_id: str = '', timeout_s: float = 5.0,
                sleep: Callable[[float], Any] = time.sleep) -> dai.DeviceInfo:
    """The first available device matching `device_id` (MxID / device ID, IP, or USB name;
    '' = any), looked for during `timeout_s`.

    Raises:
        DeviceNotFoundError: with one line naming what was looked for and what is visible.
    """
    wanted = device_id.strip()
    deadline = time.monotonic() + max(0.0, timeout_s)
    while True:
        for info in dai.Device.getAllAvailableDevices():
            if _matches(info, wanted):
                return info
        if wanted and _is_ip(wanted):  # PoE outside the broadcast domain: ask directly
            found, info = dai.Device.getDeviceByIdOrName(wanted)
            if found:
                return info
        if time.monotonic() >= deadline:
            break
        sleep(0.2)
    visible = dai.Device.getAllConnectedDevices()
    busy = [i for i in visible if _matches(i, wanted)]
    what = f"OAK device '{wanted}' (MxID, IP or USB name)" if wanted else \
        'any OAK device (USB or PoE)'
    if busy:
        what = f"OAK device '{wanted}'" if wanted else 'every OAK device connected'
        raise DeviceNotFoundError(
            f'{what} is in use (by another process?): '
            f'{", ".join(_describe(i) for i in busy)}')
    seen = ', '.join(_describe(i) for i in visible) or 'none'
    usb = 'check the cable and udev rules (in a container pass /dev/bus/usb)'
    if not wanted:
        hint = f"{usb}, or set device_id to a PoE camera's IP"
    elif _is_ip(wanted):
        hint = "check the camera's power and network (can you ping it?)"
    else:
        hint = f'{usb} and the ID'
    during = f' for {timeout_s:g} s' if timeout_s > 0 else ''
    raise DeviceNotFoundError(f'no OAK device found: looked for {what}{during}; '
                              f'devices visible: {seen}; {hint}')


class QueueConnection:
    """Depth frames from a depthai MessageQueue: the reading half of `OakConnection`, and on
    its own a host-fed connection (tests, replay: push `make_host_frame`s into the queue).

    Attributes:
        device_id: the device's MxID / device ID.
        description: product name and id for logs.
        calibration: the device's CalibrationHandler.
    """

    def __init__(self, queue: dai.MessageQueue, calibration: dai.CalibrationHandler,
                 device_id: str = 'host', description: str | None = None):
        self._queue = queue
        self.calibration = calibration
        self.device_id = device_id
        self.description = description or f'host queue {device_id}'

    def _running(self) -> bool:
        return not self._queue.isClosed()

    def get(self, timeout_s: float) -> dai.ImgFrame | None:
        """The next depth frame, or None after `timeout_s`.

        Raises:
            DeviceLostError: the pipeline stopped or the queue closed (device gone).
        """
        if not self._running():
            raise DeviceLostError('the pipeline stopped running')
        try:
            return self._queue.get(datetime.timedelta(seconds=timeout_s))
        except (RuntimeError, dai.MessageQueue.QueueException) as e:  # closed, XLink error
            raise DeviceLostError(str(e) or type(e).__name__) from None

    def close(self):
        try:
            self._queue.close()
        except Exception:  # noqa: BLE001 - closing twice, or a lost device
            pass


class OakConnection(QueueConnection):
    """An open device running the stereo pipeline (`build_pipeline`)."""

    def __init__(self, cfg: OakConfig, info: dai.DeviceInfo):
        self.device = dai.Device(info)
        self.pipeline = None
        try:
            if hasattr(self.device, 'setMaxReconnectionAttempts'):
                self.device.setMaxReconnectionAttempts(0)  # OakDriver reconnects itself
            device_id = str(self.device.getDeviceId())
            try:
                product = str(self.device.getProductName())
            except RuntimeError:
                product = ''
            calibration = self.device.readCalibration()
            self.pipeline = dai.Pipeline(self.device)
            queue = build_pipeline(self.pipeline, cfg)
            super().__init__(queue, calibration, device_id, f'{product or "OAK"} {device_id}')
            self.pipeline.start()
        except Exception:
            self.close()
            raise

    def _running(self) -> bool:
        return self.pipeline.isRunning() and super()._running()

    def close(self):
        if hasattr(self, '_queue'):
            super().close()
        try:
            if self.pipeline is not None and self.pipeline.isRunning():
                self.pipeline.stop()
        except Exception:  # noqa: BLE001 - a lost device may fail to stop cleanly
            pass
        try:
            self.device.close()
        except Exception:  # noqa: BLE001
            pass


def open_connection(cfg: OakConfig, device_id: str | None = None,
                 timeout_s: float | None = None) -> OakConnection:
    """Find (`find_device`) and open a device, start the pipeline.

    Args:
        device_id: overrides cfg.device_id (reconnecting to the same unit).
        timeout_s: overrides cfg.connect_timeout_s.
    """
    wanted = cfg.device_id if device_id is None else device_id
    info = find_device(wanted, cfg.connect_timeout_s if timeout_s is None else timeout_s)
    return OakConnection(cfg, info)


def backoff_delays(initial: float, maximum: float):
    """initial, 2 x initial, 4 x ... capped at maximum (an endless generator)."""
    d = float(initial)
    while True:
        yield min(d, maximum)
        d = min(d * 2.0, maximum)


class OakDriver:
    """Reads frames from a connection on a thread; reconnects with backoff when it fails.

    Callbacks run on the driver thread:
        on_frame(frame: dai.ImgFrame, connection) for every frame;
        on_event(kind, message, info) with kind 'lost' (the connection failed: message says
        why), 'retry' (an attempt to open failed; info has attempt and delay_s, the wait
        before the next one), 'reconnected' (after a loss; info has outage_s and attempts)
        or 'connected' (the first connection when started without one); a raising on_frame is
        reported as 'frame_error' and the loop goes on.

    Args:
        connection: the open first connection (the node opens it before starting, so that a
            missing device fails start-up), or None to look for the device on the thread
            (retrying with backoff: `wait_for_device`).
        reopen: opens a new connection for a device id (default: `open_connection` without
            waiting): cfg.device_id when set, else the MxID of the unit first opened, so
            a re-plugged camera comes back and another one does not take its place.
    """

    def __init__(self, cfg: OakConfig, connection, on_frame: Callable, on_event: Callable,
                 reopen: Callable[[str], Any] | None = None):
        self.cfg = cfg
        self.connection = connection
        self._on_frame = on_frame
        self._on_event = on_event
        self._open = reopen or (lambda dev: open_connection(cfg, device_id=dev, timeout_s=0.0))
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name='oak-driver', daemon=True)
        self.frames = 0
        self.reconnects = 0

    def start(self):
        self._thread.start()

    def stop(self, timeout: float = 5.0) -> bool:
        """Stop the thread and close the connection; True when the thread ended."""
        self._stop.set()
        if self._thread.is_alive() and threading.current_thread() is not self._thread:
            self._thread.join(timeout)
        return not self._thread.is_alive()

    @property
    def running(self) -> bool:
        return self._thread.is_alive()

    def _read(self, connection):
        """Frames until the connection fails (raises) or stop is requested."""
        # The first frame after (re)starting a pipeline can take a few seconds.
        timeout = max(self.cfg.frame_timeout_s, 10.0)
        last = time.monotonic()
        while not self._stop.is_set():
            frame = connection.get(min(0.2, self.cfg.frame_timeout_s))
            now = time.monotonic()
            if frame is None:
                if now - last > timeout:
                    raise DeviceLostError(f'no frame for {now - last:.1f} s')
                continue
            last = now
            timeout = self.cfg.frame_timeout_s
            self.frames += 1
            try:
                self._on_frame(frame, connection)
            except Exception as e:  # noqa: BLE001 - one bad frame must not stop the camera
                self._on_event('frame_error', f'{type(e).__name__}: {e}', {})

    def _run(self):
        connection = self.connection
        first = connection is None  # wait_for_device: nothing opened yet
        # Reopen what was asked for (an IP reaches a PoE camera outside the broadcast
        # domain); when that was 'any', the unit found first, by its MxID.
        device_id = self.cfg.device_id or (getattr(connection, 'device_id', '') if connection
                                           is not None else '')
        lost_at = time.monotonic()
        while not self._stop.is_set():
            if connection is None:
                connection = self._reconnect(device_id, lost_at, first)
                if connection is None:
                    return
                first = False
                device_id = self.cfg.device_id or getattr(connection, 'device_id', '')
            try:
                self._read(connection)
            except Exception as e:  # noqa: BLE001 - any failure: report and reconnect
                lost_at = time.monotonic()
                self._on_event('lost', f'{type(e).__name__}: {e}', {'device_id': device_id})
            finally:
                connection.close()
                self.connection = connection = None

    def _reconnect(self, device_id: str, lost_at: float, first: bool):
        """A new connection, retried with backoff; None when stopped first."""
        delays = backoff_delays(self.cfg.reconnect_backoff_s, self.cfg.reconnect_backoff_max_s)
        wait = 0.0 if first else next(delays)
        attempt = 0
        while not self._stop.wait(wait):
            attempt += 1
            try:
                connection = self._open(device_id)
            except Exception as e:  # noqa: BLE001
                wait = next(delays)
                self._on_event('retry', f'{type(e).__name__}: {e}',
                               {'attempt': attempt, 'delay_s': wait, 'device_id': device_id})
                continue
            if self._stop.is_set():
                connection.close()
                return None
            self.connection = connection
            if not first:
                self.reconnects += 1
            self._on_event('connected' if first else 'reconnected',
                           getattr(connection, 'description', device_id),
                           {'outage_s': time.monotonic() - lost_at, 'attempts': attempt,
                            'device_id': getattr(connection, 'device_id', device_id)})
            return connection
        return None
