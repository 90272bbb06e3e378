"""The reconstructor node over real DDS (loopback, localhost-only discovery; conftest.py).

Two ways of running the node, both with the real core (`smpl_depth_ros.pipeline`):
* in-process: `ReconstructorNode` on an executor thread, in the test's own rclpy context,
  with the real Reconstructor shared across tests (loaded once) through a thin wrapper
  that can add a delay (the deliberately slow worker) and counts resets;
* a subprocess started like `ros2 run` would: the `reconstructor` console script (or
  `python -m smpl_depth_ros.ros.reconstructor_node` when the package is not installed)
  with `--ros-args -p ... --params-file config/reconstructor.yaml`, stopped by SIGINT.

Frames come from `synth.dataset.make_sequence` (in-process tests) and from a bag written
by the `synth_bag` tool (played to the subprocess as raw CDR, bag stamps kept): the body
model posed, placed in a room and ray-cast with sensor noise, so the ground-truth mesh is
known exactly.
"""
from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import torch

rclpy = pytest.importorskip('rclpy')

from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.parameter import Parameter, parameter_value_to_python  # noqa: E402
from rclpy.qos import QoSProfile, ReliabilityPolicy  # noqa: E402
from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from sensor_msgs.msg import CameraInfo, Image, JointState  # noqa: E402
from visualization_msgs.msg import Marker, MarkerArray  # noqa: E402

from smpl_depth_ros.config import FitConfig, PipelineConfig  # noqa: E402
from smpl_depth_ros.ros import adapters as A  # noqa: E402
from smpl_depth_ros.ros import body_msgs, markers  # noqa: E402
from smpl_depth_ros.ros.reconstructor_node import ReconstructorNode  # noqa: E402
from smpl_depth_ros.stamps import stamp_to_ns  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
PARAMS_FILE = REPO / 'config' / 'reconstructor.yaml'
FRAME = 'camera_depth_optical_frame'
OUTPUTS = {'mesh': Marker, 'segmentation': Image, 'segmentation/labels': Image,
           'smpl_params': JointState, 'skeleton': MarkerArray, 'meshes': MarkerArray,
           'bodies/params': JointState, 'bodies/tracked': JointState, 'bodies/index': Image}


# -- synthetic frames ------------------------------------------------------------------
class Scene:
    """A synthetic sequence (`synth.dataset.make_sequence`: one person moving in a room,
    sensor noise, kinect_v1-like camera): depth frames + ground-truth vertices."""

    def __init__(self, body, frames: int = 4, seed: int = 3):
        from smpl_depth_ros.synth.camera import get_camera
        from smpl_depth_ros.synth.dataset import make_sequence
        from smpl_depth_ros.synth.poses import PoseSampler

        self.camera = get_camera('kinect_v1')
        seq = list(make_sequence(body, PoseSampler(body), np.random.default_rng(seed),
                                 self.camera, frames))
        self.K = seq[0]['K']
        self.depth = [f['depth'] for f in seq]
        self.vertices = [np.asarray(f['vertices'], np.float64) for f in seq]
        self.body_mask = [f['labels'] > 0 for f in seq]

    def depth_msg(self, i: int, stamp_ns: int, frame_id: str = FRAME,
                  encoding: str = '16UC1') -> Image:
        return A.depth_to_image_msg(self.depth[i % len(self.depth)],
                                    A.make_header(stamp_ns=stamp_ns, frame_id=frame_id),
                                    encoding)

    def info_msg(self, frame_id: str = FRAME, K=None, size=None) -> CameraInfo:
        return A.camera_info_msg(self.K if K is None else K,
                                 size or (self.camera.width, self.camera.height),
                                 A.make_header(frame_id=frame_id))


def mesh_vertices(marker: Marker, faces: np.ndarray, num_vertices: int) -> np.ndarray:
    """(V, 3) vertices back from a full TRIANGLE_LIST (3 points per face, in order)."""
    pts = np.array([[p.x, p.y, p.z] for p in marker.points])
    v = np.full((num_vertices, 3), np.nan)
    v[faces.reshape(-1)] = pts
    return v


# -- the real core, shared -------------------------------------------------------------
class Core:
    """The real Reconstructor behind the node's factory: optional delay before each
    frame's reconstruction (a deliberately slow worker), counts of calls and resets."""

    def __init__(self, rec, delay: float = 0.0):
        self._rec = rec
        self.delay = delay
        self.finish_delay = 0.0  # before each frame's labels (a deliberately slow labeller)
        self.calls = 0
        self.resets = 0
        self.busy = False
        self.durations: list[float] = []  # wall time of each frame's reconstruction (s)

    @property
    def body(self):
        return self._rec.body

    @property
    def device(self):
        return self._rec.device

    @property
    def config(self):
        return self._rec.config

    @config.setter
    def config(self, cfg):
        self._rec.config = cfg

    def __getattr__(self, name):  # set_config and anything else the node may use
        return getattr(self._rec, name)

    def detect(self, depth, K, stamp_ns=None, lens=None):
        return self._rec.detect(depth, K, stamp_ns=stamp_ns, lens=lens)

    def reconstruct(self, det, finish=True):
        self.busy = True
        t0 = time.monotonic()
        try:
            if self.delay:
                time.sleep(self.delay)
            self.calls += 1
            return self._rec.reconstruct(det, finish=finish)
        finally:
            self.durations.append(time.monotonic() - t0)
            self.busy = False

    def finish(self, result):
        if self.finish_delay:
            time.sleep(self.finish_delay)
        return self._rec.finish(result)

    def process(self, depth, K, stamp_ns=None, lens=None):
        return self.reconstruct(self.detect(depth, K, stamp_ns, lens))

    def reset(self):
        self.resets += 1
        self._rec.reset()


@pytest.fixture(scope='module')
def real_core():
    pipeline = pytest.importorskip('smpl_depth_ros.pipeline',
                                   reason='the core pipeline has not landed yet')
    rec = pipeline.Reconstructor(PipelineConfig(device='cpu'))
    return rec, rec.config if hasattr(rec, 'config') else None


@pytest.fixture(scope='module')
def scene(real_core):
    return Scene(real_core[0].body)


