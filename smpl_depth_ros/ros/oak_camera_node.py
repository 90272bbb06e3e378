"""The `oak_camera` node: live depth from a Luxonis OAK (depthai 3.x), and `reconstruct_oak`.

Topics (relative names, remappable):
    publishes   depth/image_raw (sensor_msgs/Image 16UC1, millimetres, 0 = invalid)
                depth/camera_info (sensor_msgs/CameraInfo: the device calibration at the
                published size; same header as the image)

Stamps are the capture times from the device clock mapped to ROS time (`oak.ClockMapper`);
frame_id is the `frame_id` parameter. The device is opened at start-up: none found ->
one error line and exit code 1 (unless `wait_for_device`). A device lost while running
is logged and reopened with exponential backoff; publishing resumes when it is back.

Threading: a driver thread blocks on the device queue, converts each frame to an array
(capture stamp mapped to ROS time) and drops it into a one-slot hand-off (newest wins, dropped
frames counted); a guard condition wakes the executor, which builds the messages and
publishes them. ROS entities are created and destroyed on the main thread only.

`reconstruct_oak` runs this node and the `reconstructor` node in one process on one
MultiThreadedExecutor; the camera hands its message objects straight to the
reconstructor's depth/camera_info callbacks (no serialisation) and still publishes them.
"""
from __future__ import annotations

import os

# Before depthai is imported: its start-up warnings (e.g. 'USB protocol not available')
# would otherwise precede our own one-line error. DEPTHAI_LEVEL=warn shows them again.
os.environ.setdefault('DEPTHAI_LEVEL', 'error')

import sys  # noqa: E402
import threading  # noqa: E402
import time  # noqa: E402
from dataclasses import dataclass  # noqa: E402
from typing import Any, Callable  # noqa: E402

import numpy as np  # noqa: E402

from rclpy.executors import MultiThreadedExecutor  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy  # noqa: E402
from rcl_interfaces.msg import SetParametersResult  # noqa: E402
from sensor_msgs.msg import CameraInfo, Image  # noqa: E402

from smpl_depth_ros.config import param  # noqa: E402
from smpl_depth_ros.params import build_schema, check_declared  # noqa: E402
from smpl_depth_ros.ros import adapters as A  # noqa: E402
from smpl_depth_ros.ros import oak, oak_device  # noqa: E402
from smpl_depth_ros.ros.parameters import declare  # noqa: E402
from smpl_depth_ros.ros.runner import ros_args, run_nodes  # noqa: E402

NODE_NAME = 'oak_camera'
DEPTH_TOPIC = 'depth/image_raw'
INFO_TOPIC = 'depth/camera_info'

RELIABILITY = {'best_effort': ReliabilityPolicy.BEST_EFFORT,
               'reliable': ReliabilityPolicy.RELIABLE}


@dataclass(frozen=True)
class OakNodeOptions:
    """The node's own parameters (beside the camera's, `oak.OakConfig`)."""

    frame_id: str = param('oak_depth_optical_frame', 'frame_id of the published header')
    publisher_reliability: str = param('reliable', "QoS reliability of the publishers: "
                                       "'reliable' (serves reliable and best-effort "
                                       "subscribers) or 'best_effort'",
                                       choices=tuple(RELIABILITY), restart=True)
    warn_throttle_s: float = param(5.0, 'per-problem throttle of warnings (s)',
                                   range=(0.0, 3600.0))


SCHEMA = build_schema({'camera': oak.OakConfig, 'node': OakNodeOptions})


def parameter_defaults() -> dict[str, Any]:
    """Every node parameter with its default."""
    return {n: p.default for n, p in SCHEMA.items()}


def validate(values: dict[str, Any]) -> str | None:
    """Why a full set of parameter values is invalid, or None."""
    reason = check_declared(SCHEMA, values)
    if reason:
        return reason
    if not str(values['frame_id']).strip():
        return 'frame_id must not be empty'
    return oak.validate(oak.config_from_dict(values))


