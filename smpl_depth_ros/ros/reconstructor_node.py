"""The `reconstructor` node: live depth in; mesh, segmentation, body parameters out.

Topics (relative names, remappable):
    subscribes  depth (sensor_msgs/Image, 16UC1 mm or 32FC1 m)
                camera_info (sensor_msgs/CameraInfo; paired by frame_id, newest wins)
    publishes   ~/mesh (visualization_msgs/Marker TRIANGLE_LIST)
                ~/segmentation (sensor_msgs/Image rgb8), ~/segmentation/labels (mono8)
                ~/smpl_params (sensor_msgs/JointState, schema in ros.adapters)
                ~/skeleton (visualization_msgs/MarkerArray)
                /diagnostics (diagnostic_msgs/DiagnosticArray)

Threading: the subscription callbacks only convert the message and drop the frame into a
one-slot mailbox (a newer frame overwrites a stale one, which is counted as dropped). Three
worker threads run the core one frame apart: once the reconstructor has taken a frame, the
detector takes the newest one, timed to be done when the reconstructor usually is, and
runs `Reconstructor.detect` (checks, sensor noise, person candidates) and
`Reconstructor.look_ahead` (the network passes of the candidates likely to be persons);
the reconstructor runs `Reconstructor.reconstruct` (the network passes still missing, fits,
tracks) and hands the result to the publisher, which publishes the bodies (meshes,
skeleton, parameters, IDs, TF) at once, then runs `Reconstructor.finish` (the labels from
the fitted meshes) and publishes the images (segmentation, body index), beside the next
frame's fits. Their results
are those of `Reconstructor.process` frame by frame. A changed configuration is applied by
the detector while the detector and the reconstructor are idle. ROS entities are created
and destroyed on the main (executor) thread only.

Camera distortion: with a non-zero D the depth image is taken as a rectified one, seen
through camera_info's P (the ROS convention; reported once in the log and in diagnostics),
unless `undistort` says it is the raw image of a lens-distorted camera: then the pipeline
resamples it to pinhole (`smpl_depth_ros.rectify`) and the published images stay aligned
with it.
"""
from __future__ import annotations

import gc
import sys
import threading
import time
from collections import Counter, deque
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from rcl_interfaces.msg import SetParametersResult
from diagnostic_msgs.msg import DiagnosticArray
from sensor_msgs.msg import CameraInfo, Image

from smpl_depth_ros import params as P
from smpl_depth_ros.config import PipelineConfig
from smpl_depth_ros.rectify import Lens
from smpl_depth_ros.stamps import stamp_to_ns
from smpl_depth_ros.ros import adapters as A
from smpl_depth_ros.ros.outputs import TOPICS, FrameOutputs
from smpl_depth_ros.ros.parameters import declare
from smpl_depth_ros.ros.runner import ros_args, run_nodes
from smpl_depth_ros.types import InputError

NODE_NAME = 'reconstructor'

STAMP_JUMP_BACK_S = 0.001    # a depth stamp this far before the previous one is a jump
STAMP_JUMP_FORWARD_S = 60.0  # ... and this far after it
INFO_STALE_S = 2.0           # diagnostics warn when camera_info is older than this
STAGE_FRAMES = 15            # the stages' usual times: medians over this many frames
RELIABILITY = {'best_effort': ReliabilityPolicy.BEST_EFFORT,
               'reliable': ReliabilityPolicy.RELIABLE}


# -- the frame hand-off ----------------------------------------------------------------
@dataclass
class Frame:
    """A converted depth frame waiting for the worker."""

    header: Any
    depth: np.ndarray
    K: np.ndarray
    stamp_ns: int
    received: float  # time.monotonic() when the callback got it
    lens: Lens | None = None  # the camera's lens, when it distorts (rectify)