@pytest.fixture
def core(real_core):
    rec, cfg0 = real_core
    core = Core(rec)
    yield core
    if cfg0 is not None:
        if hasattr(rec, 'set_config'):
            rec.set_config(cfg0)
        else:
            rec.config = cfg0
            if hasattr(rec, 'set_fit_config'):
                rec.set_fit_config(cfg0.fit)
    rec.reset()


# -- a test-side node: publishes frames, collects every output ------------------------
def wait_for(pred, timeout: float, step: float = 0.02) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if pred():
            return True
        time.sleep(step)
    return bool(pred())


class Probe:
    """Publishes depth/camera_info into `ns` and records the node's outputs."""

    def __init__(self, context, ns: str, node_name: str = 'reconstructor'):
        self.node = rclpy.create_node('tester', context=context)
        self.lock = threading.Lock()
        self.got: dict[str, list] = {k: [] for k in OUTPUTS}
        self.got['diagnostics'] = []
        rel = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE)
        self.pub_depth = self.node.create_publisher(Image, f'{ns}/depth', rel)
        self.pub_info = self.node.create_publisher(CameraInfo, f'{ns}/camera_info', rel)
        for name, typ in OUTPUTS.items():
            self.node.create_subscription(typ, f'{ns}/{node_name}/{name}',
                                          self._keep(name), rel)
        self.node.create_subscription(DiagnosticArray, '/diagnostics',
                                      self._keep('diagnostics'), QoSProfile(depth=200))
        self.infos: list[CameraInfo] = []
        self.node.create_timer(0.05, self._send_infos)  # like a camera: 20 Hz camera_info

    def _keep(self, name):
        def cb(msg):
            with self.lock:
                self.got[name].append((time.monotonic(), msg))
        return cb

    def _send_infos(self):
        for m in list(self.infos):
            self.pub_info.publish(m)

    def count(self, name: str) -> int:
        with self.lock:
            return len(self.got[name])

    def msgs(self, name: str) -> list:
        with self.lock:
            return [m for _, m in self.got[name]]

    def clear(self):
        with self.lock:
            for v in self.got.values():
                v.clear()

    def now_ns(self) -> int:
        return self.node.get_clock().now().nanoseconds

    def wait_connected(self, timeout: float = 20.0):
        assert wait_for(lambda: self.pub_depth.get_subscription_count() > 0 and
                        self.pub_info.get_subscription_count() > 0, timeout), \
            'the node never subscribed to depth / camera_info'

    def with_stamp(self, name: str, stamp_ns: int) -> list:
        return [m for m in self.msgs(name) if stamp_to_ns(_header(m).stamp) == stamp_ns]

    def problems(self) -> list[tuple[str, str]]:
        """(reason, message) of every input-problem diagnostics entry so far."""
        out = []
        for arr in self.msgs('diagnostics'):
            for s in arr.status:
                if s.name.endswith(': input'):
                    out.append((A.diagnostic_values(s)['reason'], s.message))
        return out

    def summary(self) -> dict[str, str] | None:
        """Key/values of the newest processing summary on /diagnostics."""
        for arr in reversed(self.msgs('diagnostics')):
            for s in arr.status:
                if s.name.endswith(': processing'):
                    return A.diagnostic_values(s)
        return None


def _header(m):
    return m.markers[0].header if isinstance(m, MarkerArray) else m.header


class Spinner:
    """Spins nodes of one context on a background thread."""

    def __init__(self, context, *nodes):
        self.executor = SingleThreadedExecutor(context=context)
        for n in nodes:
            self.executor.add_node(n)
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()

    def _spin(self):
        try:
            self.executor.spin()
        except Exception:  # context shut down under us at teardown
            pass

    def add(self, node):
        self.executor.add_node(node)

    def close(self):
        self.executor.shutdown(timeout_sec=2.0)
        self.thread.join(5.0)


@pytest.fixture
def harness(rclpy_context, core, scene):
    """make(tune=True, **params) -> (node, tester); the node runs in-process under
    namespace /ip, with the process settings the console script gives it (tune_process:
    torch threads, gc.freeze) unless `tune` is False."""
    made = []
    spinner = Spinner(rclpy_context)

    def make(tune: bool = True, **params):
        overrides = [Parameter(k, value=v) for k, v in params.items()]
        node = ReconstructorNode(reconstructor_factory=lambda cfg: core, context=rclpy_context,
                                 namespace='/ip', parameter_overrides=overrides)
        if tune:
            node.tune_process()
        tester = Probe(rclpy_context, '/ip')
        tester.infos.append(scene.info_msg())
        spinner.add(node)
        spinner.add(tester.node)
        made.extend([node, tester.node])
        tester.wait_connected()
        assert wait_for(lambda: FRAME in node._camera_infos, 10.0), 'camera_info not received'
        return node, tester

    yield make
    for n in made:
        if isinstance(n, ReconstructorNode):
            assert n.stop(), 'worker did not stop'
    spinner.close()
    for n in made:
        n.destroy_node()


def send_until(tester: Probe, scene: Scene, name: str, timeout: float, index: int = 0,
               period: float = 0.5) -> int:
    """Publish frames every `period` s until `name` arrives for one of them; its stamp."""
    end = time.monotonic() + timeout
    stamps = []
    while time.monotonic() < end:
        stamps.append(tester.now_ns())
        tester.pub_depth.publish(scene.depth_msg(index, stamps[-1]))
        t_next = time.monotonic() + period
        while time.monotonic() < t_next:
            for s in stamps:
                if tester.with_stamp(name, s):
                    return s
            time.sleep(0.02)
    raise AssertionError(f'no {name} output within {timeout} s')


