"""The OAK camera (depthai 3.x) without a device, with the real depthai library.

* the adapter (`ros.oak`, no rclpy inside): host `dai.ImgFrame`s -> DepthFrame, a host
  `dai.CalibrationHandler` -> K at the published size, depthai timestamps -> ROS time, the
  stereo configuration on a real `StereoDepthConfig`, the pipeline wiring against the real
  class APIs, and the reconnecting driver (`ros.oak_device`) over host `dai.MessageQueue`s
  (closing a queue is what an unplugged device looks like to the reader);
* the node in-process (rclpy, localhost-only DDS from conftest.py) fed from a host queue:
  published image + camera_info, stamps, unplug -> error -> reconnect -> publishing again;
* a synthetic depth frame (`synth.dataset.make_frame`, oak_d camera) made into a host
  ImgFrame with a host calibration, published by the node and reconstructed by the real
  `reconstructor` node: over DDS, and in `reconstruct_oak`'s one-process hand-off;
* the console scripts without a device: exit code 1, one line, no traceback.

`@pytest.mark.hardware` tests need a connected OAK and are skipped without one.
"""
from __future__ import annotations

import datetime
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

dai = pytest.importorskip('depthai')
rclpy = pytest.importorskip('rclpy')

from rclpy.executors import MultiThreadedExecutor, SingleThreadedExecutor  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.qos import QoSProfile, ReliabilityPolicy  # noqa: E402
from sensor_msgs.msg import CameraInfo, Image, JointState  # noqa: E402
from visualization_msgs.msg import Marker  # noqa: E402

from smpl_depth_ros.ros import adapters as A  # noqa: E402
from smpl_depth_ros.ros import oak  # noqa: E402
from smpl_depth_ros.ros import oak_device as oakdev  # noqa: E402
from smpl_depth_ros.ros.oak_camera_node import (OakCameraNode,  # noqa: E402
                                                make_reconstruct_oak)
from smpl_depth_ros.ros.runner import shutdown_executor  # noqa: E402
from smpl_depth_ros.stamps import stamp_to_ns  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
PARAMS_FILE = REPO / 'config' / 'oak_camera.yaml'
K_OAK = np.array([[400.0, 0.0, 320.0], [0.0, 400.0, 200.0], [0.0, 0.0, 1.0]])  # oak_d
FRAME = 'oak_depth_optical_frame'


def host_calibration(K=K_OAK, size=(640, 400), calib_size=(1280, 800)):
    """A host CalibrationHandler whose CAM_C is `K` at `size`, stored at `calib_size`."""
    s = calib_size[0] / size[0]
    Kc = np.array(K, np.float64)
    Kc[:2] *= s
    calib = dai.CalibrationHandler()
    calib.setCameraIntrinsics(dai.CameraBoardSocket.CAM_C, Kc.tolist(), *calib_size)
    return calib


def wait_for(pred, timeout: float, step: float = 0.02) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if pred():
            return True
        time.sleep(step)
    return bool(pred())


def devices_attached() -> bool:
    return bool(dai.Device.getAllAvailableDevices() or dai.Device.getAllConnectedDevices())


# -- ImgFrame -> depth --------------------------------------------------------------------
def test_host_imgframe_to_depth():
    rng = np.random.default_rng(0)
    mm = rng.integers(0, 12000, (400, 640)).astype(np.uint16)
    frame = dai.ImgFrame()                      # as StereoDepth's depth output: RAW16 mm
    frame.setType(dai.ImgFrame.Type.RAW16)
    frame.setWidth(640)
    frame.setHeight(400)
    frame.setFrame(mm)
    ts = datetime.timedelta(seconds=1234, microseconds=567891)
    frame.setTimestamp(ts)
    frame.setSequenceNum(42)

    d = oak.frame_to_depth(frame)
    assert d.depth_mm.dtype == np.uint16 and d.size == (640, 400)
    np.testing.assert_array_equal(d.depth_mm, mm)
    assert d.sequence == 42
    assert d.source_stamp_ns == d.stamp_ns == 1234_567_891_000
    np.testing.assert_allclose(d.depth_m(), mm.astype(np.float32) * 0.001, rtol=1e-6)

    # The depth range zeroes what is outside it (edges kept).
    d = oak.frame_to_depth(frame, min_range=0.5, max_range=8.0)
    keep = (mm >= 500) & (mm <= 8000)
    np.testing.assert_array_equal(d.depth_mm, np.where(keep, mm, 0))
    # The DepthFrame owns its pixels: the device reuses frame buffers.
    frame.setFrame(np.zeros_like(mm))
    assert d.depth_mm[keep].min() >= 500


