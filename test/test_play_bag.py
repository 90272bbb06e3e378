"""play_bag -> a running `reconstructor` node -> outputs recorded, against process_bag.

The live path (a bag replayed over DDS with `play_bag` into the node, started like `ros2
run` would, its outputs recorded by an rclpy subscriber here) and the offline path
(the `process_bag` console script on the same bag) run the same core with the same
parameters on the same frames in the same order, so they must give the same meshes up to
floating-point noise (measured: identical).
`play_bag --pace` makes that hold on any machine: it sends the next depth frame only once
the node has published the mesh of the previous one, so the node's one-slot queue never
replaces a frame and tracking sees exactly the frames `process_bag` sees.

DDS stays on this machine (conftest.py: localhost-only discovery, a private domain id).
"""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

rclpy = pytest.importorskip('rclpy')

from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.qos import QoSProfile, ReliabilityPolicy  # noqa: E402
from sensor_msgs.msg import CameraInfo  # noqa: E402
from visualization_msgs.msg import Marker  # noqa: E402

from smpl_depth_ros.stamps import stamp_to_ns  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
DEPTH, INFO = '/camera/depth/image_raw', '/camera/depth/camera_info'
FRAMES = 4
# Live and offline meshes differ only by floating-point noise (same core, frames, order,
# random subsets, thread count); 1 mm mean leaves room for rounding differences.
SAME_MESH_MM = 1.0


def _env() -> dict:
    env = dict(os.environ)  # conftest: localhost-only discovery, the test's domain id
    assert env['ROS_AUTOMATIC_DISCOVERY_RANGE'] == 'LOCALHOST'
    env['PYTHONPATH'] = os.pathsep.join([str(REPO)] + [p for p in env.get(
        'PYTHONPATH', '').split(os.pathsep) if p])
    env['PYTHONUNBUFFERED'] = '1'
    return env


def _command(script: str, module: str) -> list[str]:
    exe = Path(sys.executable).parent / script
    return [str(exe)] if exe.exists() else [sys.executable, '-m', module]


def play(*args: str, timeout: float = 300.0) -> tuple[int, dict, str]:
    """Run play_bag to completion: (exit code, its JSON summary, stderr)."""
    proc = subprocess.run(_command('play_bag', 'smpl_depth_ros.tools.play_bag') + list(args),
                          cwd=REPO, env=_env(), capture_output=True, text=True,
                          timeout=timeout)
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith('{')]
    return proc.returncode, (json.loads(lines[-1]) if lines else {}), proc.stderr


@pytest.fixture(scope='module')
def bag(tmp_path_factory):
    """A short smooth synth_bag sequence (320x240, seed 4: the person is found in every
    frame), MCAP."""
    from smpl_depth_ros.tools import synth_bag
    out = tmp_path_factory.mktemp('play') / 'seq'
    assert synth_bag.main(['--out', str(out), '--frames', str(FRAMES), '--seed', '4',
                           '--sequence', '--width', '320', '--height', '240']) == 0
    return out


def marker_points(m) -> np.ndarray:
    return np.array([[p.x, p.y, p.z] for p in m.points], np.float64)


class Recorder:
    """Records the node's meshes (by header stamp) on a background executor."""

    def __init__(self, context, topic: str):
        self.node = rclpy.create_node('play_bag_probe', context=context)
        self.lock = threading.Lock()
        self.meshes: dict[int, list] = {}
        self.node.create_subscription(Marker, topic, self._on_mesh, QoSProfile(
            depth=50, reliability=ReliabilityPolicy.RELIABLE))
        self.executor = SingleThreadedExecutor(context=context)
        self.executor.add_node(self.node)
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()

    def _spin(self):
        try:
            self.executor.spin()
        except Exception:  # the context shut down under us at teardown
            pass

    def _on_mesh(self, msg: Marker):
        with self.lock:
            self.meshes.setdefault(stamp_to_ns(msg.header.stamp), []).append(msg)

    def count(self) -> int:
        with self.lock:
            return sum(len(v) for v in self.meshes.values())

    def close(self):
        self.executor.shutdown(timeout_sec=2.0)
        self.thread.join(5.0)
        self.node.destroy_node()