class Mailbox:
    """One-slot, newest-wins hand-off between callbacks and the worker."""

    def __init__(self):
        self._cv = threading.Condition()
        self._item = None
        self.dropped = 0

    def put(self, item) -> bool:
        """Store `item`; True when it overwrote an unprocessed one (counted as dropped)."""
        with self._cv:
            stale = self._item is not None
            if stale:
                self.dropped += 1
            self._item = item
            self._cv.notify()
            return stale

    def get(self, timeout: float, then: Callable[[Any], None] | None = None):
        """The newest item (removing it), or None after `timeout` seconds; `then(item)`
        is called before the mailbox lets go of it (no moment where it is nowhere)."""
        with self._cv:
            if self._item is None:
                self._cv.wait(timeout)
            item, self._item = self._item, None
            if then is not None:
                then(item)
            return item

    def pending(self) -> int:
        with self._cv:
            return int(self._item is not None)

    def wake(self):
        with self._cv:
            self._cv.notify_all()


class Handoff:
    """One-slot hand-off of a frame from one worker thread to the next: detected, from
    the detector to the reconstructor; reconstructed, from the reconstructor to the
    publisher. The giver waits for the slot to be free (`wait_free`) before it takes
    on the next frame, so nothing is dropped here; `busy` is True from `take` to `done`."""

    def __init__(self):
        self._cv = threading.Condition()
        self._item = None
        self.busy = False
        self.taken = 0.0  # time.monotonic() of the last `take`
        self.detecting = False  # the detector holds a frame (taken from the mailbox)

    def wait_free(self, timeout: float, idle: bool = False) -> bool:
        """Wait until the slot is empty (with `idle`, and the reconstructor idle too);
        False after `timeout` seconds."""
        with self._cv:
            return self._cv.wait_for(
                lambda: self._item is None and not (idle and self.busy), timeout)

    def hold(self, mailbox: Mailbox, timeout: float):
        """The newest frame of `mailbox` for the detector (None after `timeout` seconds):
        from then until `put` or `release` it counts as pending here, so a frame is
        always pending somewhere until it is reconstructed or reported."""
        return mailbox.get(timeout=timeout, then=self._hold)

    def _hold(self, frame) -> None:
        with self._cv:
            self.detecting = frame is not None

    def release(self) -> None:
        """The held frame ends in the detector (reported as unusable)."""
        with self._cv:
            self.detecting = False
            self._cv.notify_all()

    def put(self, item) -> None:
        with self._cv:
            self._item = item
            self.detecting = False
            self._cv.notify_all()

    def take(self, timeout: float):
        """The waiting item (the reconstructor is then busy until `done`), or None after
        `timeout` seconds."""
        with self._cv:
            if self._item is None:
                self._cv.wait(timeout)
            item, self._item = self._item, None
            self.busy = item is not None
            if self.busy:
                self.taken = time.monotonic()
            self._cv.notify_all()
            return item

    def wait_until(self, when: float) -> None:
        """Wait until time.monotonic() reaches `when`, or the reconstructor is done."""
        with self._cv:
            self._cv.wait_for(lambda: not self.busy, max(0.0, when - time.monotonic()))

    def done(self) -> None:
        with self._cv:
            self.busy = False
            self._cv.notify_all()

    def pending(self) -> int:
        """Frames between the mailbox and the reconstructor (0 or 1)."""
        with self._cv:
            return int(self._item is not None or self.detecting)

    def wake(self) -> None:
        with self._cv:
            self._cv.notify_all()


def _percentiles(values) -> tuple[float, float, float]:
    if not values:
        return float('nan'), float('nan'), float('nan')
    a = np.asarray(values, np.float64)
    return float(np.percentile(a, 50)), float(np.percentile(a, 95)), float(a.max())