def test_imgframe_row_padding_and_wrong_type():
    mm = np.arange(6 * 5, dtype=np.uint16).reshape(6, 5) * 7
    stride = 16                                  # 10 bytes of pixels + 6 of padding per row
    buf = np.full((6, stride), 0xAB, np.uint8)
    buf[:, :10] = mm.view(np.uint8).reshape(6, 10)
    frame = dai.ImgFrame()
    frame.setType(dai.ImgFrame.Type.RAW16)
    frame.setWidth(5)
    frame.setHeight(6)
    frame.setStride(stride)
    frame.setData(buf.reshape(-1))
    np.testing.assert_array_equal(oak.frame_to_depth(frame).depth_mm, mm)

    frame.setData(buf.reshape(-1)[:40])          # truncated
    with pytest.raises(oak.FrameError, match='bytes'):
        oak.frame_to_depth(frame)
    gray = dai.ImgFrame()
    gray.setType(dai.ImgFrame.Type.GRAY8)
    gray.setWidth(5)
    gray.setHeight(6)
    gray.setData(np.zeros(30, np.uint8))
    with pytest.raises(oak.FrameError, match='RAW16'):
        oak.frame_to_depth(gray)


# -- calibration -> CameraInfo ------------------------------------------------------------
def test_calibration_to_camera_info_at_output_resolution():
    calib = host_calibration()                  # CAM_C: fx = 800 at 1280x800
    socket = oak.depth_socket(oak.OakConfig())
    assert socket == dai.CameraBoardSocket.CAM_C
    K, D = oak.intrinsics(calib, socket, (640, 400))
    np.testing.assert_allclose(K, K_OAK)        # the native aspect ratio: a plain rescale
    np.testing.assert_allclose(
        K, calib.getCameraIntrinsics(dai.CameraBoardSocket.CAM_C, 640, 400))
    assert D.shape == (5,) and not D.any()      # rectified: no distortion
    K2, _ = oak.intrinsics(calib, socket, (320, 200))     # decimation 2
    np.testing.assert_allclose(K2, np.diag([0.5, 0.5, 1.0]) @ K_OAK)
    K3, _ = oak.intrinsics(calib, socket, (640, 480))     # 4:3: centre crop, then scale
    np.testing.assert_allclose(K3, [[480, 0, 320], [0, 480, 240], [0, 0, 1]])

    # Through the JSON a device would give (eeprom round trip), then into CameraInfo.
    calib2 = dai.CalibrationHandler.fromJson(calib.eepromToJson())
    K, D = oak.intrinsics(calib2, socket, (640, 400))
    header = A.make_header(stamp_ns=5_000_000_123, frame_id=FRAME)
    info = A.camera_info_msg(K, (640, 400), header, D=D)
    K_back, D_back, size = A.camera_info_to_K(info)
    np.testing.assert_allclose(K_back, K_OAK)
    assert size == (640, 400) and not D_back.any()
    assert info.header.frame_id == FRAME and stamp_to_ns(info.header.stamp) == 5_000_000_123

    with pytest.raises(oak.CalibrationError, match='CAM_A'):
        oak.intrinsics(calib, oak.depth_socket(oak.OakConfig(align_to_color=True)),
                       (640, 400))


def test_frame_intrinsics_from_the_frame_transformation():
    frame = oak.make_host_frame(np.zeros((400, 640), np.uint16))
    assert oak.frame_intrinsics(frame) is None  # host-made: no transformation
    frame.setTransformation(dai.ImgTransformation(640, 400, K_OAK.tolist()))
    np.testing.assert_allclose(oak.frame_intrinsics(frame), K_OAK)


# -- device clock -> ROS time -------------------------------------------------------------
def test_clock_mapper_offset_and_resync():
    t = {'ros': 1_700_000_000_000_000_000, 'dai': 5_000_000_000, 'mono': 0.0}
    mapper = oak.ClockMapper(lambda: t['ros'], lambda: t['dai'], resync_period_s=1.0,
                             monotonic=lambda: t['mono'])
    offset = t['ros'] - t['dai']
    assert mapper.to_target_ns(4_990_000_000) == offset + 4_990_000_000
    assert mapper.to_target_ns(datetime.timedelta(seconds=4, microseconds=990_000)) == \
        offset + 4_990_000_000
    # The ROS clock steps by 2 s (NTP, a time jump): followed at the next resync only.
    t['ros'] += 2_000_000_000
    t['mono'] += 0.5
    assert mapper.offset_ns == offset
    t['mono'] += 0.6
    assert mapper.offset_ns == offset + 2_000_000_000
    assert mapper.resync(force=True) == offset + 2_000_000_000