# -- in-process tests ------------------------------------------------------------------
def test_outputs_copy_header_and_match_model(harness, core, scene):
    node, tester = harness()
    stamp = send_until(tester, scene, 'mesh', 30.0)
    for name in OUTPUTS:
        assert wait_for(lambda: tester.with_stamp(name, stamp), 5.0), f'no {name} output'
        for m in tester.with_stamp(name, stamp):
            assert _header(m).frame_id == FRAME
            if isinstance(m, MarkerArray):
                assert all(mk.header.frame_id == FRAME for mk in m.markers)
    body = core.body
    mesh = tester.with_stamp('mesh', stamp)[0]
    assert mesh.type == Marker.TRIANGLE_LIST
    assert len(mesh.points) == 3 * len(body.faces)
    seg, lab = tester.with_stamp('segmentation', stamp)[0], \
        tester.with_stamp('segmentation/labels', stamp)[0]
    assert (seg.encoding, seg.width, seg.height) == ('rgb8', scene.camera.width,
                                                    scene.camera.height)
    assert (lab.encoding, lab.width, lab.height) == ('mono8', scene.camera.width,
                                                    scene.camera.height)
    labels = A.image_to_array(lab)
    body_px = scene.body_mask[0]
    # Most body pixels get a body-part label; the background mostly stays background.
    assert (labels[body_px] > 0).mean() > 0.7
    assert (labels[~body_px] == 0).mean() > 0.95
    params = body_msgs.joint_state_to_params(tester.with_stamp('smpl_params', stamp)[0])
    assert params['joint_names'] == tuple(body.joint_names[1:])
    assert params['shape_names'] == tuple(body.shape_names)
    assert params['pose'].shape == (body.num_pose_joints, 3)
    skel = tester.with_stamp('skeleton', stamp)[0]
    kinds = sorted(mk.type for mk in skel.markers)
    assert kinds == sorted([Marker.SPHERE_LIST, Marker.LINE_LIST])
    joints = next(mk for mk in skel.markers if mk.type == Marker.SPHERE_LIST)
    assert len(joints.points) == len(body.joint_names)


def test_bodies_are_published_before_the_labels_are_made(harness, core, scene):
    """A frame's meshes, parameters, IDs (and TF) go out as soon as its fits are done; its
    segmentation and body index follow once the labels are made: with labelling slowed
    by 0.8 s, the frame's ~/bodies/tracked arrives that much before its ~/bodies/index,
    and both carry the frame's stamp."""
    core.finish_delay = 0.8
    node, tester = harness()
    stamp = send_until(tester, scene, 'bodies/index', 30.0)
    arrived = {}
    with tester.lock:
        for name in ('bodies/tracked', 'bodies/params', 'meshes', 'bodies/index',
                     'segmentation'):
            t = [t for t, m in tester.got[name] if stamp_to_ns(_header(m).stamp) == stamp]
            assert t, name
            arrived[name] = t[0]
    for name in ('bodies/tracked', 'bodies/params', 'meshes'):
        assert arrived['bodies/index'] - arrived[name] > 0.5, (name, arrived)
    assert abs(arrived['segmentation'] - arrived['bodies/index']) < 0.3


def test_two_people_keep_their_ids_and_a_person_leaving_is_deleted(harness, core, scene):
    """Two people walking in view (synth.dataset.make_multi_sequence), then one of them
    gone: every output carries the track IDs, which stay the same; the tracked list, the
    ID-prefixed parameters and the body index image agree; the person who left gets
    DELETE markers."""
    from smpl_depth_ros.synth.dataset import make_multi_sequence
    from smpl_depth_ros.synth.poses import PoseSampler
    body = core.body
    frames = list(make_multi_sequence(body, PoseSampler(body), np.random.default_rng(5),
                                      scene.camera, 6, 2))
    gone = frames[-1]['person_index'] == 1  # the last frame without the second person
    frames.append(dict(frames[-1], depth=np.where(gone, 0, frames[-1]['depth'])))
    node, tester = harness(max_persons=3)
    core.set_config(core.config.with_overrides(max_persons=3))  # the shared core
    got = []
    t0 = tester.now_ns()
    for i, f in enumerate(frames):
        # A 30 Hz stream's stamps: tracks time out by stamps, so how long this machine
        # takes per frame must not decide whether an ID is kept.
        stamp = t0 + i * 33_333_333
        msg = A.depth_to_image_msg(f['depth'], A.make_header(stamp_ns=stamp, frame_id=FRAME),
                                   '16UC1')
        tester.pub_depth.publish(msg)
        assert wait_for(lambda: all(tester.with_stamp(k, stamp) for k in (
            'bodies/tracked', 'bodies/params', 'bodies/index', 'meshes', 'skeleton')),
            30.0), f'frame {i}: no outputs'
        got.append({k: tester.with_stamp(k, stamp)[0] for k in (
            'bodies/tracked', 'bodies/params', 'bodies/index', 'meshes', 'skeleton')})
    ids = [[str(n) for n in g['bodies/tracked'].name] for g in got]
    assert all(len(x) == 2 for x in ids[:-1]) and len(ids[-1]) == 1, ids
    assert all(sorted(x) == sorted(ids[0]) for x in ids[1:-1]), ids  # stable
    left = (set(ids[0]) - set(ids[-1])).pop()
    for g, names in zip(got, ids):
        bodies = body_msgs.joint_state_to_bodies(g['bodies/params'])
        assert sorted(f'body_{k}' for k in bodies) == sorted(names)
        for b in bodies.values():
            assert b['pose'].shape == (body.num_pose_joints, 3)
            assert b['joint_confidence'].shape == (len(body.joint_names),)
        index = A.image_to_array(g['bodies/index'])
        assert set(np.unique(index)) <= set(range(len(names))) | {255}
        assert all((index == k).sum() > 500 for k in range(len(names)))
        mesh_ids = {m.id for m in g['meshes'].markers if m.action == Marker.ADD}
        assert mesh_ids == {int(n[5:]) for n in names}
    # index k is the k-th tracked person: its pixels are that person's in the truth
    f0, idx0 = frames[0], A.image_to_array(got[0]['bodies/index'])
    for k in range(2):
        truth = np.bincount(f0['person_index'][idx0 == k] + 1, minlength=3)[1:]
        assert truth.max() > 0.8 * (idx0 == k).sum()
    last = got[-1]
    deleted = {(m.ns, m.id) for m in last['meshes'].markers + last['skeleton'].markers
               if m.action == Marker.DELETE}
    lid = int(left[5:])
    assert deleted == {('body_mesh', lid), ('skeleton/joints', lid), ('skeleton/bones', lid)}