ConnectionFactory = Callable[[str, float], Any]


class OakCameraNode(Node):
    """Publishes OAK stereo depth + camera info (see the module docstring).

    Args:
        connection_factory: ``(device_id, timeout_s) -> connection`` (default
            `oak_device.open_connection` with this node's OakConfig); tests pass host-made
            connections.
        **kwargs: passed to rclpy's Node (context, parameter_overrides, cli_args ...).

    Raises:
        oak_device.DeviceNotFoundError: no device at start-up (and not `wait_for_device`).
        ValueError: invalid parameters.
    """

    def __init__(self, connection_factory: ConnectionFactory | None = None, **kwargs):
        super().__init__(NODE_NAME, **kwargs)
        self._values = declare(self, SCHEMA)
        reason = validate(self._values)
        if reason:
            raise ValueError(f'invalid parameters: {reason}')
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self.add_post_set_parameters_callback(self._after_set_parameters)
        self.cfg = oak.config_from_dict(self._values)
        self._frame_id = str(self._values['frame_id'])

        self._lock = threading.Lock()
        self._pending = None            # (DepthFrame, K, D): the one-slot hand-off
        self._sinks: list[Callable[[Image, CameraInfo], Any]] = []
        self._throttle: dict[str, float] = {}
        self._intrinsics: dict[tuple, tuple[np.ndarray, np.ndarray]] = {}
        self._checked_connections: set[int] = set()
        self.published = 0
        self.dropped = 0
        self.last_stamp_ns: int | None = None

        qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=2,
                         reliability=RELIABILITY[self._values['publisher_reliability']])
        self._pub_depth = self.create_publisher(Image, DEPTH_TOPIC, qos)
        self._pub_info = self.create_publisher(CameraInfo, INFO_TOPIC, qos)
        self._wake = self.create_guard_condition(self._publish_pending)
        self._mapper = oak.ClockMapper(lambda: self.get_clock().now().nanoseconds)

        cfg = self.cfg
        self._open = connection_factory or (
            lambda device_id, timeout_s: oak_device.open_connection(cfg, device_id, timeout_s))
        connection = None
        if not cfg.wait_for_device:
            connection = self._open(cfg.device_id, cfg.connect_timeout_s)  # raises: no device
            self._log_connected(connection)
        else:
            self.get_logger().info('waiting for ' + (f"OAK device '{cfg.device_id}'" if
                                                     cfg.device_id else 'an OAK device'))
        self._driver = oak_device.OakDriver(cfg, connection, self._on_frame, self._on_event,
                                            reopen=lambda dev: self._open(dev, 0.0))
        self._driver.start()

    # -- public --------------------------------------------------------------------------
    def add_sink(self, sink: Callable[[Image, CameraInfo], Any]):
        """Also hand every published (image, camera_info) pair to `sink` (executor thread,
        the same message objects that were published)."""
        self._sinks.append(sink)

    @property
    def driver(self) -> oak_device.OakDriver:
        return self._driver

    def stop(self, timeout: float = 5.0) -> bool:
        """Stop the driver thread and close the device; True when it ended."""
        return self._driver.stop(timeout)

    def destroy_node(self):
        self.stop()
        super().destroy_node()

    # -- parameters ----------------------------------------------------------------------
    def _on_set_parameters(self, params: list[Parameter]) -> SetParametersResult:
        new = dict(self._values)
        for p in params:
            if p.name in new:
                new[p.name] = p.value
        reason = validate(new)
        return SetParametersResult(successful=reason is None, reason=reason or '')

    def _after_set_parameters(self, params: list[Parameter]):
        for p in params:
            if p.name in self._values:
                self._values[p.name] = p.value
        self._frame_id = str(self._values['frame_id'])

    # -- logging -------------------------------------------------------------------------
    def _throttled(self, key: str) -> bool:
        now = time.monotonic()
        last = self._throttle.get(key)
        if last is not None and now - last < self._values['warn_throttle_s']:
            return False
        self._throttle[key] = now
        return True

    @property
    def sensor_preset(self) -> str:
        """The depth-noise preset of the open camera (`oak.sensor_preset`)."""
        opened = self._driver.connection
        return oak.sensor_preset(self.cfg, getattr(opened, 'description', ''))

    def _log_connected(self, connection):
        cfg = self.cfg
        align = 'CAM_A (colour)' if cfg.align_to_color else 'rectified CAM_C'
        self.get_logger().info(
            f"opened {getattr(connection, 'description', 'OAK')}: {cfg.width}x{cfg.height} at "
            f"{cfg.fps:g} fps, preset {cfg.preset}, depth in {align} view, range "
            f"{cfg.min_range:g}-{cfg.max_range:g} m; publishing '{self._pub_depth.topic_name}'"
            f" + '{self._pub_info.topic_name}' as '{self._frame_id}'")

    def _on_event(self, kind: str, message: str, info: dict):
        """Driver-thread events (see oak_device.OakDriver)."""
        if not self.context.ok():  # shutting down: rosout is gone
            return
        log = self.get_logger()
        dev = info.get('device_id')
        what = f"OAK device '{dev}'" if dev else 'OAK device'
        if kind == 'lost':
            log.error(f'{what} lost ({message}); reconnecting, first try in '
                      f'{self.cfg.reconnect_backoff_s:g} s')
        elif kind == 'retry':
            if self._throttled('retry'):
                log.warning(f"{what} not available yet (attempt {info['attempt']}, next in "
                            f"{info['delay_s']:g} s): {message.split(': ', 1)[-1]}")
        elif kind == 'reconnected':
            self._intrinsics.clear()
            log.info(f"{what} reconnected after {info['outage_s']:.1f} s "
                     f"({info['attempts']} attempt(s)); publishing again")
        elif kind == 'connected':
            self._log_connected(self._driver.connection)
        elif kind == 'frame_error':
            if self._throttled('frame_error'):
                log.warning(f'skipped a depth frame: {message}')

    # -- driver thread: convert and hand over ----------------------------------------------
    def _camera_model(self, connection, size: tuple[int, int]):
        key = (id(connection), size)
        got = self._intrinsics.get(key)
        if got is None:
            got = oak.intrinsics(connection.calibration, oak.depth_socket(self.cfg), size)
            if len(self._intrinsics) > 8:
                self._intrinsics.clear()
            self._intrinsics[key] = got
        return got

    def _check_frame_intrinsics(self, frame, connection, K: np.ndarray):
        """Once per connection: warn when the frame's own intrinsics disagree with the
        calibration's (a hint that the published K does not fit the image)."""
        if id(connection) in self._checked_connections:
            return
        self._checked_connections.add(id(connection))
        Kf = oak.frame_intrinsics(frame)
        if Kf is None:
            return
        rel = np.abs(Kf[:2] - K[:2]).max() / max(K[0, 0], 1.0)
        if rel > 0.01:
            self.get_logger().warning(
                f'the depth frame carries intrinsics fx={Kf[0, 0]:.1f} fy={Kf[1, 1]:.1f} '
                f'cx={Kf[0, 2]:.1f} cy={Kf[1, 2]:.1f}, the calibration gives fx={K[0, 0]:.1f}'
                f' fy={K[1, 1]:.1f} cx={K[0, 2]:.1f} cy={K[1, 2]:.1f}; publishing the '
                'calibration\'s')

    def _on_frame(self, frame, connection):
        depth = oak.frame_to_depth(frame, self._mapper, self.cfg.min_range,
                                   self.cfg.max_range)
        K, D = self._camera_model(connection, depth.size)
        self._check_frame_intrinsics(frame, connection, K)
        with self._lock:
            if self._pending is not None:
                self.dropped += 1
            self._pending = (depth, K, D)
        self._wake.trigger()

    # -- executor thread: build, publish, hand to sinks ------------------------------------
    def _publish_pending(self):
        with self._lock:
            item, self._pending = self._pending, None
        if item is None:
            return
        depth, K, D = item
        header = A.make_header(stamp_ns=depth.stamp_ns, frame_id=self._frame_id)
        image = depth_image_msg(depth, header)
        info = A.camera_info_msg(K, depth.size, header, D=D)
        self._pub_info.publish(info)
        self._pub_depth.publish(image)
        for sink in self._sinks:
            sink(image, info)
        self.published += 1
        self.last_stamp_ns = depth.stamp_ns