def test_clock_mapper_with_the_real_depthai_clock():
    mapper = oak.ClockMapper(time.time_ns)      # ROS (system) time <- dai.Clock
    captured = dai.Clock.now() - datetime.timedelta(milliseconds=50)
    frame = oak.make_host_frame(np.ones((4, 4), np.uint16), timestamp=captured)
    d = oak.frame_to_depth(frame, mapper)
    expected = time.time_ns() - 50_000_000
    assert abs(d.stamp_ns - expected) < 5_000_000, (d.stamp_ns - expected) / 1e6
    assert d.source_stamp_ns == oak.timedelta_to_ns(captured)
    assert mapper.uncertainty_ns < 1_000_000
    # Frame order is kept.
    later = oak.frame_to_depth(oak.make_host_frame(np.ones((4, 4), np.uint16)), mapper)
    assert later.stamp_ns > d.stamp_ns


# -- configuration and pipeline -------------------------------------------------------------
def test_configure_stereo_on_a_real_config():
    cfg = oak.OakConfig(subpixel=False, extended_disparity=True, confidence_threshold=200,
                        decimation=2, median_filter='5x5', spatial_filter='on',
                        spatial_alpha=0.7, spatial_delta=9, spatial_hole_filling_radius=3,
                        spatial_iterations=2, temporal_filter='on', temporal_alpha=0.3,
                        temporal_persistency='valid_1_in_last_2', min_range=0.4,
                        max_range=6.5)
    c = oak.configure_stereo(dai.StereoDepthConfig(), cfg)
    pp = c.postProcessing
    assert c.getDepthUnit() == dai.StereoDepthConfig.AlgorithmControl.DepthUnit.MILLIMETER
    assert not c.getSubpixel() and c.getExtendedDisparity()
    assert c.getConfidenceThreshold() == 200
    assert pp.decimationFilter.decimationFactor == 2
    assert c.getMedianFilter() == dai.StereoDepthConfig.MedianFilter.KERNEL_5x5
    sf, tf = pp.spatialFilter, pp.temporalFilter
    assert sf.enable and sf.alpha == pytest.approx(0.7) and sf.delta == 9
    assert sf.holeFillingRadius == 3 and sf.numIterations == 2
    assert tf.enable and tf.alpha == pytest.approx(0.3)
    assert tf.persistencyMode.name == 'VALID_1_IN_LAST_2'
    assert (pp.thresholdFilter.minRange, pp.thresholdFilter.maxRange) == (400, 6500)

    # 'preset' leaves the preset's choices alone; 'off' switches a filter off.
    base = dai.StereoDepthConfig()
    base.setMedianFilter(dai.StereoDepthConfig.MedianFilter.KERNEL_7x7)
    base.setConfidenceThreshold(15)
    base.postProcessing.spatialFilter.enable = True
    base.postProcessing.spatialFilter.alpha = 0.5
    base.postProcessing.temporalFilter.enable = True
    c = oak.configure_stereo(base, oak.OakConfig(temporal_filter='off'))
    assert c.getMedianFilter() == dai.StereoDepthConfig.MedianFilter.KERNEL_7x7
    assert c.getConfidenceThreshold() == 15
    assert c.postProcessing.spatialFilter.enable
    assert c.postProcessing.spatialFilter.alpha == pytest.approx(0.5)
    assert not c.postProcessing.temporalFilter.enable
    assert c.getSubpixel() and c.postProcessing.decimationFilter.decimationFactor == 1


class Spec:
    """A stand-in for a depthai object that records calls and insists that every attribute
    and keyword argument exists on the real class (pybind signatures, from __doc__)."""

    RETURNS = {'build': 'self', 'requestOutput': 'Output', 'createOutputQueue': 'queue'}
    ATTRS = {'left': 'Input', 'right': 'Input', 'depth': 'Output'}

    def __init__(self, cls, log: list, name: str):
        self._cls, self._log, self._name = cls, log, name
        if cls is dai.node.StereoDepth:
            self.initialConfig = dai.StereoDepthConfig()

    def __getattr__(self, attr):
        assert hasattr(self._cls, attr), f'{self._cls.__name__} has no {attr!r}'
        if attr in self.ATTRS:
            return Spec(getattr(dai.Node, self.ATTRS[attr]), self._log, f'{self._name}.{attr}')
        doc = getattr(self._cls, attr).__doc__ or ''

        def call(*args, **kwargs):
            for k in kwargs:
                assert f'{k}:' in doc, f'{self._cls.__name__}.{attr} takes no {k!r}'
            self._log.append((f'{self._name}.{attr}', args, kwargs))
            kind = self.RETURNS.get(attr)
            if kind == 'self':
                return self
            if kind == 'queue':
                return 'the depth queue'
            if kind:
                return Spec(getattr(dai.Node, kind), self._log, f'{self._name}.{attr}()')
            return None
        return call


class SpecPipeline:
    def __init__(self):
        self.log = []
        self.nodes = []

    def create(self, cls):
        assert hasattr(dai.Pipeline, 'create')
        node = Spec(cls, self.log, f'{cls.__name__}{len(self.nodes)}')
        self.nodes.append(node)
        return node