def test_faults_then_good_input_is_published_within_a_second(harness, core, scene,
                                                              monkeypatch):
    """Fault injection: camera_info stops (and restarts), the depth stream pauses, stamps
    jump backwards and forwards by hours, the network and the fit raise inside the worker,
    a parameter is set to an invalid value. After each, a good frame is answered within
    1 s, and /diagnostics said what happened."""
    node, tester = harness()
    send_until(tester, scene, 'mesh', 30.0)
    hour = 3600 * 10**9

    def good(offset_ns: int = 0, index: int = 1) -> float:
        """Seconds from publishing a good frame to its answer on ~/bodies/tracked."""
        stamp = tester.now_ns() + offset_ns
        t0 = time.monotonic()
        tester.pub_depth.publish(scene.depth_msg(index, stamp))
        assert wait_for(lambda: tester.with_stamp('bodies/tracked', stamp), 10.0), \
            'no answer'
        return time.monotonic() - t0

    def said(reason: str) -> bool:
        return wait_for(lambda: any(r == reason for r, _ in tester.problems()), 3.0)

    took = {}
    # camera_info stops: the last one keeps serving, and the summary says how old it is
    infos, tester.infos = tester.infos, []
    time.sleep(2.5)
    took['camera_info stopped'] = good()
    def summary_says(text):
        return any(text in s.message for a in tester.msgs('diagnostics') for s in a.status
                   if s.name.endswith(': processing'))
    assert wait_for(lambda: summary_says('no camera_info for'), 3.0), tester.summary()
    tester.infos = infos  # ... and restarts
    took['camera_info restarted'] = good()
    # the depth stream pauses
    time.sleep(3.0)
    took['depth paused 3 s'] = good()
    # stamps jump back and forth by hours
    took['stamps -2 h'] = good(-2 * hour)
    assert said('time_jump')
    took['stamps +2 h'] = good(0)
    # the network, then the fit, raise inside the worker
    for where, obj, name in (('network', core._rec.net, 'predict'),
                             ('fit', core._rec.fitter, 'fit')):
        real = getattr(obj, name)
        calls = []

        def boom(*a, _real=real, _calls=calls, **k):
            if not _calls:
                _calls.append(1)
                raise RuntimeError(f'injected fault in the {where}')
            return _real(*a, **k)
        monkeypatch.setattr(obj, name, boom)
        stamp = tester.now_ns()
        tester.pub_depth.publish(scene.depth_msg(0, stamp))
        assert wait_for(lambda: calls, 10.0)
        # (a second 'internal' within warn_throttle_s is not posted again: the summary's
        # last_error names it)
        assert wait_for(lambda: any(r == 'internal' and where in m
                                    for r, m in tester.problems()) or
                        where in (tester.summary() or {}).get('last_error', ''), 5.0), \
            tester.problems()
        took[f'{where} raised'] = good()
        monkeypatch.setattr(obj, name, real)
    # an invalid parameter at run time is refused; the node keeps going
    res = node.set_parameters([Parameter('max_persons', value=-1)])[0]
    assert not res.successful and 'max_persons' in res.reason
    took['invalid parameter'] = good()
    assert all(t < 1.0 for t in took.values()), took