def depth_image_msg(depth: oak.DepthFrame, header) -> Image:
    """16UC1 millimetre Image of a DepthFrame (through the shared adapter)."""
    return A.depth_mm_to_image_msg(depth.depth_mm, header)


# -- entry points ----------------------------------------------------------------------
def _describe_startup_error(e: Exception) -> str:
    return str(e) if isinstance(e, (oak_device.DeviceNotFoundError, ValueError)) else \
        f'{type(e).__name__}: {e}'


def main(argv: list[str] | None = None) -> int:
    """Console script `oak_camera`.

    Args:
        argv: the command line after the program name (default sys.argv[1:]); ROS
            arguments follow `--ros-args` as with `ros2 run`.
    """
    return run_nodes(NODE_NAME, ros_args(NODE_NAME, argv), lambda: [OakCameraNode()],
                     describe=_describe_startup_error)


def feed_reconstructor(reconstructor) -> Callable[[Image, CameraInfo], None]:
    """A camera sink that hands the message objects straight to a ReconstructorNode's
    camera_info and depth callbacks (no serialisation)."""
    def sink(image: Image, info: CameraInfo):
        reconstructor._on_camera_info(info)
        reconstructor._on_depth(image)
    return sink


def make_reconstruct_oak(connection_factory: ConnectionFactory | None = None,
                         reconstructor_factory=None, **node_kwargs):
    """(camera, reconstructor) nodes wired for `reconstruct_oak` (not yet spinning).

    The camera is opened first, so a missing device fails before the models load.
    """
    from smpl_depth_ros.ros.reconstructor_node import ReconstructorNode

    camera = OakCameraNode(connection_factory=connection_factory, **node_kwargs)
    try:
        rec = ReconstructorNode(reconstructor_factory=reconstructor_factory, **node_kwargs)
    except BaseException:
        camera.destroy_node()
        raise
    camera.add_sink(feed_reconstructor(rec))
    rec.get_logger().info(f"fed directly by '{camera.get_fully_qualified_name()}' (the "
                          'published message objects, no serialisation); its own '
                          'subscriptions stay open to other publishers')
    tell_sensor(camera, rec)
    return camera, rec


def tell_sensor(camera: OakCameraNode, rec) -> None:
    """Give the reconstructor the camera's depth-noise preset (its `sensor` parameter),
    unless it was set to something other than 'auto'."""
    if rec.get_parameter('sensor').value != 'auto':
        return
    name = camera.sensor_preset
    result = rec.set_parameters([Parameter('sensor', Parameter.Type.STRING, name)])[0]
    if result.successful:
        rec.get_logger().info(f"sensor '{name}' (the OAK's depth noise; "
                              "-p sensor:=auto to measure it from the frames instead)")


def main_with_reconstructor(argv: list[str] | None = None) -> int:
    """Console script `reconstruct_oak`: oak_camera + reconstructor in one process.

    Both nodes read the same command line (`--ros-args -p ...`, `--params-file ...`); their
    parameter names do not overlap except warn_throttle_s.
    """
    name = 'reconstruct_oak'
    def make_nodes():
        camera, rec = make_reconstruct_oak()
        return camera, rec.tune_process()

    return run_nodes(name, ros_args(name, argv), make_nodes,
                     executor_factory=lambda: MultiThreadedExecutor(num_threads=2),
                     describe=_describe_startup_error)


if __name__ == '__main__':
    sys.exit(main())