@pytest.mark.parametrize('align', [False, True])
def test_build_pipeline_against_the_real_api(align):
    cfg = oak.OakConfig(width=640, height=400, fps=15.0, preset='high_accuracy',
                        align_to_color=align, median_filter='3x3')
    p = SpecPipeline()
    q = oak.build_pipeline(p, cfg)
    assert q == 'the depth queue'
    calls = {}
    for name, args, kwargs in p.log:
        calls.setdefault(name, []).append((args, kwargs))
    cam_b, cam_c, stereo = p.nodes
    assert calls['Camera0.build'][0][0] == (dai.CameraBoardSocket.CAM_B,)
    assert calls['Camera1.build'][0][0] == (dai.CameraBoardSocket.CAM_C,)
    for cam in ('Camera0', 'Camera1'):
        (args, kwargs), = calls[f'{cam}.requestOutput']
        assert args == ((640, 400),) and kwargs['fps'] == 15.0
        assert kwargs['resizeMode'] == dai.ImgResizeMode.CROP
    assert calls['Camera0.requestOutput().link'][0][0][0]._name == 'StereoDepth2.left'
    assert calls['Camera1.requestOutput().link'][0][0][0]._name == 'StereoDepth2.right'
    assert calls['StereoDepth2.setDefaultProfilePreset'][0][0] == (
        dai.node.StereoDepth.PresetMode.ACCURACY,)
    (align_args, _), = calls['StereoDepth2.setDepthAlign']
    if align:
        assert align_args == (dai.CameraBoardSocket.CAM_A,)
        assert calls['StereoDepth2.setOutputSize'][0][0] == (640, 400)
    else:
        assert align_args == (
            dai.StereoDepthConfig.AlgorithmControl.DepthAlign.RECTIFIED_RIGHT,)
        assert 'StereoDepth2.setOutputSize' not in calls
    assert stereo.initialConfig.getMedianFilter() == \
        dai.StereoDepthConfig.MedianFilter.KERNEL_3x3
    (_, kwargs), = calls['StereoDepth2.depth.createOutputQueue']
    assert kwargs == {'maxSize': 2, 'blocking': False}
    # The preset is applied before our settings (it rewrites the whole config).
    names = [n for n, _, _ in p.log]
    assert names.index('StereoDepth2.setDefaultProfilePreset') < \
        names.index('StereoDepth2.setDepthAlign')


def test_validate_config():
    assert oak.validate(oak.OakConfig()) is None
    for kw, word in [({'preset': 'ultra'}, 'preset'), ({'median_filter': '9x9'}, 'median'),
                     ({'spatial_filter': 'yes'}, 'spatial_filter'), ({'fps': 0.0}, 'fps'),
                     ({'decimation': 5}, 'decimation'), ({'max_range': 70.0}, 'max_range'),
                     ({'min_range': 3.0, 'max_range': 2.0}, 'min_range'),
                     ({'temporal_persistency': 'always'}, 'temporal_persistency'),
                     ({'reconnect_backoff_s': 20.0}, 'reconnect_backoff_s')]:
        reason = oak.validate(oak.OakConfig(**kw))
        assert reason and word in reason, (kw, reason)
    for name in oak.PRESETS:
        assert isinstance(oak.preset_mode(name), dai.node.StereoDepth.PresetMode)


# -- the reconnecting driver ----------------------------------------------------------------
def host_connection(device_id: str = 'HOSTDEV', maxsize: int = 4):
    q = dai.MessageQueue('depth', maxsize, False)
    return oakdev.QueueConnection(q, host_calibration(), device_id), q


def test_driver_survives_unplug_and_backs_off():
    cfg = oak.OakConfig(reconnect_backoff_s=0.05, reconnect_backoff_max_s=0.2,
                        frame_timeout_s=1.0)
    first, q1 = host_connection()
    second, q2 = host_connection()
    frames, events, opened = [], [], []
    plan = [oakdev.DeviceNotFoundError('not back yet')] * 3 + [second]

    def reopen(device_id):
        opened.append((device_id, time.monotonic()))
        item = plan.pop(0)
        if isinstance(item, Exception):
            raise item
        return item

    driver = oakdev.OakDriver(cfg, first, lambda f, s: frames.append((f.getSequenceNum(), s)),
                              lambda kind, msg, info: events.append((kind, msg, info)),
                              reopen=reopen)
    driver.start()
    try:
        for i in range(3):
            q1.send(oak.make_host_frame(np.full((4, 4), 1000, np.uint16), sequence=i))
        assert wait_for(lambda: len(frames) == 3, 5.0)
        t_unplug = time.monotonic()
        q1.close()                                # the device goes away
        assert wait_for(lambda: any(k == 'reconnected' for k, _, _ in events), 5.0), events
        q2.send(oak.make_host_frame(np.full((4, 4), 1000, np.uint16), sequence=10))
        assert wait_for(lambda: len(frames) == 4, 5.0)
    finally:
        assert driver.stop()
    kinds = [k for k, _, _ in events]
    assert kinds == ['lost', 'retry', 'retry', 'retry', 'reconnected'], events
    assert 'DeviceLostError' in events[0][1]
    assert [e[2]['delay_s'] for e in events[1:4]] == [0.1, 0.2, 0.2]   # doubling, capped
    assert all(dev == 'HOSTDEV' for dev, _ in opened)   # the same unit, not any device
    gaps = np.diff([t_unplug] + [t for _, t in opened])
    assert gaps[0] >= 0.045 and gaps[1] >= 0.095 and gaps[2] >= 0.19, gaps
    assert frames[-1][0] == 10 and frames[-1][1] is second
    assert events[-1][2]['attempts'] == 4 and driver.reconnects == 1
    assert first._queue.isClosed() and second._queue.isClosed()   # closed on stop too


