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
one-slot mailbox (a newer frame overwrites a stale one, which is counted as dropped); one
worker thread runs `Reconstructor.process` and publishes. ROS entities are created and
destroyed on the main (executor) thread only.

Camera distortion: D is read but the depth image is used as is (no undistortion); a
non-zero D is reported once in the log and in diagnostics.
"""
from __future__ import annotations

import gc
import sys
import threading
import time
from collections import Counter, deque
from dataclasses import dataclass, fields
from typing import Any, Callable

import numpy as np

from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from rcl_interfaces.msg import (FloatingPointRange, IntegerRange, ParameterDescriptor,
                                ParameterType, SetParametersResult)
from diagnostic_msgs.msg import DiagnosticArray
from sensor_msgs.msg import CameraInfo, Image

from smpl_depth_ros.config import FitConfig, PipelineConfig
from smpl_depth_ros.sensor_noise import check_sensor, sensor_choices
from smpl_depth_ros.stamps import stamp_to_ns
from smpl_depth_ros.ros import adapters as A
from smpl_depth_ros.ros.outputs import OUTPUT_PARAMS, TOPICS, FrameOutputs, OutputOptions
from smpl_depth_ros.ros.runner import ros_args, run_nodes
from smpl_depth_ros.types import InputError

NODE_NAME = 'reconstructor'

# Descriptions of the core parameters (PipelineConfig fields, FitConfig as 'fit.<name>').
_CORE_DOC = {
    'backend': "body model backend: 'anny' (shipped) or 'smpl' (your own model file)",
    'model_path': 'SMPL model file or directory (or env SMPL_MODEL_PATH); anny: optional',
    'weights_path': "correspondence network weights ('' = the shipped ones: the broad "
                    'network for stereo sensors, the original for the others)',
    'device': "torch device: 'auto' (CUDA when available), 'cpu' or 'cuda'; a change "
              'reloads the model',
    'depth_min': 'person search range: nearest depth (metres)',
    'depth_max': 'person search range: farthest depth (metres)',
    'max_persons': 'persons reconstructed per frame (most central first)',
    'min_person_pixels': 'smallest person blob (pixels)',
    'flip_tta': 'run the network on each crop and its mirror image and average (twice the '
                'network time; better segmentation and fits)',
    'tracking': 'warm-start from the previous frame while the track holds',
    'max_image_pixels': 'larger depth images are rejected (width x height)',
    'tracking_max_gap_s': 'reset tracking after a longer gap between frame stamps (s)',
    'track_timeout_s': 'a person unseen for longer loses its ID; IDs are never reused (s)',
    'track_gate_m': 'a person keeps its ID within this distance of where it was predicted, '
                    '+0.5 m per second unseen (m)',
    'reject_residual_m': 'person candidates whose fit leaves a larger median residual are '
                         'not reported (m)',
    'sensor': "the depth sensor, whose noise the thresholds scale with: 'auto' (measured "
              "from the frames), a preset (e.g. 'realsense_d435', 'oak_d', "
              "'azure_kinect_nfov', 'kinect_v1') or 'none' (fixed thresholds)",
    'shape_sample_every': 'tracking: every n-th tracked frame also fits the shape; tracked '
                          "frames fit the pose at the mean of these samples (0: keep the "
                          "cold fit's shape)",
    'segmentation': "published labels: 'model' (each person pixel takes the part of its "
                    "nearest fitted vertex) or 'network' (the network's labels as they are)",
    'model_label_margin_m': "'model' segmentation: pixels the network called background "
                            'join the person this close to the fitted mesh (m)',
    'model_label_keep_network_m': "'model' segmentation: a body pixel keeps the network's "
                                  'part when a vertex of it is this close to being its '
                                  'nearest (m; 0 = the fit decides everywhere)',
    'fit.lambda_data': 'fitting: data term weight',
    'fit.lambda_pose': 'fitting: joint-limit prior weight',
    'fit.lambda_pose_l2': 'fitting: pull of every joint towards rest (per rad^2)',
    'fit.lambda_pose_weak': 'fitting: pull of the collars and wrists towards rest (per '
                            'rad^2; joints a depth image hardly observes)',
    'fit.lambda_shape': 'fitting: shape prior weight',
    'fit.gm_sigma': 'fitting: Geman-McClure scale (metres)',
    'fit.gm_sigma_start': 'fitting: cold fits start with this wider scale and anneal to '
                          'gm_sigma (metres)',
    'fit.solver': "fitting solver: 'fast' or 'lbfgs'",
    'fit.iterations': 'fitting: cold-start iterations',
    'fit.tracking_iterations': 'fitting: warm-start iterations while tracking',
    'fit.lambda_temporal': "fitting: tracking's temporal prior, weight (per rad^2) of a "
                           "joint's rotation away from the previous frame's (0 = off)",
    'fit.lbfgs_iterations': 'fitting: L-BFGS iterations',
    'fit.lbfgs_lr': 'fitting: L-BFGS learning rate',
    'fit.max_points': 'fitting: per-vertex targets kept per frame',
    'fit.min_cell_points': 'fitting: drop vertex cells with fewer points (isolated wrong '
                           'correspondences), when typical cells hold twice that',
    'fit.min_joint_support': 'fitting: joints whose rotation moves fewer targets (in '
                             'skinning weight) are held in place (unseen limbs; 0 = off)',
    'fit.complete_hidden': 'fitting: cold fits give those joints their most likely pose '
                           'given the fitted ones (a pose Gaussian learned from the '
                           'synthetic poses), not rest',
    'fit.lost_residual_m': 'fitting: median residual above which the track is lost (m)',
    'fit.icp_rounds': 'fitting: part-constrained nearest-vertex refinements after the '
                      'correspondence fit (0 = none)',
    'fit.icp_margin_m': 'fitting: those refits also take the pixels the network left out '
                        'that lie this close to the fitted mesh (m; 0 = off)',
    'fit.icp_front_cos': 'fitting: the refinements match each pixel (and each pixel the '
                         'network left out) to a vertex facing the camera: cosine of its '
                         'normal and the view ray below this (1 = any)',
    'fit.icp_tangent_weight': 'fitting: weight of the residual along the surface in the '
                              'refits to those nearest-vertex correspondences (0 = point '
                              'to plane, 1 = point to point)',
    'fit.tracking_icp_rounds': 'fitting: the same refinements on tracked frames (on their '
                               'warm fit; 0 = none, faster)',
    'fit.segment_init': 'fitting: cold fits start from per-segment closed-form rotations',
    'fit.flip_restart': 'fitting: cold fits retry turned 180 degrees when the fit is poor',
    'fit.flip_residual_m': 'fitting: median residual that triggers that retry (m)',
}
# Node-only parameters: default, description.
_NODE_PARAMS = {
    'qos_reliability': ('best_effort', "input QoS reliability: 'best_effort' (sensor data) "
                        "or 'reliable' (needed for reliable-only publishers)"),
    'qos_depth': (1, 'input QoS history depth'),
    'cpu_threads': (1, 'torch CPU threads (0 = torch default); 1 is fastest beside a 30 Hz '
                    'DDS stream on a 2-core machine'),
    **OUTPUT_PARAMS,
    'diagnostics_period_s': (1.0, 'period of the /diagnostics summary (s)'),
    'warn_throttle_s': (5.0, 'per-problem throttle of warnings (s)'),
}
READ_ONLY = {'backend', 'model_path', 'weights_path', 'qos_reliability', 'qos_depth',
             'cpu_threads'}
DEVICES = ('auto', 'cpu', 'cuda')
STAMP_JUMP_BACK_S = 0.001    # a depth stamp this far before the previous one is a jump
STAMP_JUMP_FORWARD_S = 60.0  # ... and this far after it
INFO_STALE_S = 2.0           # diagnostics warn when camera_info is older than this
BACKENDS = ('anny', 'smpl')
SOLVERS = ('fast', 'lbfgs')
SEGMENTATIONS = ('model', 'network')
RELIABILITY = {'best_effort': ReliabilityPolicy.BEST_EFFORT,
               'reliable': ReliabilityPolicy.RELIABLE}
_FLOAT_RANGES = {
    'depth_min': (0.0, 100.0), 'depth_max': (0.0, 100.0), 'tracking_max_gap_s': (0.0, 3600.0),
    'track_timeout_s': (0.0, 3600.0), 'track_gate_m': (0.0, 100.0),
    'mesh_decimation': (0.001, 1.0), 'mesh_lifetime_s': (0.0, 3600.0),
    'diagnostics_period_s': (0.05, 3600.0), 'warn_throttle_s': (0.0, 3600.0),
    'fit.gm_sigma': (1e-6, 10.0), 'fit.gm_sigma_start': (1e-6, 10.0),
    'fit.lost_residual_m': (0.0, 10.0), 'fit.min_joint_support': (0.0, 1e6),
    'fit.flip_residual_m': (0.0, 10.0), 'reject_residual_m': (0.0, 10.0),
    'model_label_margin_m': (0.0, 1.0), 'model_label_keep_network_m': (0.0, 1.0),
    'fit.lambda_temporal': (0.0, 1e6), 'fit.icp_tangent_weight': (0.0, 1.0),
    'fit.icp_margin_m': (0.0, 1.0), 'fit.lambda_pose_weak': (0.0, 1e6),
    'fit.icp_front_cos': (-1.0, 1.0),
}
_INT_RANGES = {
    'qos_depth': (1, 1000), 'cpu_threads': (0, 1024), 'max_persons': (1, 100),
    'min_person_pixels': (1, 10_000_000),
    'max_image_pixels': (1, 1 << 30), 'fit.iterations': (0, 10_000),
    'fit.tracking_iterations': (0, 10_000), 'fit.lbfgs_iterations': (0, 10_000),
    'fit.max_points': (1, 10_000_000), 'fit.icp_rounds': (0, 100),
    'fit.min_cell_points': (1, 1_000_000), 'fit.tracking_icp_rounds': (0, 100),
    'shape_sample_every': (0, 1_000_000),
}


def parameter_defaults() -> dict[str, Any]:
    """Every node parameter with its default (from PipelineConfig / FitConfig)."""
    cfg = PipelineConfig()
    out = {f.name: getattr(cfg, f.name) for f in fields(PipelineConfig) if f.name != 'fit'}
    out.update({f'fit.{f.name}': getattr(cfg.fit, f.name) for f in fields(FitConfig)})
    out.update({k: v[0] for k, v in _NODE_PARAMS.items()})
    return out


def _descriptor(name: str, default) -> ParameterDescriptor:
    doc = _CORE_DOC.get(name) or _NODE_PARAMS.get(name, (None, ''))[1] or (
        f'FitConfig.{name[4:]}' if name.startswith('fit.') else f'PipelineConfig.{name}')
    d = ParameterDescriptor(name=name, description=doc, read_only=name in READ_ONLY)
    if isinstance(default, bool):
        d.type = ParameterType.PARAMETER_BOOL
    elif isinstance(default, int):
        d.type = ParameterType.PARAMETER_INTEGER
        if name in _INT_RANGES:
            lo, hi = _INT_RANGES[name]
            d.integer_range = [IntegerRange(from_value=lo, to_value=hi, step=1)]
    elif isinstance(default, float):
        d.type = ParameterType.PARAMETER_DOUBLE
        if name in _FLOAT_RANGES:
            lo, hi = _FLOAT_RANGES[name]
            d.floating_point_range = [FloatingPointRange(from_value=lo, to_value=hi, step=0.0)]
    else:
        d.type = ParameterType.PARAMETER_STRING
    choices = {'backend': BACKENDS, 'device': DEVICES, 'fit.solver': SOLVERS,
               'segmentation': SEGMENTATIONS, 'sensor': sensor_choices(),
               'qos_reliability': tuple(RELIABILITY)}.get(name)
    if choices:
        d.additional_constraints = 'one of: ' + ', '.join(choices)
    if d.read_only:
        d.additional_constraints = (d.additional_constraints + '; ' if
                                    d.additional_constraints else '') + 'needs a restart'
    return d


def _yaml_value(v) -> str:
    if isinstance(v, bool):
        return 'true' if v else 'false'
    if isinstance(v, float):
        r = repr(v)
        if 'e' in r and '.' not in r.split('e')[0]:  # 1e-07 -> 1.0e-07 (a YAML 1.1 float)
            r = r.replace('e', '.0e', 1)
        return r
    if isinstance(v, str):
        return "''" if v == '' else v
    return str(v)


def params_yaml() -> str:
    """The defaults as a `--params-file` (what config/reconstructor.yaml holds):
    `reconstructor --print-params > config/reconstructor.yaml`."""
    defaults = parameter_defaults()
    out = ['# Parameters of the `reconstructor` node (smpl_depth_ros.ros.reconstructor_node),',
           '# generated by `reconstructor --print-params` from PipelineConfig / FitConfig and',
           '# the node defaults (test_reconstructor_node checks that they agree). Keyed `/**:`',
           '# so it survives node renames and namespaces:',
           '#   reconstructor --ros-args --params-file config/reconstructor.yaml -p device:=cpu',
           '/**:', '  ros__parameters:']

    def line(indent: str, key: str, name: str):
        d = _descriptor(name, defaults[name])
        note = d.description + (' [read-only]' if d.read_only else '')
        if d.additional_constraints and not d.read_only:
            note += f' [{d.additional_constraints}]'
        out.append(f'{indent}{key}: {_yaml_value(defaults[name])}  # {note}')

    out.append('    # -- core (PipelineConfig) ' + '-' * 50)
    for name in defaults:
        if '.' not in name and name not in _NODE_PARAMS:
            line('    ', name, name)
    out.append('    fit:  # FitConfig')
    for name in defaults:
        if name.startswith('fit.'):
            line('      ', name[4:], name)
    out.append('    # -- node ' + '-' * 66)
    for name in _NODE_PARAMS:
        line('    ', name, name)
    return '\n'.join(out) + '\n'


def validate(values: dict[str, Any]) -> str | None:
    """Reason why a full set of parameter values is invalid, or None."""
    if values['backend'] not in BACKENDS:
        return f"backend must be one of {BACKENDS}, got '{values['backend']}'"
    if values['device'] not in DEVICES:
        return f"device must be one of {DEVICES}, got '{values['device']}'"
    if values['device'] == 'cuda':
        import torch
        if not torch.cuda.is_available():
            return "device 'cuda' requested but CUDA is not available"
    if values['fit.solver'] not in SOLVERS:
        return f"fit.solver must be one of {SOLVERS}, got '{values['fit.solver']}'"
    if values['segmentation'] not in SEGMENTATIONS:
        return (f'segmentation must be one of {SEGMENTATIONS}, '
                f"got '{values['segmentation']}'")
    if values.get('sensor') is not None and check_sensor(values['sensor']):
        return check_sensor(values['sensor'])
    if values['qos_reliability'] not in RELIABILITY:
        return (f"qos_reliability must be one of {tuple(RELIABILITY)}, "
                f"got '{values['qos_reliability']}'")
    if not values['depth_min'] < values['depth_max']:
        return (f"depth_min ({values['depth_min']}) must be smaller than depth_max "
                f"({values['depth_max']})")
    for name, (lo, hi) in {**_FLOAT_RANGES, **_INT_RANGES}.items():
        v = values.get(name)
        if v is not None and not lo <= v <= hi:
            return f'{name} must be in [{lo}, {hi}], got {v}'
    return None


def config_from_values(values: dict[str, Any]) -> PipelineConfig:
    core = {f.name: values[f.name] for f in fields(PipelineConfig) if f.name != 'fit'}
    fit = FitConfig(**{f.name: values[f'fit.{f.name}'] for f in fields(FitConfig)})
    return PipelineConfig(**core, fit=fit)


# -- the frame hand-off ----------------------------------------------------------------
@dataclass
class Frame:
    """A converted depth frame waiting for the worker."""

    header: Any
    depth: np.ndarray
    K: np.ndarray
    stamp_ns: int
    received: float  # time.monotonic() when the callback got it


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

    def get(self, timeout: float):
        """The newest item (removing it), or None after `timeout` seconds."""
        with self._cv:
            if self._item is None:
                self._cv.wait(timeout)
            item, self._item = self._item, None
            return item

    def pending(self) -> int:
        with self._cv:
            return int(self._item is not None)

    def wake(self):
        with self._cv:
            self._cv.notify_all()


def _percentiles(values) -> tuple[float, float, float]:
    if not values:
        return float('nan'), float('nan'), float('nan')
    a = np.asarray(values, np.float64)
    return float(np.percentile(a, 50)), float(np.percentile(a, 95)), float(a.max())


class ReconstructorNode(Node):
    """Depth -> body mesh + parameters, one worker thread (see the module docstring).

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
        defaults = parameter_defaults()
        self.declare_parameters('', [(n, v, _descriptor(n, v)) for n, v in defaults.items()])
        self._values = {n: self.get_parameter(n).value for n in defaults}
        reason = validate(self._values)
        if reason:
            raise ValueError(f'invalid parameters: {reason}')
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self.add_post_set_parameters_callback(self._after_set_parameters)

        self._lock = threading.Lock()             # stats, pending config
        self._diag_lock = threading.Lock()        # /diagnostics publisher (two threads)
        self._mailbox = Mailbox()
        self._stop = threading.Event()
        self._camera_infos: dict[str, Any] = {}   # frame_id -> (K, D, size) | InputError
        self._info_time: dict[str, float] = {}    # frame_id -> last camera_info (monotonic)
        self._last_stamp_ns: int | None = None    # worker: the previous frame's stamp
        self._depth_time = 0.0                    # last depth message (monotonic)
        self._notices = Counter()                 # events that skip no frame (time jumps)
        self._distortion_warned: set[str] = set()
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

        self._config = config_from_values(self._values)
        if self._values['cpu_threads'] > 0:
            import torch
            torch.set_num_threads(self._values['cpu_threads'])
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
        # The model, network and libraries are loaded for good: move their objects out of
        # the cyclic garbage collector's reach, so that collections triggered by each
        # frame's many small objects stay short (fewer latency spikes).
        gc.collect()
        gc.freeze()
        self._outputs = FrameOutputs(self._body, self._rec.fitter.joint_frames,
                                     OutputOptions.from_values(self._values),
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
        self._worker = threading.Thread(target=self._run_worker, name='reconstructor-worker',
                                        daemon=True)
        self._worker.start()
        log.info(f"listening on '{self._sub_depth.topic_name}' + "
                 f"'{self._sub_info.topic_name}' ({self._values['qos_reliability']}, depth "
                 f"{self._values['qos_depth']})")

    # -- parameters ----------------------------------------------------------------------
    def _on_set_parameters(self, params: list[Parameter]) -> SetParametersResult:
        new = dict(self._values)
        for p in params:
            if p.name in READ_ONLY and p.value != self._values.get(p.name):
                return SetParametersResult(successful=False,
                                           reason=f'{p.name} is read-only: restart the node '
                                                  'to change it')
            if p.name in new:
                new[p.name] = p.value
        reason = validate(new)
        return SetParametersResult(successful=reason is None, reason=reason or '')

    def _after_set_parameters(self, params: list[Parameter]):
        # Runs on the executor thread after a successful change.
        for p in params:
            if p.name in self._values:
                self._values[p.name] = p.value
        names = {p.name for p in params}
        if hasattr(self, '_outputs'):  # (set once the model is loaded)
            self._outputs.opts = OutputOptions.from_values(self._values)
        if 'diagnostics_period_s' in names:
            self._diag_timer.timer_period_ns = int(self._values['diagnostics_period_s'] * 1e9)
        core = {f.name for f in fields(PipelineConfig)} | {
            f'fit.{f.name}' for f in fields(FitConfig)}
        if names & core:
            with self._lock:
                self._pending_config = config_from_values(self._values)
        self.get_logger().info('parameters changed: ' + ', '.join(
            f'{p.name}={p.value}' for p in params))

    def _apply_pending_config(self):
        """Worker thread: hand a changed configuration to the core."""
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
        """Worker: say when the stamps jump backwards or far forwards (a bag loop, a clock
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
            K, D, size = A.camera_info_to_K(msg)
        except InputError as e:
            self._camera_infos[fid] = e
            return
        if D.size and np.any(D != 0) and fid not in self._distortion_warned:
            self._distortion_warned.add(fid)
            self.get_logger().warning(
                f"camera_info for '{fid}' has non-zero distortion ({msg.distortion_model}); "
                'the depth image is used without undistortion')
        self._camera_infos[fid] = (K, D, size)

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
            K, _, (cw, ch) = cam
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
        frame = Frame(msg.header, depth, K, stamp_to_ns(msg.header.stamp), received)
        self._mailbox.put(frame)

    # -- worker thread -------------------------------------------------------------------
    def _run_worker(self):
        while not self._stop.is_set():
            frame = self._mailbox.get(timeout=0.1)
            if frame is None or self._stop.is_set():
                continue
            self._check_stamp(frame)
            try:
                self._apply_pending_config()
                result = self._rec.process(frame.depth, frame.K, stamp_ns=frame.stamp_ns)
            except InputError as e:
                self._report(e, frame.header)
                continue
            except Exception as e:  # noqa: BLE001 - a bad frame must not kill the node
                self._report(InputError('internal', f'{type(e).__name__}: {e}'), frame.header)
                continue
            try:
                self._publish_result(result, frame)
            except Exception as e:  # noqa: BLE001
                if self._stop.is_set() or not self.context.ok():
                    return
                self._report(InputError('publish', f'{type(e).__name__}: {e}'), frame.header)

    def _publish_result(self, result, frame: Frame):
        header = frame.header
        persons = list(result.persons)[:max(1, self._config.max_persons)]
        if not persons:
            self._report(InputError('no_person', 'no person found between depth_min='
                                    f'{self._config.depth_min} m and depth_max='
                                    f'{self._config.depth_max} m'), header)
        published = False
        for key, msg in self._outputs.build(result, persons, header):
            pub = self._pubs.get(key)
            if pub is not None:
                pub.publish(msg)  # rclpy publishers take CDR bytes as they are
                published = True
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
                'frames_pending': self._mailbox.pending(),
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
            'tracking': self._config.tracking,
            'time_to_first_result_s': self._first_result_s if self._first_result_s
            is not None else 'none yet',
            'distortion_ignored_for': ', '.join(sorted(self._distortion_warned)) or 'none',
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
        """Stop and join the worker (before destroy_node); True when it ended."""
        self._stop.set()
        self._mailbox.wake()
        if self._worker.is_alive() and threading.current_thread() is not self._worker:
            self._worker.join(timeout)
        return not self._worker.is_alive()

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
        sys.stdout.write(params_yaml())
        return 0
    return run_nodes(NODE_NAME, args, lambda: [ReconstructorNode()])


if __name__ == '__main__':
    sys.exit(main())