def test_play_bag_plain(rclpy_context, bag):
    """Recorded timing, --rate, --topics, a subscriber of our own: every message arrives
    equal to the recorded one."""
    from rosbags.highlevel import AnyReader

    from smpl_depth_ros.bagio import jazzy_typestore
    with AnyReader([bag], default_typestore=jazzy_typestore()) as reader:
        recorded = [bytes(raw) for c, _, raw in reader.messages() if c.topic == INFO]
    node = rclpy.create_node('play_probe', context=rclpy_context)
    got, lock = [], threading.Lock()

    def keep(msg):
        with lock:
            got.append(msg)
    node.create_subscription(CameraInfo, INFO, keep, QoSProfile(
        depth=50, reliability=ReliabilityPolicy.RELIABLE))
    ex = SingleThreadedExecutor(context=rclpy_context)
    ex.add_node(node)
    th = threading.Thread(target=lambda: _spin_quietly(ex), daemon=True)
    th.start()
    try:
        t0 = time.monotonic()
        code, summary, err = play(str(bag), '--topics', INFO, '--rate', '0.5',
                                  '--wait-for-subscribers', '30')
        took = time.monotonic() - t0
        assert code == 0, err
        assert summary['messages'] == {INFO: FRAMES} and summary['loops'] == 1, summary
        # FRAMES stamps 1/30 s apart played at half speed: at least (FRAMES - 1) / 15 s.
        assert summary['seconds'] >= (FRAMES - 1) / 15.0 - 0.01, summary
        assert took < 120
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline and len(got) < FRAMES:
            time.sleep(0.05)
        from rclpy.serialization import deserialize_message
        with lock:
            assert got == [deserialize_message(r, CameraInfo) for r in recorded]
        # Unknown topics and bad options: one clear line, exit code 1.
        code, summary, err = play(str(bag), '--topics', '/nope')
        assert code == 1 and '/nope' in err and 'Traceback' not in err, err
    finally:
        ex.shutdown(timeout_sec=2.0)
        th.join(5.0)
        node.destroy_node()


def test_play_bag_clock(rclpy_context, bag):
    """--clock: /clock carries the bag's time, never going backwards, from the first
    message's time to the last's (a late timer tick once sent it backwards in CI)."""
    from rosbags.highlevel import AnyReader
    from rosgraph_msgs.msg import Clock

    from smpl_depth_ros.bagio import jazzy_typestore
    with AnyReader([bag], default_typestore=jazzy_typestore()) as reader:
        times = [t for c, t, _ in reader.messages() if c.topic == INFO]
    node = rclpy.create_node('clock_probe', context=rclpy_context)
    got, lock = [], threading.Lock()

    def keep(msg):
        with lock:
            got.append(msg.clock.sec * 1_000_000_000 + msg.clock.nanosec)
    node.create_subscription(Clock, '/clock', keep, QoSProfile(
        depth=5000, reliability=ReliabilityPolicy.RELIABLE))
    ex = SingleThreadedExecutor(context=rclpy_context)
    ex.add_node(node)
    th = threading.Thread(target=lambda: _spin_quietly(ex), daemon=True)
    th.start()
    try:
        # A fast timer (2 ms) makes late ticks common: a tick that fires after a
        # message's due time must not stamp a time beyond that message's.
        code, summary, err = play(str(bag), '--topics', INFO, '--clock', '500',
                                  '--wait-for-subscribers', '30', '--start-delay', '0.5')
        assert code == 0, err
        time.sleep(0.5)
        with lock:
            clk = list(got)
        assert len(clk) >= FRAMES, clk
        assert all(b >= a for a, b in zip(clk, clk[1:])), clk
        assert clk[0] >= times[0] and clk[-1] >= times[-1], (clk, times)
        assert clk[-1] <= times[-1] + 200_000_000  # 40 ms per timer tick at most, + slack
        assert set(times) <= set(clk)  # published right before every message
    finally:
        ex.shutdown(timeout_sec=2.0)
        th.join(5.0)
        node.destroy_node()