def test_driver_treats_silence_as_a_lost_device():
    cfg = oak.OakConfig(reconnect_backoff_s=0.05, frame_timeout_s=0.3)
    connection, q = host_connection()
    events = []
    driver = oakdev.OakDriver(cfg, connection, lambda f, s: None,
                              lambda kind, msg, info: events.append((kind, msg)),
                              reopen=lambda dev: (_ for _ in ()).throw(
                                  oakdev.DeviceNotFoundError('gone')))
    driver.start()
    try:
        q.send(oak.make_host_frame(np.ones((2, 2), np.uint16)))  # one frame, then nothing
        assert wait_for(lambda: events and events[0][0] == 'lost', 5.0), events
        assert 'no frame for' in events[0][1]
    finally:
        assert driver.stop()


def test_find_device_names_what_it_looked_for():
    if devices_attached():
        pytest.skip('an OAK device is attached')
    with pytest.raises(oakdev.DeviceNotFoundError) as e:
        oakdev.find_device('', timeout_s=0.0)
    assert 'any OAK device' in str(e.value) and '\n' not in str(e.value)
    with pytest.raises(oakdev.DeviceNotFoundError) as e:
        oakdev.find_device('18443010D116631200', timeout_s=0.0)
    assert "'18443010D116631200'" in str(e.value)


def test_params_file_mirrors_defaults():
    yaml = pytest.importorskip('yaml')
    from smpl_depth_ros.ros.oak_camera_node import parameter_defaults, validate

    values = yaml.safe_load(PARAMS_FILE.read_text())['/**']['ros__parameters']
    defaults = parameter_defaults()
    assert set(values) == set(defaults)
    for k, v in defaults.items():
        assert type(values[k]) is type(v), k
        assert values[k] == pytest.approx(v) if isinstance(v, float) else values[k] == v, k
    assert validate(values) is None
    assert defaults['frame_id'] == FRAME


# -- console scripts without a device ---------------------------------------------------------
def _script(name: str) -> list[str]:
    exe = Path(sys.executable).with_name(name)
    if exe.exists():
        return [str(exe)]
    module = 'smpl_depth_ros.ros.oak_camera_node'
    func = 'main' if name == 'oak_camera' else 'main_with_reconstructor'
    return [sys.executable, '-c', f'import sys; from {module} import {func}; sys.exit({func}())']


def test_console_scripts_without_a_device_fail_in_one_line():
    if devices_attached():
        pytest.skip('an OAK device is attached')
    env = dict(os.environ, PYTHONPATH=str(REPO))
    env.pop('DEPTHAI_LEVEL', None)              # the node's own default must keep it quiet
    runs = {
        'any': _script('oak_camera') + ['--ros-args', '-p', 'connect_timeout_s:=0.5'],
        'mxid': _script('oak_camera') + ['--ros-args', '-p', 'connect_timeout_s:=0.5',
                                         '-p', 'device_id:=18443010D116631200'],
        'composite': _script('reconstruct_oak') + [
            '--ros-args', '-p', 'connect_timeout_s:=0.5', '-p', 'device_id:=192.168.7.7'],
    }
    procs = {k: subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                 text=True, env=env, cwd=REPO) for k, cmd in runs.items()}
    out = {}
    for k, p in procs.items():
        try:
            text, _ = p.communicate(timeout=120)
        except subprocess.TimeoutExpired:
            p.kill()
            text, _ = p.communicate()
        out[k] = (p.returncode, [ln for ln in text.splitlines() if ln.strip()])
    for k, (code, lines) in out.items():
        assert code == 1, (k, code, lines)
        assert len(lines) == 1, (k, lines)
        assert 'Traceback' not in lines[0], (k, lines)
    assert 'no OAK device found' in out['any'][1][0]
    assert 'any OAK device (USB or PoE)' in out['any'][1][0]
    assert "'18443010D116631200'" in out['mxid'][1][0]
    assert "'192.168.7.7'" in out['composite'][1][0]