class ReconstructorNode(Node):
    """Depth -> body mesh + parameters, two worker threads (see the module docstring).

    Args:
        reconstructor_factory: builds the core from a PipelineConfig (default:
            `smpl_depth_ros.pipeline.Reconstructor`); tests may wrap it.
        **kwargs: passed to rclpy's Node (context, parameter_overrides, cli_args ...).
    """

    def __init__(self, reconstructor_factory: Callable[[PipelineConfig], Any] | None = None,
                 **kwargs):
        self._t_start = time.monotonic()
        super().__init__(NODE_NAME, **kwargs)
        log = self.get_logger()
        # Every parameter of the schema (params.SCHEMA), expert knobs under 'advanced.';
        # self._values holds them by their schema names.
        self._values = declare(self, P.SCHEMA)
        reason = P.check(self._values)
        if reason:
            raise ValueError(f'invalid parameters: {reason}')
        # Overrides (params file, -p) naming no parameter: a typo, or a short name.
        self.unknown_parameters = sorted(
            set(getattr(self, '_parameter_overrides', {}))
            - {p.ros_name for p in P.SCHEMA.values()} - {'use_sim_time'})
        if self.unknown_parameters:
            log.warning(f"ignoring unknown parameter(s) {', '.join(self.unknown_parameters)} "
                        "(expert knobs are under 'advanced.', e.g. advanced.fit.iterations; "
                        'see --print-params)')
        self._config, outputs, _ = P.split(self._values)
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self.add_post_set_parameters_callback(self._after_set_parameters)

        self._lock = threading.Lock()             # stats, pending config
        self._diag_lock = threading.Lock()        # /diagnostics publisher (two threads)
        self._mailbox = Mailbox()
        self._handoff = Handoff()
        self._finishing = Handoff()  # reconstructed, to finish and publish
        self._stage_s = [0.0, 0.0]                # usual detection, reconstruction (s)
        self._stage_times = (deque(maxlen=STAGE_FRAMES), deque(maxlen=STAGE_FRAMES))
        self._stop = threading.Event()
        self._camera_infos: dict[str, Any] = {}   # frame_id -> (camera, lens) | InputError
        self._info_time: dict[str, float] = {}    # frame_id -> last camera_info (monotonic)
        self._last_stamp_ns: int | None = None    # worker: the previous frame's stamp
        self._depth_time = 0.0                    # last depth message (monotonic)
        self._notices = Counter()                 # events that skip no frame (time jumps)
        self._lens_log: dict[str, str] = {}       # frame_id -> what is done with its lens
        self._throttle: dict[str, float] = {}
        self._stats = Counter()
        self._errors = Counter()
        self._last_error: tuple[str, str] | None = None
        self._latency_stamp = deque(maxlen=300)   # ms, header stamp -> publish
        self._latency_recv = deque(maxlen=300)    # ms, callback -> publish
        self._timings: dict[str, float] = {}
        self._last_person: dict[str, Any] = {}
        self._first_result_s: float | None = None
        self._prev = (time.monotonic(), 0, 0)     # diagnostics rate window
        self._pending_config: PipelineConfig | None = None
        self._errors_prev = 0

        # Publishers first (outputs), then the core, then the inputs.
        self._pubs = {}
        for key, (topic, msgtype) in TOPICS.items():
            try:
                cls = A.as_factory().cls(msgtype)
            except ImportError:  # tf2_msgs is not installed (a bare rclpy venv)
                log.warning(f'{msgtype} is not installed: {topic} is not published')
                continue
            self._pubs[key] = self.create_publisher(
                cls, topic if topic.startswith('/') else f'~/{topic}',
                100 if key == 'tf' else 5)  # tf2_ros' TransformBroadcaster keeps 100
        self._pub_diag = self.create_publisher(DiagnosticArray, '/diagnostics', 10)

        if reconstructor_factory is None:
            from smpl_depth_ros.pipeline import Reconstructor  # torch: after rclpy.init
            reconstructor_factory = Reconstructor
        self._factory = reconstructor_factory
        log.info(f"loading the {self._config.backend} body model and network "
                 f"(device '{self._config.device}') ...")
        t0 = time.monotonic()
        self._rec = self._factory(self._config)
        if not self.context.ok():  # SIGINT/SIGTERM while loading
            raise ExternalShutdownException()
        self._body = self._rec.body
        self._outputs = FrameOutputs(self._body, self._rec.fitter.joint_frames,
                                     outputs,
                                     has_tf='tf' in self._pubs)
        log.info(f'loaded {self._body.name} body model ({self._body.num_vertices} vertices, '
                 f'{len(self._body.faces)} triangles) and network on {self._rec.device} in '
                 f'{time.monotonic() - t0:.2f} s')

        qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=self._values['qos_depth'],
                         reliability=RELIABILITY[self._values['qos_reliability']])
        self._sub_info = self.create_subscription(CameraInfo, 'camera_info',
                                                  self._on_camera_info, qos)
        self._sub_depth = self.create_subscription(Image, 'depth', self._on_depth, qos)
        self._diag_timer = self.create_timer(self._values['diagnostics_period_s'],
                                             self._publish_diagnostics)
        self._detector = threading.Thread(target=self._run_detector,
                                          name='reconstructor-detector', daemon=True)
        self._worker = threading.Thread(target=self._run_worker, name='reconstructor-worker',
                                        daemon=True)
        self._publisher = threading.Thread(target=self._run_publisher,
                                           name='reconstructor-publisher', daemon=True)
        self._detector.start()
        self._worker.start()
        self._publisher.start()
        log.info(f"listening on '{self._sub_depth.topic_name}' + "
                 f"'{self._sub_info.topic_name}' ({self._values['qos_reliability']}, depth "
                 f"{self._values['qos_depth']})")

    def tune_process(self) -> 'ReconstructorNode':
        """Process-wide settings for a process that runs this node, applied by the console
        scripts (never by the constructor): torch's CPU threads (`cpu_threads`), and the
        loaded model, network and libraries moved out of the cyclic garbage collector's
        reach, so that collections triggered by each frame's many small objects stay short
        (fewer latency spikes)."""
        if self._values['cpu_threads'] > 0:
            import torch
            torch.set_num_threads(self._values['cpu_threads'])
        gc.collect()
        gc.freeze()
        return self

    # -- parameters ----------------------------------------------------------------------
    def _on_set_parameters(self, params: list[Parameter]) -> SetParametersResult:
        new = dict(self._values)
        for p in params:
            spec = P.lookup(p.name)
            if spec is None or spec.ros_name != p.name:  # use_sim_time, ...
                continue
            if spec.restart and p.value != self._values[spec.name]:
                return SetParametersResult(successful=False,
                                           reason=f'{p.name} is read-only: restart the node '
                                                  'to change it')
            new[spec.name] = p.value
        reason = P.check(new)
        return SetParametersResult(successful=reason is None, reason=reason or '')

    def _after_set_parameters(self, params: list[Parameter]):
        # Runs on the executor thread after a successful change.
        groups = set()
        for p in params:
            spec = P.lookup(p.name)
            if spec is not None and spec.ros_name == p.name:
                self._values[spec.name] = p.value
                groups.add(spec.group)
        config, outputs, node = P.split(self._values)
        if hasattr(self, '_outputs'):  # (set once the model is loaded)
            self._outputs.opts = outputs
        if 'node' in groups:
            self._diag_timer.timer_period_ns = int(node.diagnostics_period_s * 1e9)
        if groups & {'core', 'fit'}:
            with self._lock:
                self._pending_config = config
        self.get_logger().info('parameters changed: ' + ', '.join(
            f'{p.name}={p.value}' for p in params))

    def _apply_pending_config(self):
        """Detector thread, both workers idle: hand a changed configuration to the core."""
        with self._lock:
            cfg, self._pending_config = self._pending_config, None
        if cfg is None:
            return
        old = self._config
        if cfg.device != old.device:
            t0 = time.monotonic()
            try:
                rec = self._factory(cfg)
            except Exception as e:  # keep the old core running
                self._report(InputError('reload', f'reloading on device {cfg.device!r} '
                                        f'failed, keeping {old.device!r}: {e}'))
                return
            self._rec, self._body = rec, rec.body
            self.get_logger().info(f'reloaded the core on {rec.device} in '
                                   f'{time.monotonic() - t0:.2f} s')
        elif hasattr(self._rec, 'set_config'):
            self._rec.set_config(cfg)
        else:  # Reconstructor reads .config per frame; the fitter holds its own FitConfig
            self._rec.config = cfg
            if cfg.fit != old.fit and hasattr(self._rec, 'set_fit_config'):
                self._rec.set_fit_config(cfg.fit)
        self._config = cfg
        if old.tracking and not cfg.tracking:
            self._rec.reset()

    # -- problems ------------------------------------------------------------------------
    def _throttled(self, key: str) -> bool:
        """True when a message for `key` may be emitted now (per-key throttle)."""
        now = time.monotonic()
        last = self._throttle.get(key)
        if last is not None and now - last < self._values['warn_throttle_s']:
            return False
        self._throttle[key] = now
        return True

    def _report(self, err: InputError, header=None):
        """Count a problem, warn (throttled per reason) and post a diagnostics entry."""
        reason = getattr(err, 'reason', 'internal')
        with self._lock:
            self._errors[reason] += 1
            count = self._errors[reason]
            self._last_error = (reason, str(err))
        if self._throttled('problem:' + reason):
            where = (f" (frame '{header.frame_id}' at {header.stamp.sec}."
                     f"{header.stamp.nanosec:09d})" if header is not None else '')
            self.get_logger().warning(f'skipped a frame [{reason}]: {err}{where}; '
                                      f'{count} so far')
            status = A.diagnostic_status(
                f'{self.get_name()}: input', A.WARN, f'[{reason}] {err}',
                {'reason': reason, 'count': count, 'frame_id': getattr(header, 'frame_id', '')},
                hardware_id=str(self._rec.device) if hasattr(self, '_rec') else '')
            self._publish_diag([status])

    def _notice(self, reason: str, text: str, header=None):
        """An event that skips no frame (a time jump): counted, warned (throttled per
        reason) and posted on /diagnostics."""
        with self._lock:
            self._notices[reason] += 1
            count = self._notices[reason]
        if self._throttled('notice:' + reason):
            self.get_logger().warning(f'{text}; {count} so far')
            self._publish_diag([A.diagnostic_status(
                f'{self.get_name()}: input', A.WARN, f'[{reason}] {text}',
                {'reason': reason, 'count': count,
                 'frame_id': getattr(header, 'frame_id', '')})])

    def _check_stamp(self, frame: Frame):
        """Detector: say when the stamps jump backwards or far forwards (a bag loop, a clock
        change); the tracks restart on their own (tracking_max_gap_s, track_timeout_s)."""
        prev, self._last_stamp_ns = self._last_stamp_ns, frame.stamp_ns
        if prev is None:
            return
        dt = (frame.stamp_ns - prev) * 1e-9
        if dt < -STAMP_JUMP_BACK_S or dt > STAMP_JUMP_FORWARD_S:
            self._notice('time_jump', f'depth stamps jumped {dt:+.3f} s: tracking restarts, '
                                      'persons get new IDs', frame.header)

    # -- callbacks (executor thread): convert and hand over, nothing more -----------------
    def _on_camera_info(self, msg: CameraInfo):
        fid = msg.header.frame_id
        self._info_time[fid] = time.monotonic()
        try:
            cam = A.camera_info_intrinsics(msg)
        except InputError as e:
            self._camera_infos[fid] = e
            return
        lens = cam.lens(self._sub_depth.topic_name)
        if lens is not None and fid not in self._lens_log:
            undo = lens.undo(self._config.undistort)
            self._lens_log[fid] = 'undistorted' if undo else 'taken as rectified'
            log = self.get_logger()
            (log.info if undo else log.warning)(lens.notice(fid, self._config.undistort))
        self._camera_infos[fid] = (cam, lens)

    def _on_depth(self, msg: Image):
        received = self._depth_time = time.monotonic()
        with self._lock:
            self._stats['received'] += 1
        fid = msg.header.frame_id
        try:
            cam = self._camera_infos.get(fid)
            if cam is None:
                others = ', '.join(f"'{k}'" for k in self._camera_infos) or 'none'
                raise InputError('no_camera_info', (
                    f"no camera_info for frame_id '{fid}' on "
                    f"'{self._sub_info.topic_name}' (camera_info frame_ids seen: {others}); "
                    'depth is not processed until a matching camera_info arrives'))
            if isinstance(cam, InputError):
                raise cam
            cam, lens = cam
            K, (cw, ch) = cam.K, cam.size
            w, h = int(msg.width), int(msg.height)
            if h * w > self._values['max_image_pixels']:
                raise InputError('too_large', f'depth image {w}x{h} has {w * h} pixels, more '
                                 f"than max_image_pixels={self._values['max_image_pixels']}")
            if cw and ch and (cw, ch) != (w, h):
                raise InputError('size_mismatch', f'depth image is {w}x{h} but its '
                                 f'camera_info says {cw}x{ch}')
            depth = A.image_to_depth(msg, max_pixels=self._values['max_image_pixels'])
        except InputError as e:
            self._report(e, msg.header)
            return
        frame = Frame(msg.header, depth, K, stamp_to_ns(msg.header.stamp), received, lens)
        self._mailbox.put(frame)

    # -- worker threads ------------------------------------------------------------------
    def _run_detector(self):
        while not self._stop.is_set():
            with self._lock:
                pending = self._pending_config is not None
            # The slot free (the reconstructor has taken the previous frame), the newest
            # frame is detected so as to be ready when the reconstructor is (its usual
            # time after taking a frame, less a detection's): earlier, the frame would
            # only age in the slot. A new configuration waits for both to be idle.
            if not self._handoff.wait_free(0.1, idle=pending):
                continue
            if pending:
                try:
                    self._apply_pending_config()
                except Exception as e:  # noqa: BLE001 - the node keeps its old settings
                    self._report(InputError('internal', 'applying the new parameters: '
                                            f'{type(e).__name__}: {e}'))
            self._handoff.wait_until(self._handoff.taken + self._stage_s[1] - self._stage_s[0])
            frame = self._handoff.hold(self._mailbox, timeout=0.1)
            if frame is None:
                continue
            if self._stop.is_set():
                self._handoff.release()
                return
            self._check_stamp(frame)
            t0 = time.monotonic()
            try:
                det = self._rec.detect(frame.depth, frame.K, stamp_ns=frame.stamp_ns,
                                       lens=frame.lens)
                self._rec.look_ahead(det)
            except InputError as e:
                self._report(e, frame.header)
                det = None
            except Exception as e:  # noqa: BLE001 - a bad frame must not kill the node
                self._report(InputError('internal', f'{type(e).__name__}: {e}'), frame.header)
                det = None
            if det is None:  # (reported: counted as rejected)
                self._handoff.release()
                continue
            self._stage_time(0, time.monotonic() - t0)
            self._handoff.put((frame, det))

    def _run_worker(self):
        while not self._stop.is_set():
            item = self._handoff.take(timeout=0.1)
            if item is None:
                continue
            t0 = time.monotonic()
            try:
                if not self._stop.is_set():
                    self._reconstruct(*item)
            finally:
                self._stage_time(1, time.monotonic() - t0)
                self._handoff.done()

    def _run_publisher(self):
        while not self._stop.is_set():
            item = self._finishing.take(timeout=0.1)
            if item is None:
                continue
            try:
                if not self._stop.is_set():
                    self._finish(*item)
            finally:
                self._finishing.done()

    def _stage_time(self, stage: int, seconds: float) -> None:
        """Follow the usual time of a detection (0) and a reconstruction (1): the median of
        the last STAGE_FRAMES (the occasional slow frame, a further candidate fitted,
        does not move it)."""
        times = self._stage_times[stage]
        times.append(seconds)
        self._stage_s[stage] = float(np.median(times))

    def _reconstruct(self, frame: Frame, det):
        rec = self._rec
        try:
            result = rec.reconstruct(det, finish=False)
        except InputError as e:
            self._report(e, frame.header)
            return
        except Exception as e:  # noqa: BLE001 - a bad frame must not kill the node
            self._report(InputError('internal', f'{type(e).__name__}: {e}'), frame.header)
            return
        # To the publisher, once it has published the frame before (it is quicker).
        while not self._finishing.wait_free(0.1):
            if self._stop.is_set():
                return
        self._finishing.put((frame, result, rec))

    def _finish(self, frame: Frame, result, rec):
        """Publish the frame's bodies (meshes, skeleton, parameters, IDs, TF: they do not
        wait for the labels), then label it (`Reconstructor.finish`) and publish its
        images (segmentation, body index)."""
        persons = list(result.persons)[:max(1, self._config.max_persons)]
        if not self._guarded(frame, self._publish_bodies, result, persons, frame):
            return
        try:
            result = rec.finish(result)
        except Exception as e:  # noqa: BLE001 - a bad frame must not kill the node
            self._report(InputError('internal', f'{type(e).__name__}: {e}'), frame.header)
            return
        self._guarded(frame, self._publish_images, result, len(persons), frame)

    def _guarded(self, frame: Frame, publish: Callable, *args) -> bool:
        """Run `publish(*args)`; a failure is reported (unless shutting down), not raised."""
        try:
            publish(*args)
            return True
        except Exception as e:  # noqa: BLE001
            if not (self._stop.is_set() or not self.context.ok()):
                self._report(InputError('publish', f'{type(e).__name__}: {e}'), frame.header)
            return False

    def _publish_images(self, result, n: int, frame: Frame):
        """The images of the finished `result`'s first `n` persons (those whose bodies
        were published; finished: with their labelled masks)."""
        persons = list(result.persons)[:n]
        for key, msg in self._outputs.build(result, persons, frame.header, bodies=False):
            self._send(key, msg)

    def _send(self, key: str, msg) -> bool:
        pub = self._pubs.get(key)
        if pub is None:
            return False
        pub.publish(msg)  # rclpy publishers take CDR bytes as they are
        return True

    def _publish_bodies(self, result, persons: list, frame: Frame):
        header = frame.header
        if not persons:
            self._report(InputError('no_person', 'no person found between depth_min='
                                    f'{self._config.depth_min} m and depth_max='
                                    f'{self._config.depth_max} m'), header)
        published = False
        for key, msg in self._outputs.build(result, persons, header, images=False):
            published |= self._send(key, msg)
        published |= bool(self._outputs.opts.publish_segmentation)  # (the images follow)
        now_ns = self.get_clock().now().nanoseconds
        with self._lock:
            self._stats['processed'] += 1
            if published:
                self._stats['published'] += 1
            self._latency_stamp.append((now_ns - frame.stamp_ns) / 1e6)
            self._latency_recv.append((time.monotonic() - frame.received) * 1e3)
            self._timings = dict(result.timings_ms)
            if persons:
                p = persons[0]
                self._last_person = dict(residual_m=float(p.residual_m),
                                         num_points=int(p.num_points),
                                         tracked=bool(getattr(p, 'tracked', False)))
        if self._first_result_s is None and persons:
            self._first_result_s = time.monotonic() - self._t_start
            self.get_logger().info(f'first result {self._first_result_s:.2f} s after start-up '
                                   f'({len(persons)} person(s), '
                                   f"{result.timings_ms.get('total', float('nan')):.0f} ms)")

    # -- diagnostics ---------------------------------------------------------------------
    def _publish_diag(self, statuses):
        msg = A.diagnostics(A.make_header(stamp_ns=self.get_clock().now().nanoseconds),
                            statuses)
        with self._diag_lock:
            self._pub_diag.publish(msg)

    def diagnostics_values(self) -> tuple[int, str, dict[str, Any]]:
        """(level, message, key/values) of the processing summary."""
        now = time.monotonic()
        with self._lock:
            rec, pub = self._stats['received'], self._stats['published']
            t_prev, rec_prev, pub_prev = self._prev
            self._prev = (now, rec, pub)
            dt = max(now - t_prev, 1e-6)
            sp50, sp95, smax = _percentiles(self._latency_stamp)
            rp50, rp95, rmax = _percentiles(self._latency_recv)
            values = {
                'rate_in_hz': (rec - rec_prev) / dt,
                'rate_out_hz': (pub - pub_prev) / dt,
                'frames_received': rec,
                'frames_processed': self._stats['processed'],
                'frames_published': pub,
                'frames_dropped': self._mailbox.dropped,
                'frames_pending': (self._mailbox.pending() + self._handoff.pending()
                                   + self._finishing.pending()),
                'frames_no_camera_info': self._errors['no_camera_info'],
                'frames_rejected': sum(self._errors.values()),
                'latency_stamp_ms_p50': sp50, 'latency_stamp_ms_p95': sp95,
                'latency_stamp_ms_max': smax,
                'latency_receive_ms_p50': rp50, 'latency_receive_ms_p95': rp95,
                'latency_receive_ms_max': rmax,
            }
            values.update({f'time_{k}_ms': t for k, t in self._timings.items()})
            values.update({f'fit_{k}': x for k, x in self._last_person.items()})
            values.update({f'errors_{k}': n for k, n in sorted(self._errors.items())})
            values.update({f'events_{k}': n for k, n in sorted(self._notices.items())})
            now_m = time.monotonic()
            info_age = max((now_m - t for t in self._info_time.values()), default=None)
            values['camera_info_age_s'] = 'none yet' if info_age is None else info_age
            if self._last_error:
                values['last_error'] = f'[{self._last_error[0]}] {self._last_error[1]}'
            errors_now = sum(self._errors.values())
        values.update({
            'model': self._body.name, 'device': str(self._rec.device),
            'net_precision': self._rec.net_precision,
            'tracking': self._config.tracking,
            'time_to_first_result_s': self._first_result_s if self._first_result_s
            is not None else 'none yet',
            'lens_distortion': ', '.join(f'{k}: {v}' for k, v in sorted(self._lens_log.items()))
            or 'none',
        })
        if rec == 0:
            return A.STALE, 'no depth received', values
        age = values['camera_info_age_s']
        if isinstance(age, float) and age > INFO_STALE_S and \
                self._depth_time > max(self._info_time.values()):
            return A.WARN, (f'no camera_info for {age:.1f} s while depth arrives: using the '
                            'last one received'), values
        if values['rate_out_hz'] == 0 and values['rate_in_hz'] > 0:
            return A.WARN, 'receiving depth but publishing nothing', values
        prev_err, self._errors_prev = self._errors_prev, errors_now
        if errors_now > prev_err:
            return A.WARN, f'{errors_now - prev_err} frame(s) rejected in the last period', \
                values
        return A.OK, 'ok', values

    def _publish_diagnostics(self):
        level, message, values = self.diagnostics_values()
        self._publish_diag([A.diagnostic_status(f'{self.get_name()}: processing', level,
                                                message, values,
                                                hardware_id=str(self._rec.device))])

    # -- shutdown ------------------------------------------------------------------------
    def stop(self, timeout: float = 10.0) -> bool:
        """Stop and join the workers (before destroy_node); True when they ended."""
        self._stop.set()
        self._mailbox.wake()
        self._handoff.wake()
        self._finishing.wake()
        end = time.monotonic() + timeout
        threads = (self._detector, self._worker, self._publisher)
        for th in threads:
            if th.is_alive() and threading.current_thread() is not th:
                th.join(max(0.0, end - time.monotonic()))
        return not any(th.is_alive() for th in threads)

    def destroy_node(self):
        self.stop()
        super().destroy_node()


def main(argv: list[str] | None = None) -> int:
    """Console script `reconstructor`.

    Args:
        argv: the command line after the program name (default sys.argv[1:]); ROS
            arguments follow `--ros-args` as with `ros2 run`. `--print-params` prints
            the default parameters as a params file and exits.
    """
    args = ros_args(NODE_NAME, argv)
    if '--print-params' in args[1:args.index('--ros-args') if '--ros-args' in args else None]:
        sys.stdout.write(P.params_yaml())
        return 0
    return run_nodes(NODE_NAME, args, lambda: [ReconstructorNode().tune_process()])


if __name__ == '__main__':
    sys.exit(main())