def test_clock_tick_never_passes_the_next_message():
    """A /clock timer tick that runs late (after the next message's due time, as on a
    loaded CI machine) stamps that message's time, not a later one the message's own
    /clock would then contradict; --pace holds it; before the first message, nothing."""
    from smpl_depth_ros.tools.play_bag import clock_ns
    t0, msg2 = 1_700_000_000_000_000_000, 1_700_000_000_033_333_333
    clock = dict(t0=None, w0=10.0, hold=None, next=None)
    assert clock_ns(clock, 10.5, 1.0) is None
    clock.update(t0=t0, next=msg2)
    assert clock_ns(clock, 10.010, 1.0) == t0 + 10_000_000  # on time: interpolated
    assert clock_ns(clock, 10.0341, 1.0) == msg2  # late tick: capped at the next message
    assert clock_ns(clock, 10.005, 2.0) == t0 + 10_000_000  # --rate scales bag time
    clock['hold'] = t0
    assert clock_ns(clock, 11.0, 1.0) == t0


def _spin_quietly(ex):
    try:
        ex.spin()
    except Exception:
        pass


def test_live_node_matches_offline(rclpy_context, bag, tmp_path):
    ns = '/lv'
    node_cmd = _command('reconstructor', 'smpl_depth_ros.ros.reconstructor_node')
    proc = subprocess.Popen(
        node_cmd + ['--ros-args', '-r', f'__ns:={ns}', '-r', f'depth:={DEPTH}',
                    '-r', f'camera_info:={INFO}', '-p', 'device:=cpu',
                    '-p', 'qos_reliability:=reliable', '-p', 'mesh_lifetime_s:=2.0',
                    # torch's default thread count, as process_bag's in-process run: the
                    # network's rounding depends on it, and a cold fit can turn a
                    # rounding difference into ~2 mm (one more or one fewer accepted
                    # Levenberg-Marquardt step).
                    '-p', 'cpu_threads:=0'],
        cwd=REPO, env=_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    recorder = Recorder(rclpy_context, f'{ns}/reconstructor/mesh')
    try:
        # camera_info first (the node keeps the newest per frame_id), so the first depth
        # frame cannot overtake it on the other topic; waits for the node to be up.
        code, summary, err = play(str(bag), '--topics', INFO, '--wait-for-subscribers',
                                  '120')
        assert code == 0 and summary['messages'] == {INFO: FRAMES}, err
        code, summary, err = play(str(bag), '--wait-for-subscribers', '60',
                                  '--pace', f'{ns}/reconstructor/mesh', '--pace-timeout', '120')
        assert code == 0, err
        assert summary['messages'] == {DEPTH: FRAMES, INFO: FRAMES}, summary
        assert 'nothing on' not in err, err  # every frame gave a mesh before the next
        deadline = time.monotonic() + 30
        while recorder.count() < FRAMES and time.monotonic() < deadline:
            time.sleep(0.05)
    finally:
        recorder.close()
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
        try:
            _, node_err = proc.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            _, node_err = proc.communicate()
    assert proc.returncode == 0, node_err
    assert 'Traceback' not in node_err, node_err
    live = recorder.meshes
    assert len(live) == FRAMES and all(len(v) == 1 for v in live.values()), \
        ({k: len(v) for k, v in live.items()}, node_err[-3000:])

    # The offline path as a user runs it, in a fresh process like the node (both import
    # the current sources).
    out = subprocess.run(_command('process_bag', 'smpl_depth_ros.offline') + [
        str(bag), '--out', str(tmp_path / 'offline'), '--device', 'cpu', '--quiet'],
        cwd=REPO, env=_env(), capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr
    assert json.loads(out.stdout.splitlines()[-1])['processed'] == FRAMES
    from rosbags.highlevel import AnyReader

    from smpl_depth_ros.bagio import jazzy_typestore
    offline = {}
    with AnyReader([tmp_path / 'offline' / 'bag'], default_typestore=jazzy_typestore()) as r:
        conns = [c for c in r.connections if c.topic == '/reconstructor/mesh']
        for c, _, raw in r.messages(connections=conns):
            m = r.deserialize(raw, c.msgtype)
            offline[stamp_to_ns(m.header.stamp)] = marker_points(m)
    assert sorted(offline) == sorted(live), (sorted(offline), sorted(live))
    diffs = []
    for stamp, (m,) in sorted(live.items()):
        assert m.header.frame_id == 'camera_depth_optical_frame'
        assert m.lifetime.sec == 2
        pts = marker_points(m)
        assert pts.shape == offline[stamp].shape
        diffs.append(float(np.linalg.norm(pts - offline[stamp], axis=1).mean()) * 1e3)
    print(f'live vs offline mean mesh difference per frame (mm): {np.round(diffs, 4)}')
    assert max(diffs) < SAME_MESH_MM, diffs