# -- the node, in-process ---------------------------------------------------------------------
class Spinner:
    """Spins nodes of one context on a background thread until `close`."""

    def __init__(self, context, *nodes, multi: bool = False):
        self.executor = (MultiThreadedExecutor(num_threads=2, context=context) if multi else
                         SingleThreadedExecutor(context=context))
        for n in nodes:
            self.executor.add_node(n)
        self.running = True
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()

    def _spin(self):
        try:
            while self.running:
                self.executor.spin_once(timeout_sec=0.05)
        except Exception:  # context shut down under us at teardown
            pass

    def close(self):
        self.running = False
        self.thread.join(5.0)
        shutdown_executor(self.executor, 2.0)


class Collector:
    """Subscribes to topics and keeps every message."""

    def __init__(self, context, topics: dict):
        self.node = rclpy.create_node('collector', context=context)
        self.lock = threading.Lock()
        self.got = {t: [] for t in topics}
        qos = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE)
        for topic, typ in topics.items():
            self.node.create_subscription(typ, topic, self._keep(topic), qos)

    def _keep(self, topic):
        def cb(msg):
            with self.lock:
                self.got[topic].append(msg)
        return cb

    def msgs(self, topic):
        with self.lock:
            return list(self.got[topic])


class RecordingCamera(OakCameraNode):
    """OakCameraNode that also keeps its driver events."""

    def __init__(self, *a, **kw):
        self.events = []
        super().__init__(*a, **kw)

    def _on_event(self, kind, message, info):
        self.events.append((kind, message))
        super()._on_event(kind, message, info)


class HostDevice:
    """A connection factory over host queues: `plug()` makes the next connection, `unplug()`
    closes the current one; opening while unplugged fails like a missing device."""

    def __init__(self, calibration=None):
        self.calibration = calibration or host_calibration()
        self.queue = None
        self.plugged = True
        self.opens = []

    def __call__(self, device_id: str, timeout_s: float):
        self.opens.append(device_id)
        if not self.plugged:
            raise oakdev.DeviceNotFoundError(f"no OAK device found: looked for '{device_id}'")
        self.queue = dai.MessageQueue('depth', 4, False)
        return oakdev.QueueConnection(self.queue, self.calibration, 'HOSTDEV', 'host OAK HOSTDEV')

    def unplug(self):
        self.plugged = False
        self.queue.close()

    def send(self, mm: np.ndarray, sequence: int = 0, timestamp=None):
        self.queue.send(oak.make_host_frame(mm, timestamp=timestamp, sequence=sequence))


def test_node_publishes_depth_and_camera_info(rclpy_context):
    dev = HostDevice()
    cam = RecordingCamera(connection_factory=dev, context=rclpy_context, namespace='/oak',
                          parameter_overrides=[Parameter('min_range', value=0.3),
                                               Parameter('max_range', value=6.0),
                                               Parameter('reconnect_backoff_s', value=0.05),
                                               Parameter('reconnect_backoff_max_s',
                                                         value=0.1)])
    col = Collector(rclpy_context, {'/oak/depth/image_raw': Image,
                                    '/oak/depth/camera_info': CameraInfo})
    spinner = Spinner(rclpy_context, cam, col.node)
    try:
        assert wait_for(lambda: cam._pub_depth.get_subscription_count() > 0, 10.0)
        mm = np.random.default_rng(1).integers(0, 9000, (400, 640)).astype(np.uint16)
        ros_before = cam.get_clock().now().nanoseconds
        dev.send(mm, sequence=1)
        ros_after = cam.get_clock().now().nanoseconds
        assert wait_for(lambda: col.msgs('/oak/depth/image_raw'), 10.0)
        img = col.msgs('/oak/depth/image_raw')[0]
        assert wait_for(lambda: col.msgs('/oak/depth/camera_info'), 5.0)
        info = next(m for m in col.msgs('/oak/depth/camera_info') if m.header == img.header)
        assert (img.encoding, img.width, img.height, img.step) == ('16UC1', 640, 400, 1280)
        assert img.header.frame_id == FRAME
        stamp = stamp_to_ns(img.header.stamp)   # the capture time, in ROS time
        assert ros_before - 5_000_000 <= stamp <= ros_after + 5_000_000
        got = A.image_to_array(img)
        np.testing.assert_array_equal(got, np.where((mm >= 300) & (mm <= 6000), mm, 0))
        K, D, size = A.camera_info_to_K(info)
        np.testing.assert_allclose(K, K_OAK)
        assert size == (640, 400) and not D.any()

        # frame_id may change at runtime; the stream parameters may not.
        assert cam.set_parameters([Parameter('frame_id', value='cam2')])[0].successful
        assert not cam.set_parameters([Parameter('fps', value=15.0)])[0].successful

        # Unplugged: error logged, retries with backoff, publishing resumes once it's back.
        n0 = len(col.msgs('/oak/depth/image_raw'))
        dev.unplug()
        assert wait_for(lambda: sum(k == 'retry' for k, _ in cam.events) >= 2, 5.0)
        assert cam.events[0][0] == 'lost'
        dev.plugged = True
        assert wait_for(lambda: any(k == 'reconnected' for k, _ in cam.events), 5.0)
        assert set(dev.opens[1:]) == {'HOSTDEV'}
        dev.send(mm, sequence=2)
        assert wait_for(lambda: len(col.msgs('/oak/depth/image_raw')) > n0, 10.0)
        assert col.msgs('/oak/depth/image_raw')[-1].header.frame_id == 'cam2'
    finally:
        assert cam.stop()
        spinner.close()
        col.node.destroy_node()
        cam.destroy_node()