def test_burst_against_slow_worker(harness, core, scene):
    core.delay = 0.3  # deliberately slow: far below the 30 Hz input
    node, tester = harness()
    send_until(tester, scene, 'mesh', 30.0)  # warm up

    def idle():
        return (not core.busy and node._mailbox.pending() == 0
                and node._handoff.pending() == 0)

    assert wait_for(idle, 30.0)
    tester.clear()
    calls0 = len(core.durations)
    sent = {}
    t0 = time.monotonic()
    i = 0
    # 30 Hz until 5 outputs came back (at least 3 s, at most 40 s).
    while time.monotonic() - t0 < 40.0 and (time.monotonic() - t0 < 3.0 or
                                            tester.count('mesh') < 5):
        s = tester.now_ns()
        sent[s] = time.monotonic()
        tester.pub_depth.publish(scene.depth_msg(i, s))
        i += 1
        time.sleep(1 / 30)
    assert wait_for(idle, 30.0)
    time.sleep(0.3)
    with tester.lock:
        got = [(t, stamp_to_ns(m.header.stamp)) for t, m in tester.got['mesh']]
    lat = np.array([t - sent[s] for t, s in got if s in sent])
    assert len(lat) >= 3, f'too few outputs: {len(lat)} for {i} frames'
    # Bounded latency: at most one frame waiting (the one being processed) plus its own
    # processing, whatever the burst length; a queue would grow by ~1 s per second.
    service = max(core.durations[calls0:])  # one reconstruction, the delay included
    bound = 2 * service + 0.5
    assert lat.max() < bound, (lat, service)
    # No growth over the burst: the last third's answers as quick as the first third's,
    # within one reconstruction (the very last frame, sent after the detector had taken
    # the one before it, may wait a whole reconstruction more: 2 x service).
    third = max(1, len(lat) // 3)
    assert np.median(lat[-third:]) < np.median(lat[:third]) + service, lat
    # Fewer outputs than inputs, the rest dropped and counted; every frame accounted for.
    assert len(lat) < i / 3
    with node._lock:
        received, processed = node._stats['received'], node._stats['processed']
        rejected = sum(node._errors.values())
    assert node._mailbox.dropped > 0
    assert received == processed + rejected + node._mailbox.dropped
    # The periodic summary may have been taken while the last frame was still being
    # processed: wait for one taken after it (nothing pending, every drop counted).
    assert wait_for(lambda: (tester.summary() or {}).get('frames_pending') == '0' and int(
        tester.summary().get('frames_dropped', 0)) == node._mailbox.dropped, 3.0)
    summary = tester.summary()
    assert float(summary['latency_receive_ms_max']) < bound * 1e3


BAD_INPUTS = ['encoding', 'size_mismatch', 'truncated', 'all_zero', 'all_nan', 'no_person',
              'too_large', 'bad_intrinsics', 'no_camera_info']


def _bad_msg(kind: str, scene: Scene, tester: Probe, stamp: int) -> tuple[Image, set]:
    """A bad depth frame of `kind` and the diagnostics reasons it may produce."""
    h, w = scene.camera.height, scene.camera.width
    hdr = A.make_header(stamp_ns=stamp, frame_id=FRAME)
    if kind == 'encoding':
        m = A.depth_to_image_msg(scene.depth[0], hdr, '16UC1')
        m.encoding = 'rgb8'
        return m, {'encoding'}
    if kind == 'size_mismatch':
        return A.depth_to_image_msg(scene.depth[0][::2, ::2], hdr, '16UC1'), {'size_mismatch'}
    if kind == 'truncated':
        m = A.depth_to_image_msg(scene.depth[0], hdr, '16UC1')
        m.data = m.data[:len(m.data) // 2]
        return m, {'size_mismatch'}
    if kind == 'all_zero':
        return A.depth_to_image_msg(np.zeros((h, w)), hdr, '16UC1'), {'no_valid_depth'}
    if kind == 'all_nan':
        return A.depth_to_image_msg(np.full((h, w), np.nan), hdr, '32FC1'), {'no_valid_depth'}
    if kind == 'no_person':  # a wall beyond depth_max
        return A.depth_to_image_msg(np.full((h, w), 9.0), hdr, '16UC1'), \
            {'no_person', 'no_valid_depth'}
    if kind == 'too_large':  # 1280x1024 > max_image_pixels (set to 1e6 below)
        return A.depth_to_image_msg(np.full((1024, 1280), 2.0), hdr, '16UC1'), {'too_large'}
    if kind == 'bad_intrinsics':
        hdr = A.make_header(stamp_ns=stamp, frame_id='uncalibrated')
        return A.depth_to_image_msg(scene.depth[0], hdr, '16UC1'), {'bad_intrinsics'}
    if kind == 'no_camera_info':
        hdr = A.make_header(stamp_ns=stamp, frame_id='no_such_camera')
        return A.depth_to_image_msg(scene.depth[0], hdr, '16UC1'), {'no_camera_info'}
    raise ValueError(kind)


def test_bad_inputs_then_good_frame(harness, core, scene):
    node, tester = harness(**{'advanced.max_image_pixels': 1_000_000,
                              'advanced.warn_throttle_s': 30.0})
    tester.infos.append(scene.info_msg('uncalibrated', K=np.zeros((3, 3))))
    assert wait_for(lambda: 'uncalibrated' in node._camera_infos, 10.0)
    seen = []
    for kind in BAD_INPUTS:
        n0 = len(tester.problems())
        stamp = tester.now_ns()
        msg, reasons = _bad_msg(kind, scene, tester, stamp)
        if reasons & set(seen):
            # Same reason as an earlier frame: its warning and entry are throttled, the
            # summary counts it.
            def count():
                return sum(int((tester.summary() or {}).get(f'errors_{r}', 0))
                           for r in reasons)
            assert wait_for(lambda: tester.summary() is not None, 5.0)
            c0 = count()
            tester.pub_depth.publish(msg)
            assert wait_for(lambda: count() > c0, 10.0), f'{kind} not counted'
            continue
        tester.pub_depth.publish(msg)
        assert wait_for(lambda: len(tester.problems()) > n0, 10.0), f'no diagnostics for {kind}'
        reason, text = tester.problems()[-1]
        assert reason in reasons, (kind, reason, text)
        assert text  # a message naming the problem
        seen.append(reason)
        assert node.context.ok() and node._worker.is_alive() and node._detector.is_alive()
        assert not tester.with_stamp('mesh', stamp)
    # The node goes on: a good frame still produces every output.
    stamp = send_until(tester, scene, 'mesh', 30.0)
    for name in OUTPUTS:
        assert wait_for(lambda: tester.with_stamp(name, stamp), 5.0), name
    # The summary counts every rejected frame by reason.
    assert wait_for(lambda: 'errors_no_camera_info' in (tester.summary() or {}), 5.0)
    summary = tester.summary()
    for r in set(seen):
        assert int(summary[f'errors_{r}']) >= 1, (r, summary)
    assert int(summary['frames_no_camera_info']) >= 1


def test_a_lens_distorted_camera_is_undistorted(harness, core, scene):
    """An Azure Kinect's own depth image (rational_polynomial camera_info, as its driver
    publishes depth/image_raw) on a topic not named rect: made pinhole before use
    (`undistort` 'auto'), the mesh lands on the true body and the published labels on the
    raw image's body pixels; /diagnostics says what was done with the lens."""
    from smpl_depth_ros.synth.poses import PoseSampler
    from smpl_depth_ros.synth.sensors import LENSES, SENSORS
    from smpl_depth_ros.tools.sweep import sweep_frames
    body = core.body
    fr = list(sweep_frames(body, PoseSampler(body), SENSORS['azure_kinect_nfov'], 2.0, 3.0,
                           2, 202, lens='azure_kinect'))[1]
    model, D = LENSES['azure_kinect']
    node, tester = harness()
    h, w = fr['depth'].shape
    tester.infos.append(A.camera_info_msg(fr['K'], (w, h), A.make_header(frame_id='azure'),
                                          D=D, model=model))
    assert wait_for(lambda: 'azure' in node._camera_infos, 10.0)
    stamps = []

    def meshed():
        return [s for s in stamps if tester.with_stamp('mesh', s)]
    end = time.monotonic() + 30.0
    while not meshed() and time.monotonic() < end:
        stamps.append(tester.now_ns())
        tester.pub_depth.publish(A.depth_to_image_msg(
            fr['depth'], A.make_header(stamp_ns=stamps[-1], frame_id='azure'), '16UC1'))
        wait_for(meshed, 0.5)
    assert meshed(), 'no mesh for the distorted camera'
    stamp = meshed()[0]
    faces = body.faces_numpy()
    v = mesh_vertices(tester.with_stamp('mesh', stamp)[0], faces, body.num_vertices)
    assert np.nanmean(np.linalg.norm(v - fr['vertices'], axis=1)) < 0.03
    assert wait_for(lambda: tester.with_stamp('segmentation/labels', stamp), 5.0)
    labels = A.image_to_array(tester.with_stamp('segmentation/labels', stamp)[0])
    assert labels.shape == (h, w)
    ours, truth = labels > 0, fr['labels'] > 0
    assert (ours & truth).sum() / (ours | truth).sum() > 0.7
    assert wait_for(lambda: (tester.summary() or {}).get('lens_distortion')
                    == 'azure: undistorted', 10.0), tester.summary()


def test_runtime_parameter_validation(harness, core, scene):
    # A short (command-line tool) name in the overrides is reported, not silently dropped.
    # Constructing the node changes nothing process-wide (tune_process does, in main).
    import gc
    threads, frozen = torch.get_num_threads(), gc.get_freeze_count()
    node, tester = harness(tune=False, **{'fit.iterations': 3, 'cpu_threads': threads + 1})
    # gc.freeze() would move the node's thousands of new objects into the permanent
    # generation; objects frozen earlier in the process may meanwhile be freed.
    assert torch.get_num_threads() == threads
    assert gc.get_freeze_count() <= frozen
    assert node.unknown_parameters == ['fit.iterations']
    assert node.get_parameter('advanced.fit.iterations').value == FitConfig().iterations
    bad = [Parameter('depth_min', value=7.0),                       # >= depth_max (6.0)
           Parameter('device', value='tpu'),
           Parameter('advanced.fit.iterations', value=-1),
           Parameter('advanced.fit.solver', value='newton'),
           Parameter('backend', value='smpl'),                      # read-only
           Parameter('qos_reliability', value='reliable'),          # read-only
           Parameter('mesh_decimation', value=0.0)]
    for p in bad:
        r = node.set_parameters([p])[0]
        assert not r.successful, p.name
        assert r.reason, p.name
    assert node.get_parameter('depth_min').value == pytest.approx(0.5)
    assert node.get_parameter('backend').value == 'anny'
    # Valid changes are accepted and reach the core / the outputs.
    faces = core.body.faces_numpy()
    r = node.set_parameters([Parameter('depth_max', value=5.0),
                             Parameter('advanced.fit.iterations', value=8),
                             Parameter('mesh_decimation', value=0.5),
                             Parameter('publish_skeleton', value=False)])
    assert all(x.successful for x in r), [x.reason for x in r]
    stamp = send_until(tester, scene, 'mesh', 30.0)
    mesh = tester.with_stamp('mesh', stamp)[0]
    with torch.no_grad():
        rest = core.body(**core.body.zero_params(1)).vertices[0].cpu().numpy()
    expected = markers.decimate_faces(rest, faces, round(0.5 * len(faces)))
    assert len(mesh.points) == 3 * len(expected) < 3 * len(faces)
    assert core.config.depth_max == pytest.approx(5.0)
    assert core.config.fit.iterations == 8
    fitter = getattr(core._rec, 'fitter', None)
    if fitter is not None and hasattr(fitter, 'cfg'):
        assert fitter.cfg.iterations == 8  # reached the solver too
    time.sleep(0.5)
    assert not tester.with_stamp('skeleton', stamp)
    # Turning tracking off resets the tracker. The detector thread applies a change once
    # both workers are idle: a frame it had already begun waiting for may still be
    # reconstructed with the old settings, so the reset can follow that frame's output.
    resets = core.resets
    assert node.set_parameters([Parameter('tracking', value=False)])[0].successful
    send_until(tester, scene, 'mesh', 30.0)
    assert wait_for(lambda: core.resets > resets, 10.0)
    assert core.config.tracking is False


# -- the console script in a subprocess ------------------------------------------------
def node_command() -> list[str]:
    exe = Path(sys.executable).parent / 'reconstructor'
    if exe.exists():
        return [str(exe)]
    found = shutil.which('reconstructor')
    return [found] if found else [sys.executable, '-m', 'smpl_depth_ros.ros.reconstructor_node']


def start_node(*ros_args: str) -> subprocess.Popen:
    env = dict(os.environ)  # conftest: localhost-only discovery, the test's domain id
    env['PYTHONPATH'] = os.pathsep.join([str(REPO)] + [p for p in env.get(
        'PYTHONPATH', '').split(os.pathsep) if p])
    env['PYTHONUNBUFFERED'] = '1'
    return subprocess.Popen(node_command() + ['--ros-args', *ros_args], cwd=REPO, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def stop_node(proc: subprocess.Popen, sig=signal.SIGINT, timeout: float = 20.0):
    """Send `sig` (None: just wait) and collect (returncode, stdout, stderr)."""
    if sig is not None and proc.poll() is None:
        proc.send_signal(sig)
    try:
        out, err = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, err = proc.communicate()
        raise AssertionError(f'node did not exit on {sig!r}:\n{err}')
    return proc.returncode, out, err


def _future(fut, timeout: float = 10.0):
    assert wait_for(fut.done, timeout), 'service call timed out'
    return fut.result()


@pytest.fixture(scope='module')
def synth_bag(tmp_path_factory):
    """A 3-frame `synth_bag --sequence` bag: raw CDR messages in order + ground truth."""
    from rosbags.highlevel import AnyReader

    from smpl_depth_ros.bagio import jazzy_typestore
    from smpl_depth_ros.tools import synth_bag as tool
    out = tmp_path_factory.mktemp('bag') / 'seq'
    assert tool.main(['--out', str(out), '--frames', '3', '--seed', '3', '--sequence']) == 0
    gt = dict(np.load(tool.gt_path(str(out))))
    with AnyReader([out], default_typestore=jazzy_typestore()) as reader:
        raw = [(c.topic, c.msgtype, bytes(data)) for c, _, data in reader.messages()]
    return raw, gt


def test_subprocess_bag_frames_params_file_and_sigint(rclpy_context, real_core, synth_bag):
    """`reconstructor --ros-args -r ... -p ... --params-file config/reconstructor.yaml`
    like `ros2 run`; frames of a synth_bag bag played to it (raw CDR, bag stamps)."""
    from rclpy.parameter_client import AsyncParameterClient
    from rclpy.serialization import deserialize_message

    raw, gt = synth_bag
    topics = {t for t, _, _ in raw}
    assert topics == {'/camera/depth/image_raw', '/camera/depth/camera_info'}
    proc = start_node('-r', '__ns:=/sp', '-r', 'depth:=/camera/depth/image_raw',
                      '-r', 'camera_info:=/camera/depth/camera_info',
                      '--params-file', str(PARAMS_FILE),
                      '-p', 'depth_max:=5.5', '-p', 'mesh_lifetime_s:=2.0', '-p', 'device:=cpu',
                      # Reliable: best-effort 640x480 frames (600 kB, fragmented) over
                      # loopback were lost for a whole minute on a busy 2-core machine.
                      '-p', 'qos_reliability:=reliable')
    tester = Probe(rclpy_context, '/sp')
    rel = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
    tester.pub_depth = tester.node.create_publisher(Image, '/camera/depth/image_raw', rel)
    tester.pub_info = tester.node.create_publisher(CameraInfo, '/camera/depth/camera_info',
                                                   rel)
    spinner = Spinner(rclpy_context, tester.node)
    body = real_core[0].body
    faces = body.faces_numpy()
    try:
        tester.wait_connected(90.0)
        client = AsyncParameterClient(tester.node, '/sp/reconstructor')
        assert client.wait_for_services(20.0)
        names = ['depth_max', 'depth_min', 'mesh_lifetime_s', 'qos_reliability', 'backend',
                 'advanced.fit.iterations']
        values = [parameter_value_to_python(x)
                  for x in _future(client.get_parameters(names)).values]
        got = dict(zip(names, values))
        assert got['depth_max'] == pytest.approx(5.5)      # -p beats the params file
        assert got['depth_min'] == pytest.approx(0.5)      # from the params file
        assert got['mesh_lifetime_s'] == pytest.approx(2.0)
        assert got['qos_reliability'] == 'reliable'
        assert got['backend'] == 'anny'
        # Runtime changes: rejected with a reason, or accepted.
        res = _future(client.set_parameters([Parameter('depth_min', value=6.0)])).results
        assert not res[0].successful and 'depth_max' in res[0].reason
        res = _future(client.set_parameters([Parameter('weights_path', value='x')])).results
        assert not res[0].successful and 'read-only' in res[0].reason
        res = _future(client.set_parameters(
            [Parameter('advanced.fit.iterations', value=10)])).results
        assert res[0].successful

        # Play the bag: camera_info then depth, frame by frame, waiting for the outputs.
        errors = []
        pairs = [(raw[i], raw[i + 1]) for i in range(0, len(raw), 2)]
        for i, (info, depth) in enumerate(pairs):
            assert info[0].endswith('camera_info') and depth[0].endswith('image_raw')
            stamp = int(gt['stamps'][i])
            info_msg = deserialize_message(info[2], CameraInfo)
            depth_msg = deserialize_message(depth[2], Image)
            assert stamp_to_ns(depth_msg.header.stamp) == stamp
            deadline = time.monotonic() + 60.0
            while not tester.with_stamp('mesh', stamp) and time.monotonic() < deadline:
                tester.pub_info.publish(info_msg)
                time.sleep(0.05)
                tester.pub_depth.publish(depth_msg)
                wait_for(lambda: tester.with_stamp('mesh', stamp), 2.0)
            assert tester.with_stamp('mesh', stamp), f'no mesh for bag frame {i}'
            for name in OUTPUTS:
                assert wait_for(lambda: tester.with_stamp(name, stamp), 5.0), name
                for m in tester.with_stamp(name, stamp):
                    assert _header(m).frame_id == FRAME, name
            mesh = tester.with_stamp('mesh', stamp)[0]
            assert len(mesh.points) == 3 * len(faces)   # the model's triangle count
            assert mesh.lifetime.sec == 2
            v = mesh_vertices(mesh, faces, body.num_vertices)
            errors.append(float(np.nanmean(np.linalg.norm(v - gt['vertices'][i], axis=1))))
            p = body_msgs.joint_state_to_params(tester.with_stamp('smpl_params', stamp)[0])
            assert p['pose'].shape == (body.num_pose_joints, 3)
            assert p['shape'].shape == (body.num_shape,)
            assert p['joint_names'] == tuple(body.joint_names[1:])
            # The fitted parameters reproduce the published mesh.
            with torch.no_grad():
                out = body(torch.as_tensor(p['pose'])[None], torch.as_tensor(p['shape'])[None],
                           torch.as_tensor(p['global_orient'])[None],
                           torch.as_tensor(p['transl'])[None])
            np.testing.assert_allclose(out.vertices[0].numpy(), v, atol=2e-3)
        # Mean vertex error (same topology) against the bag's ground truth: the node hands
        # the core's fit on unchanged (the core's own accuracy is tested with the core).
        assert np.median(errors) < 0.06 and max(errors) < 0.10, errors
        assert wait_for(lambda: tester.summary() is not None, 5.0)
        summary = tester.summary()
        assert summary['model'] == body.name and summary['device'] == 'cpu'
    finally:
        spinner.close()
        code, out, err = stop_node(proc, signal.SIGINT)
    assert code == 0, err
    assert 'Traceback' not in err and 'Traceback' not in out, err
    assert 'first result' in err + out
    assert 'did not stop in time' not in err + out  # the worker was stopped and joined


def test_subprocess_sigterm_and_bad_startup_params(rclpy_context, real_core):
    # Invalid parameters at start-up: exit code 1, one clear line, no traceback.
    proc = start_node('--params-file', str(PARAMS_FILE), '-p', 'depth_min:=7.0')
    code, out, err = stop_node(proc, None, timeout=60.0)
    assert code == 1, (code, err)
    assert 'depth_min' in err and 'Traceback' not in err, err
    # SIGINT while the model loads: clean exit.
    proc = start_node('-p', 'device:=cpu')
    lines = []

    def read_until_loading():
        for line in proc.stderr:
            lines.append(line)
            if 'loading the' in line:
                return

    reader = threading.Thread(target=read_until_loading, daemon=True)
    reader.start()
    reader.join(60.0)
    assert any('loading the' in x for x in lines), lines
    code, out, err = stop_node(proc, signal.SIGINT)
    assert code == 0, ''.join(lines) + err
    assert 'Traceback' not in ''.join(lines) + err
    # SIGTERM while idle: clean exit.
    proc = start_node('-r', '__ns:=/st', '-p', 'device:=cpu')
    node = rclpy.create_node('probe', context=rclpy_context)
    try:
        pub = node.create_publisher(Image, '/st/depth', 1)
        assert wait_for(lambda: pub.get_subscription_count() > 0, 60.0)
    finally:
        node.destroy_node()
    code, out, err = stop_node(proc, signal.SIGTERM)
    assert code == 0, err
    assert 'Traceback' not in err and 'did not stop in time' not in err, err


# -- the shipped configuration -----------------------------------------------------------
def _flatten(d: dict, prefix: str = '') -> dict:
    out = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flatten(v, f'{prefix}{k}.'))
        else:
            out[f'{prefix}{k}'] = v
    return out


def test_print_params(capsys):
    import yaml
    from smpl_depth_ros.params import SCHEMA
    from smpl_depth_ros.ros.reconstructor_node import main
    assert main(['--print-params']) == 0
    printed = _flatten(yaml.safe_load(capsys.readouterr().out)['/**']['ros__parameters'])
    assert printed == {p.ros_name: p.default for p in SCHEMA.values()}
    assert 'advanced.fit.iterations' in printed and 'max_persons' in printed


def test_params_file_mirrors_defaults():
    import yaml
    from smpl_depth_ros.params import SCHEMA, check, lookup
    data = yaml.safe_load(PARAMS_FILE.read_text())
    values = _flatten(data['/**']['ros__parameters'])
    defaults = {p.ros_name: p.default for p in SCHEMA.values()}
    missing = {k: v for k, v in defaults.items() if k not in values}
    extra = sorted(set(values) - set(defaults))
    assert not missing and not extra, (
        f'config/reconstructor.yaml is out of date with PipelineConfig/FitConfig: add '
        f'{missing}, remove {extra} (regenerate: reconstructor --print-params > '
        f'config/reconstructor.yaml)')
    for k, v in defaults.items():
        assert type(values[k]) is type(v), k        # a double stays a double, etc.
        assert values[k] == pytest.approx(v) if isinstance(v, float) else values[k] == v, \
            f'{k}: {values[k]!r} in the params file, default {v!r} (regenerate: ' \
            'reconstructor --print-params > config/reconstructor.yaml)'
    assert check({lookup(k).name: v for k, v in values.items()}) is None


def test_rviz_config_shows_the_outputs():
    import yaml
    rviz = yaml.safe_load((REPO / 'config' / 'reconstructor.rviz').read_text())
    vm = rviz['Visualization Manager']
    assert vm['Global Options']['Fixed Frame'] == FRAME
    displays = {d['Class'].split('/')[-1]: d for d in vm['Displays']}
    assert displays['DepthCloud']['Depth Map Topic'] == '/depth'
    assert displays['Marker']['Topic']['Value'] == '/reconstructor/mesh'
    assert displays['MarkerArray']['Topic']['Value'] == '/reconstructor/skeleton'
    assert displays['Image']['Topic']['Value'] == '/reconstructor/segmentation'


def test_subprocess_sigint_while_a_frame_is_processed(rclpy_context, real_core, scene):
    """SIGINT with a 30 Hz stream going, 50 ms after an answer (the worker busy with the
    next frame): a clean exit, no 'Exception in thread' (a publish on a dead context)."""
    proc = start_node('-r', '__ns:=/busy', '-p', 'device:=cpu', '-p',
                      'qos_reliability:=reliable')
    node = rclpy.create_node('busy_probe', context=rclpy_context)
    got = []
    rel = QoSProfile(depth=5, reliability=ReliabilityPolicy.RELIABLE)
    pub_d = node.create_publisher(Image, '/busy/depth', rel)
    pub_i = node.create_publisher(CameraInfo, '/busy/camera_info', rel)
    node.create_subscription(JointState, '/busy/reconstructor/bodies/tracked',
                             lambda m: got.append(time.monotonic()), rel)
    spinner = Spinner(rclpy_context, node)
    try:
        end = time.monotonic() + 90.0
        n, signalled = 0, False
        while time.monotonic() < end and not signalled:
            stamp = node.get_clock().now().nanoseconds
            pub_i.publish(scene.info_msg())
            pub_d.publish(scene.depth_msg(n, stamp))
            n += 1
            time.sleep(1 / 30)
            if len(got) >= 5 and time.monotonic() - got[-1] > 0.05:
                proc.send_signal(signal.SIGINT)
                signalled = True
        assert signalled, 'the node never answered'
        for _ in range(10):  # the stream goes on while it shuts down
            pub_d.publish(scene.depth_msg(n, node.get_clock().now().nanoseconds))
            time.sleep(1 / 30)
    finally:
        spinner.close()
        node.destroy_node()
    code, out, err = stop_node(proc, None)
    assert code == 0, err
    assert 'Traceback' not in err and 'Exception in thread' not in err, err


def test_tf_frames_of_two_people_where_tf2_msgs_is_installed(harness, core, scene):
    """/tf carries body_<id> for each tracked person, parented to the depth frame, with
    the depth stamp; the TFMessage type the node publishes (a ROS install's tf2_msgs, or
    in the pip venv the one `make` generates from its definition) is Jazzy's: the type
    hash its publisher advertises is the one every Jazzy /tf endpoint has."""
    tf2 = pytest.importorskip('tf2_msgs.msg', reason='tf2_msgs is not installed')
    from smpl_depth_ros.synth.dataset import make_multi_sequence
    from smpl_depth_ros.synth.poses import PoseSampler
    body = core.body
    frames = list(make_multi_sequence(body, PoseSampler(body), np.random.default_rng(5),
                                      scene.camera, 3, 2))
    node, tester = harness(max_persons=3)
    core.set_config(core.config.with_overrides(max_persons=3))
    got = []
    tester.node.create_subscription(tf2.TFMessage, '/tf', got.append, 100)
    for f in frames:
        stamp = tester.now_ns()
        tester.pub_depth.publish(A.depth_to_image_msg(
            f['depth'], A.make_header(stamp_ns=stamp, frame_id=FRAME), '16UC1'))
        assert wait_for(lambda: tester.with_stamp('bodies/tracked', stamp), 30.0)
        tracked = tester.with_stamp('bodies/tracked', stamp)[0]
        assert wait_for(lambda: any(stamp_to_ns(t.header.stamp) == stamp
                                    for m in got for t in m.transforms), 5.0)
        roots = {t.child_frame_id: t for m in got for t in m.transforms
                 if stamp_to_ns(t.header.stamp) == stamp and t.header.frame_id == FRAME}
        assert set(roots) == {str(n) for n in tracked.name}
    pubs = [i for i in tester.node.get_publishers_info_by_topic('/tf')
            if i.node_name == node.get_name()]
    assert pubs and pubs[0].topic_type == 'tf2_msgs/msg/TFMessage'
    assert str(pubs[0].topic_type_hash) == (  # `ros2 topic info -v /tf` on Jazzy
        'RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087')