def test_invalid_parameters_fail_before_the_device_is_looked_for(rclpy_context):
    dev = HostDevice()
    with pytest.raises(ValueError, match='preset must be one of'):
        OakCameraNode(connection_factory=dev, context=rclpy_context,
                      parameter_overrides=[Parameter('preset', value='ultra')])
    assert dev.opens == []


def test_wait_for_device_starts_without_one(rclpy_context):
    dev = HostDevice()
    dev.plugged = False
    cam = RecordingCamera(connection_factory=dev, context=rclpy_context, namespace='/w',
                          parameter_overrides=[Parameter('wait_for_device', value=True),
                                               Parameter('reconnect_backoff_s', value=0.05),
                                               Parameter('reconnect_backoff_max_s',
                                                         value=0.1)])
    spinner = Spinner(rclpy_context, cam)
    try:
        assert wait_for(lambda: len(dev.opens) >= 2, 5.0)
        dev.plugged = True
        assert wait_for(lambda: ('connected', 'host OAK HOSTDEV') in cam.events, 5.0)
        dev.send(np.full((400, 640), 1500, np.uint16))
        assert wait_for(lambda: cam.published == 1, 5.0)
    finally:
        assert cam.stop()
        spinner.close()
        cam.destroy_node()


# -- a synthetic person through the camera node into the reconstructor -------------------------
@pytest.fixture(scope='module')
def real_core():
    pipeline = pytest.importorskip('smpl_depth_ros.pipeline')
    from smpl_depth_ros.config import PipelineConfig
    return pipeline.Reconstructor(PipelineConfig(device='cpu'))


@pytest.fixture(scope='module')
def person(real_core):
    """A synthetic oak_d frame (`synth.dataset.make_frame`) as depth millimetres."""
    from smpl_depth_ros.synth.camera import get_camera
    from smpl_depth_ros.synth.dataset import make_frame
    from smpl_depth_ros.synth.poses import PoseSampler

    camera = get_camera('oak_d')
    body = real_core.body
    frame = make_frame(body, PoseSampler(body), np.random.default_rng(7), camera)
    np.testing.assert_allclose(frame['K'], K_OAK)
    mm = np.clip(np.round(frame['depth'] * 1000.0), 0, 65535).astype(np.uint16)
    return {'mm': mm, 'vertices': np.asarray(frame['vertices'], np.float64)}


@pytest.fixture
def core(real_core):
    yield real_core
    real_core.reset()


def _mesh_vertices(marker: Marker) -> np.ndarray:
    return np.array([[p.x, p.y, p.z] for p in marker.points])


def _send_until(dev: HostDevice, mm, done, timeout: float, period: float = 1.0) -> None:
    end = time.monotonic() + timeout
    seq = 0
    while time.monotonic() < end:
        dev.send(mm, sequence=seq)
        seq += 1
        if wait_for(done, period):
            return
    raise AssertionError(f'no result within {timeout} s')


def test_published_messages_feed_the_reconstructor(rclpy_context, core, person):
    from smpl_depth_ros.ros.reconstructor_node import ReconstructorNode

    dev = HostDevice()
    cam = OakCameraNode(connection_factory=dev, context=rclpy_context, namespace='/oak')
    rec = ReconstructorNode(reconstructor_factory=lambda cfg: core, context=rclpy_context,
                            namespace='/oak',
                            cli_args=['--ros-args', '-r', 'depth:=depth/image_raw',
                                      '-r', 'camera_info:=depth/camera_info'],
                            parameter_overrides=[Parameter('qos_reliability',
                                                           value='reliable')])
    col = Collector(rclpy_context, {'/oak/depth/image_raw': Image,
                                    '/oak/reconstructor/smpl_params': JointState,
                                    '/oak/reconstructor/mesh': Marker})
    spinner = Spinner(rclpy_context, cam, rec, col.node)
    try:
        assert wait_for(lambda: cam._pub_depth.get_subscription_count() >= 2, 10.0)
        _send_until(dev, person['mm'], lambda: col.msgs('/oak/reconstructor/mesh'), 60.0)
        published = {stamp_to_ns(m.header.stamp) for m in col.msgs('/oak/depth/image_raw')}
        mesh = col.msgs('/oak/reconstructor/mesh')[0]
        assert mesh.header.frame_id == FRAME
        assert stamp_to_ns(mesh.header.stamp) in published   # the camera's stamp, copied
        err = np.linalg.norm(_mesh_vertices(mesh).mean(0) - person['vertices'].mean(0))
        assert err < 0.1, err                       # the fitted body is where the person is
        assert wait_for(lambda: col.msgs('/oak/reconstructor/smpl_params'), 5.0)
    finally:
        assert rec.stop() and cam.stop()
        spinner.close()
        for n in (col.node, rec, cam):
            n.destroy_node()


def test_reconstruct_oak_hands_over_the_same_messages(rclpy_context, core, person):
    dev = HostDevice()
    cam, rec = make_reconstruct_oak(connection_factory=dev,
                                    reconstructor_factory=lambda cfg: core,
                                    context=rclpy_context)
    handed = []
    original = rec._on_depth
    rec._on_depth = lambda msg: (handed.append(msg), original(msg))
    published = []
    cam.add_sink(lambda image, info: published.append(image))
    col = Collector(rclpy_context, {'/reconstructor/mesh': Marker})
    spinner = Spinner(rclpy_context, cam, rec, col.node, multi=True)
    try:
        _send_until(dev, person['mm'], lambda: col.msgs('/reconstructor/mesh'), 60.0)
        mesh = col.msgs('/reconstructor/mesh')[0]
        assert mesh.header.frame_id == FRAME
        # No serialisation: the reconstructor got the very objects the camera published.
        assert handed and all(a is b for a, b in zip(handed, published))
        assert stamp_to_ns(mesh.header.stamp) in {stamp_to_ns(m.header.stamp)
                                                  for m in handed}
        err = np.linalg.norm(_mesh_vertices(mesh).mean(0) - person['vertices'].mean(0))
        assert err < 0.1, err
        # The camera told the reconstructor which sensor it is (the core takes it when
        # both worker threads are idle).
        assert rec.get_parameter('sensor').value == 'oak_d'
        assert wait_for(lambda: rec._config.sensor == 'oak_d', 10.0), rec._config.sensor
    finally:
        assert rec.stop() and cam.stop()
        spinner.close()
        for n in (col.node, rec, cam):
            n.destroy_node()


def test_sensor_preset_follows_the_camera_and_its_settings():
    cfg = oak.OakConfig()
    assert oak.sensor_preset(cfg, 'OAK-D 1844301') == 'oak_d'
    assert oak.sensor_preset(cfg, 'OAK-D-PRO-W 1944301') == 'oak_d_pro'
    assert oak.sensor_preset(oak.OakConfig(subpixel=False), 'OAK-D-PRO') == \
        'oak_d_no_subpixel'
    from smpl_depth_ros.synth.sensors import SENSORS
    for name in ('oak_d', 'oak_d_pro', 'oak_d_no_subpixel'):
        assert name in SENSORS
    # whole-pixel disparity steps: a far larger error far away than 1/8 px subpixel
    assert float(SENSORS['oak_d_no_subpixel'].sigma(4.0)) > \
        2 * float(SENSORS['oak_d'].sigma(4.0))


# -- real hardware ----------------------------------------------------------------------------
@pytest.fixture
def oak_device():
    if not dai.Device.getAllAvailableDevices():
        pytest.skip('no OAK device attached')
    connection = oakdev.open_connection(oak.OakConfig(), timeout_s=5.0)
    yield connection
    connection.close()


@pytest.mark.hardware
def test_hardware_open_device_and_read_frames(oak_device):
    mapper = oak.ClockMapper(time.time_ns)
    frames = []
    end = time.monotonic() + 15.0
    while len(frames) < 10 and time.monotonic() < end:
        f = oak_device.get(1.0)
        if f is not None:
            frames.append(oak.frame_to_depth(f, mapper))
    assert len(frames) == 10
    assert all(d.size == (640, 400) for d in frames)
    assert all((d.depth_mm > 0).mean() > 0.05 for d in frames)
    stamps = [d.stamp_ns for d in frames]
    assert all(b > a for a, b in zip(stamps, stamps[1:]))
    assert abs(time.time_ns() - stamps[-1]) < 500_000_000
    K, _ = oak.intrinsics(oak_device.calibration, dai.CameraBoardSocket.CAM_C, (640, 400))
    assert 200 < K[0, 0] < 1000 and abs(K[0, 2] - 320) < 40 and abs(K[1, 2] - 200) < 40
