"""process_bag: synth_bag -> process_bag -> the output read back with rosbags (no ROS).

Bags are real rosbag2 bags written with `rosbags` into tmp_path: a short smooth synthetic
sequence from the `synth_bag` tool (ground truth in its `.gt.npz`), and variants of it
rewritten message by message (sqlite3 storage, missing camera_info, duplicate and
backwards stamps, an undecodable frame, a wrong encoding, a topic of an unknown message
type, truncated files).

Mesh accuracy bound (test_round_trip_cli): on these 320x240 frames of one person about
4.2 m away (~1,500 body pixels) the shipped network + fit measured 27-45 mm mean per-vertex
error per frame over the six frames (30-70 mm on longer stretches of the same sequence;
42 mm mean over the 40-frame sample bag); 320x240 gives a quarter of the pixels the
fitting issue's 640x480 figures assume. The test asks for a mean below 80 mm and every
frame below 120 mm: loose enough for CPU-dependent rounding and for the core still being
tuned, tight enough to catch a wrong person, a flipped or misplaced body (those are metres
off); stamps paired with the wrong ground-truth frame are caught exactly by the stamp
checks.
"""
from __future__ import annotations

import json
import os
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from smpl_depth_ros import offline
from smpl_depth_ros.config import PipelineConfig
from smpl_depth_ros.offline import (OUTPUTS, BagReadError, ProcessBagError, Topic,
                                    config_from_params, main, process_bag, select_topics)
from smpl_depth_ros.offline.run import _Progress
from smpl_depth_ros.params import load_params_file

REPO = Path(__file__).resolve().parents[1]
PARAMS_FILE = REPO / 'config' / 'reconstructor.yaml'
DEPTH, INFO = '/camera/depth/image_raw', '/camera/depth/camera_info'
FRAME = 'camera_depth_optical_frame'
FRAMES = 6
OUT_TOPICS = {suffix if suffix.startswith('/') else f'/reconstructor/{suffix}': t
              for suffix, t in OUTPUTS.values()}
MEAN_ERR_MM, FRAME_ERR_MM = 80.0, 120.0
QUIET = dict(progress=False, log=lambda m: None)


# -- helpers --------------------------------------------------------------------------------
def typestore():
    from smpl_depth_ros.bagio import jazzy_typestore
    return jazzy_typestore()


def read_messages(path) -> list[tuple[str, str, int, bytes]]:
    """(topic, msgtype, bag time, raw) of a bag, in time order."""
    from rosbags.highlevel import AnyReader
    with AnyReader([Path(path)], default_typestore=typestore()) as r:
        return [(c.topic, c.msgtype, t, bytes(raw)) for c, t, raw in r.messages()]


def read_decoded(path) -> dict[str, list[tuple[int, object]]]:
    """Output topic -> [(bag time, deserialised message)]: every output must decode
    (input topics are copied as they were, undecodable ones included)."""
    from rosbags.highlevel import AnyReader
    out: dict[str, list] = {}
    with AnyReader([Path(path)], default_typestore=typestore()) as r:
        conns = [c for c in r.connections if c.topic in OUT_TOPICS or
                 c.topic == '/diagnostics']
        for c, t, raw in r.messages(connections=conns):
            out.setdefault(c.topic, []).append((t, r.deserialize(raw, c.msgtype)))
    return out


def write_bag(path, msgs, storage: str = 'mcap', store=None) -> Path:
    """Write (topic, msgtype, bag time, raw) messages as a rosbag2 bag."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    store = store or typestore()
    plugin = StoragePlugin.MCAP if storage == 'mcap' else StoragePlugin.SQLITE3
    conns = {}
    with Writer(Path(path), version=9, storage_plugin=plugin) as w:
        for topic, mt, t, raw in msgs:
            if (topic, mt) not in conns:
                conns[topic, mt] = w.add_connection(topic, mt, typestore=store)
            w.write(conns[topic, mt], t, raw)
    return Path(path)


def storage_file(bag: Path) -> Path:
    return next(p for p in bag.iterdir() if p.suffix in ('.mcap', '.db3'))


def msg_header(msg):
    if hasattr(msg, 'markers'):
        return msg.markers[0].header
    return msg.transforms[0].header if hasattr(msg, 'transforms') else msg.header


def header_stamp(msg) -> int:
    from smpl_depth_ros.stamps import stamp_to_ns
    return stamp_to_ns(msg_header(msg).stamp)


def mesh_points(marker) -> np.ndarray:
    return np.array([[p.x, p.y, p.z] for p in marker.points])


def check_outputs(out: Path, summary: dict, frames_ok: list[int]):
    """The output bag holds one message per output topic for each processed frame, with
    the input frame's stamp as header stamp and bag time; all messages decode."""
    bag = read_decoded(out / 'bag')
    for topic in OUT_TOPICS:
        got = bag.get(topic, [])
        assert [header_stamp(m) for _, m in got] == frames_ok, topic
        for t, m in got:
            assert msg_header(m).frame_id == FRAME
    res = dict(np.load(out / 'results.npz'))
    assert len(res['stamps']) == summary['frames_read']
    assert summary['frames_read'] == summary['processed'] + sum(summary['skipped'].values())
    assert (res['status'] == 'ok').sum() == summary['processed']
    assert json.loads((out / 'summary.json').read_text()) == summary
    return bag, res


# -- fixtures -----------------------------------------------------------------------------
@pytest.fixture(scope='module')
def seq(tmp_path_factory):
    """synth_bag --sequence, 320x240, seed 4 (the person is found in every frame)."""
    from smpl_depth_ros.tools import synth_bag
    out = tmp_path_factory.mktemp('offline') / 'seq'
    assert synth_bag.main(['--out', str(out), '--frames', str(FRAMES), '--seed', '4',
                           '--sequence', '--width', '320', '--height', '240']) == 0
    return out, dict(np.load(synth_bag.gt_path(str(out))))


@pytest.fixture(scope='module')
def seq_msgs(seq):
    return read_messages(seq[0])


@pytest.fixture(scope='module')
def core():
    from smpl_depth_ros.pipeline import Reconstructor
    return Reconstructor(PipelineConfig(device='cpu'))


@pytest.fixture(scope='module')
def cli_run(seq, tmp_path_factory):
    """The console script on the whole sequence (params file, meshes): (out, summary)."""
    import contextlib
    import io
    out = tmp_path_factory.mktemp('cli') / 'out'
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        code = main([str(seq[0]), '--out', str(out), '--params-file', str(PARAMS_FILE),
                     '--device', 'cpu', '--export-meshes', 'ply', '--quiet'])
    assert code == 0
    return out, json.loads(buf.getvalue().strip().splitlines()[-1])


# -- tests ----------------------------------------------------------------------------------
def test_round_trip_cli(seq, seq_msgs, cli_run):
    import trimesh
    bag, gt = seq
    out, summary = cli_run
    stamps = [int(s) for s in gt['stamps']]
    assert summary['frames_read'] == summary['processed'] == FRAMES, summary
    assert summary['skipped'] == {} and summary['error'] is None
    assert summary['depth_topic'] == DEPTH and summary['info_topic'] == INFO
    assert summary['device'] == 'cpu' and summary['tracking'] is True
    assert summary['tracked'] >= FRAMES - 2       # warm starts across consecutive frames
    assert summary['fps'] > 0 and summary['peak_rss_mb'] > 0
    assert set(summary['timings_ms_mean']) >= {'network', 'fit', 'total'}
    decoded, res = check_outputs(out, summary, stamps)
    # Inputs copied unchanged, same bag times.
    copied = [m for m in read_messages(out / 'bag') if m[0] in (DEPTH, INFO)]
    assert copied == seq_msgs
    # Outputs: bag time = input bag time = header stamp (synth_bag writes them equal).
    for topic in OUT_TOPICS:
        assert [t for t, _ in decoded[topic]] == stamps, topic
    assert len(decoded['/diagnostics']) >= 1
    seg = decoded['/reconstructor/segmentation'][0][1]
    labels = decoded['/reconstructor/segmentation/labels'][0][1]
    assert (seg.encoding, labels.encoding) == ('rgb8', 'mono8')
    assert (seg.width, seg.height) == (320, 240)
    # results.npz
    assert list(res['stamps']) == stamps and list(res['bag_times']) == stamps
    assert list(res['status']) == ['ok'] * FRAMES
    assert res['pose'].shape[0] == FRAMES and np.isfinite(res['pose']).all()
    assert np.isfinite(res['residual_m']).all() and np.isfinite(res['timings_ms']).all()
    # Parameters in the JointState equal results.npz; meshes equal the markers.
    from smpl_depth_ros.ros.body_msgs import joint_state_to_params
    errors = []
    for i, ((_, js), (_, marker)) in enumerate(zip(decoded['/reconstructor/smpl_params'],
                                                   decoded['/reconstructor/mesh'])):
        p = joint_state_to_params(js)
        np.testing.assert_allclose(p['transl'], res['transl'][i], atol=1e-6)
        np.testing.assert_allclose(p['pose'], res['pose'][i], atol=1e-6)
        mesh = trimesh.load(out / 'meshes' / f'{stamps[i]}.ply', process=False)
        v = np.asarray(mesh.vertices)
        np.testing.assert_allclose(mesh_points(marker), v[np.asarray(mesh.faces).reshape(-1)],
                                   atol=1e-5)
        assert v.shape == gt['vertices'][i].shape
        errors.append(float(np.linalg.norm(v - gt['vertices'][i], axis=1).mean()) * 1e3)
    print(f'mean per-vertex error per frame (mm): {np.round(errors, 1)}')
    assert np.mean(errors) < MEAN_ERR_MM and max(errors) < FRAME_ERR_MM, errors
    assert summary['meshes_exported'] == FRAMES


def test_sqlite_input_and_output(core, seq_msgs, cli_run, tmp_path):
    """A sqlite3 bag (the first 3 frames) in, a sqlite3 bag out: the same fits as the MCAP
    run of the console script (same core, same frames, fresh fitter: deterministic)."""
    bag = write_bag(tmp_path / 'sq', seq_msgs[:6], storage='sqlite3')
    assert storage_file(bag).suffix == '.db3'
    cfg, opts, _ = config_from_params(load_params_file(PARAMS_FILE))   # as the CLI run
    summary = process_bag(bag, tmp_path / 'out', storage='sqlite3', reconstructor=core,
                          config=replace(cfg, device='cpu'), options=opts, **QUIET)
    stamps = [t for topic, _, t, _ in seq_msgs[:6] if topic == DEPTH]
    assert summary['processed'] == 3 == summary['frames_read']
    assert storage_file(tmp_path / 'out' / 'bag').suffix == '.db3'
    _, res = check_outputs(tmp_path / 'out', summary, stamps)
    ref = dict(np.load(cli_run[0] / 'results.npz'))
    for k in ('transl', 'global_orient', 'pose', 'shape'):
        np.testing.assert_allclose(res[k], ref[k][:3], atol=1e-4, err_msg=k)


def test_messy_bag(core, seq_msgs, tmp_path):
    """Camera_info after the first frame, a duplicate, time going backwards, an undecodable
    frame, a wrong encoding, a topic of unknown type; a single .mcap file as input."""
    from rosbags.typesys import get_types_from_msg

    from smpl_depth_ros.ros import adapters as A
    store = typestore()
    store.register(get_types_from_msg('int32 a\nstring b', 'my_pkg/msg/Custom'))
    custom = store.types['my_pkg/msg/Custom']
    depth = [(t, raw) for topic, _, t, raw in seq_msgs if topic == DEPTH]
    info = [(t, raw) for topic, _, t, raw in seq_msgs if topic == INFO]
    f = A.MsgFactory(store)
    ms = 1_000_000
    mono = store.serialize_cdr(A.labels_to_image_msgs(
        np.zeros((240, 320), np.uint8), A.make_header(stamp_ns=depth[2][0] + ms,
                                                      frame_id=FRAME, msgs=f), msgs=f)[1],
        'sensor_msgs/msg/Image')
    CI, D = 'sensor_msgs/msg/CameraInfo', 'sensor_msgs/msg/Image'
    C = 'my_pkg/msg/Custom'
    msgs = [
        (DEPTH, D, depth[0][0], depth[0][1]),                       # 0: waits for its info
        ('/extra', C, depth[0][0] + 1, bytes(store.serialize_cdr(custom(a=1, b='x'), C))),
        (INFO, CI, info[1][0], info[1][1]),
        (DEPTH, D, depth[1][0], depth[1][1]),                       # 1: ok
        (INFO, CI, info[2][0], info[2][1]),
        (DEPTH, D, depth[2][0], depth[2][1]),                       # 2: ok
        (DEPTH, D, depth[2][0] + ms, depth[2][1]),                  # 3: duplicate stamp
        (DEPTH, D, depth[2][0] + 2 * ms, b'\x00\x01\x00\x00garbage'),  # 4: undecodable
        (DEPTH, D, depth[2][0] + 3 * ms, bytes(mono)),              # 5: mono8
        ('/extra', C, depth[2][0] + 4 * ms, bytes(store.serialize_cdr(custom(a=2, b='y'),
                                                                        C))),
        (INFO, CI, info[3][0], info[3][1]),
        (DEPTH, D, depth[3][0], depth[3][1]),                       # 6: ok
        (DEPTH, D, depth[3][0] + ms, depth[1][1]),                  # 7: backwards + dup
    ]
    bag = write_bag(tmp_path / 'messy', msgs, store=store)
    summary = process_bag(storage_file(bag), tmp_path / 'out', reconstructor=core,
                          config=PipelineConfig(device='cpu'), **QUIET)
    assert summary['frames_read'] == 8
    assert summary['skipped'] == {'deserialize': 1, 'encoding': 1}
    assert summary['processed'] == 6
    assert summary['duplicates'] == 2 and summary['tracking_resets_backwards'] == 1
    ok_stamps = [depth[0][0], depth[1][0], depth[2][0], depth[2][0], depth[3][0], depth[1][0]]
    decoded, res = check_outputs(tmp_path / 'out', summary, ok_stamps)
    assert list(res['status']) == ['ok', 'ok', 'ok', 'ok', 'deserialize', 'encoding', 'ok',
                                   'ok']
    assert list(res['duplicate']) == [False, False, False, True, False, False, False, True]
    assert list(res['tracking_reset']) == [False] * 7 + [True]
    assert res['stamps'][4] == -1 and not np.isfinite(res['transl'][4]).any()
    assert '16UC1' in str(res['message'][5])
    # Outputs keep the input's bag times (the late-info, duplicate and backwards frames' too).
    assert [t for t, _ in decoded['/reconstructor/mesh']] == [
        depth[0][0], depth[1][0], depth[2][0], depth[2][0] + ms, depth[3][0], depth[3][0] + ms]
    # The unknown topic is copied through with its definition and bytes.
    out_msgs = read_messages(tmp_path / 'out' / 'bag')
    assert [m for m in out_msgs if m[0] == '/extra'] == [m for m in msgs if m[0] == '/extra']
    # Skipped frames are visible in /diagnostics.
    reasons = {A.diagnostic_values(s).get('reason') for _, d in decoded['/diagnostics']
               for s in d.status if s.name.endswith(': input')}
    assert reasons == {'deserialize', 'encoding'}


@pytest.mark.parametrize('storage', ['mcap', 'sqlite3'])
def test_truncated_bag(core, seq_msgs, tmp_path, storage):
    """A bag cut at 60 %: a clear error naming the file and where, the frames before it
    processed and written, a valid output bag; the console script exits with 3."""
    bag = write_bag(tmp_path / 'cut', seq_msgs, storage=storage)
    f = storage_file(bag)
    os.truncate(f, int(f.stat().st_size * 0.6))
    summary = process_bag(bag, tmp_path / 'out', reconstructor=core,
                          config=PipelineConfig(device='cpu'), **QUIET)
    assert summary['error_file'] == str(f), summary
    assert summary['error_position'] and str(f) in summary['error']
    assert summary['recovered_damaged_input'] is True
    assert 1 <= summary['frames_read'] < FRAMES, summary
    assert summary['processed'] == summary['frames_read']
    stamps = [t for topic, _, t, _ in seq_msgs if topic == DEPTH][:summary['frames_read']]
    check_outputs(tmp_path / 'out', summary, stamps)       # the output bag opens and decodes
    if storage == 'mcap':  # the console script: exit code 3, one clear line on stderr
        import contextlib
        import io
        err = io.StringIO()
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            code = main([str(bag), '--out', str(tmp_path / 'cli'), '--device', 'cpu'])
        assert code == 3, err.getvalue()
        assert f'{f}: unreadable' in err.getvalue() and 'Traceback' not in err.getvalue()
    # Nothing readable at all: an error at open, nothing processed.
    os.truncate(f, 40)
    with pytest.raises(BagReadError, match=f.name):
        process_bag(bag, tmp_path / 'out2', reconstructor=core, **QUIET)


def test_existing_output_and_late_camera_info(core, seq_msgs, tmp_path, capsys, monkeypatch):
    """An existing output is refused without --overwrite (before any model is loaded);
    with it, our previous products are replaced and other files kept. Every frame of this
    bag comes before its camera_info: they wait for it (bounded), all accounted for."""
    depth = [m for m in seq_msgs if m[0] == DEPTH]
    info = [m for m in seq_msgs if m[0] == INFO]
    late = depth[:3] + [(INFO, info[0][1], depth[2][2] + 1, info[0][3])]
    bag = write_bag(tmp_path / 'late', late)
    out = tmp_path / 'out'
    out.mkdir()
    (out / 'summary.json').write_text('{}')
    (out / 'notes.txt').write_text('mine')
    code = main([str(bag), '--out', str(out), '--device', 'cpu'])
    err = capsys.readouterr().err
    assert code == 1 and '--overwrite' in err and 'Traceback' not in err, err
    assert (out / 'summary.json').read_text() == '{}'
    with pytest.raises(ProcessBagError, match='overlaps'):
        process_bag(bag, bag / 'inside', **QUIET)
    # At most MAX_WAITING_FOR_INFO frames wait for their camera_info; older ones are
    # skipped with the reason, the rest processed when it comes.
    monkeypatch.setattr(offline.run, 'MAX_WAITING_FOR_INFO', 2)
    summary = process_bag(bag, out, overwrite=True, reconstructor=core, **QUIET)
    assert summary['frames_read'] == 3 and summary['skipped'] == {'no_camera_info': 1}
    assert summary['processed'] == 2 and (out / 'notes.txt').read_text() == 'mine'
    _, res = check_outputs(out, summary, [m[2] for m in depth[1:3]])
    assert 'within 2 depth frames' in str(res['message'][0])
    # A camera_info (of this frame_id) that never comes: every frame skipped at the end,
    # none silently.
    from smpl_depth_ros.ros import adapters as A
    f = A.rosbags_factory()
    other = A.camera_info_msg(np.array([[285.0, 0, 160], [0, 285, 120], [0, 0, 1]]),
                              (320, 240), A.make_header(stamp_ns=depth[0][2], frame_id='other',
                                                        msgs=f), f)
    raw = f.serialize(other, 'sensor_msgs/msg/CameraInfo')
    bag = write_bag(tmp_path / 'noinfo', [(INFO, info[0][1], depth[0][2] - 1, raw)] + depth[:2])
    summary = process_bag(bag, tmp_path / 'out2', reconstructor=core, **QUIET)
    assert summary['skipped'] == {'no_camera_info': 2} and summary['processed'] == 0
    _, res = check_outputs(tmp_path / 'out2', summary, [])
    assert all('by the end of the bag' in str(m) for m in res['message'])


def test_output_ns_reaches_the_run_and_overwrite_spares_links_and_meshes(cli_run, core,
                                                                         tmp_path, capsys):
    """--output-ns is what the 'already has output topics' error advises, and it works;
    --overwrite unlinks a symlinked OUT/bag without touching its target, and leaves an
    earlier run's meshes/ when this run exports none (saying so)."""
    out0, _ = cli_run
    again = tmp_path / 'again'
    assert main([str(out0 / 'bag'), '--out', str(again), '--device', 'cpu', '--quiet']) == 1
    assert '--output-ns' in capsys.readouterr().err
    assert main([str(out0 / 'bag'), '--out', str(again), '--device', 'cpu', '--quiet',
                 '--output-ns', '/second']) == 0
    topics = {m[0] for m in read_messages(again / 'bag')}
    assert '/second/mesh' in topics and '/reconstructor/mesh' in topics
    out = tmp_path / 'out'
    out.mkdir()
    target = tmp_path / 'elsewhere'
    target.mkdir()
    (target / 'keep.txt').write_text('mine')
    (out / 'bag').symlink_to(target, target_is_directory=True)
    (out / 'meshes').mkdir()
    (out / 'meshes' / 'old.ply').write_text('x')
    seen = []
    summary = process_bag(out0 / 'bag', out, overwrite=True, reconstructor=core,
                          output_ns='/third', progress=False, log=seen.append)
    assert summary['processed'] == FRAMES
    assert (target / 'keep.txt').read_text() == 'mine' and not (out / 'bag').is_symlink()
    assert (out / 'meshes' / 'old.ply').exists()
    assert any('meshes' in m and 'left as it is' in m for m in seen), seen


def test_workers_keep_input_order(seq, tmp_path):
    """--workers 2 on chunks of 2 frames: results and outputs in input order."""
    bag, gt = seq
    summary = process_bag(bag, tmp_path / 'out', workers=2, chunk_size=2,
                          config=PipelineConfig(device='cpu'), **QUIET)
    stamps = [int(s) for s in gt['stamps']]
    assert summary['processed'] == FRAMES and summary['workers'] == 2
    assert summary['peak_rss_workers_mb'] > 0
    decoded, res = check_outputs(tmp_path / 'out', summary, stamps)
    assert list(res['stamps']) == stamps
    # Tracking restarts at each chunk: frames 0, 2, 4 are cold fits.
    assert not res['tracked'][[0, 2, 4]].any()
    corners = gt['faces'].reshape(-1)
    for i, (_, m) in enumerate(decoded['/reconstructor/mesh']):
        assert header_stamp(m) == stamps[i]
        err = np.linalg.norm(mesh_points(m) - gt['vertices'][i][corners], axis=1).mean()
        assert err * 1e3 < FRAME_ERR_MM, (i, err)  # each mesh fits its own frame


def test_interrupted_run_keeps_a_valid_bag(core, seq, tmp_path):
    """Ctrl-C in the middle: the frames done are written, the rest accounted for as
    'interrupted', the output bag is closed properly."""
    class Interrupting:
        def __init__(self, rec):
            self._rec, self.calls = rec, 0

        def __getattr__(self, name):
            return getattr(self._rec, name)

        def process(self, *a, **k):
            self.calls += 1
            if self.calls == 2:
                raise KeyboardInterrupt
            return self._rec.process(*a, **k)

    stub = Interrupting(core)
    stub.config = core.config
    summary = process_bag(seq[0], tmp_path / 'out', reconstructor=stub,
                          config=PipelineConfig(device='cpu'), **QUIET)
    assert summary['interrupted'] is True
    assert summary['processed'] == 1 and summary['skipped'] == {'interrupted': 1}
    check_outputs(tmp_path / 'out', summary, [int(seq[1]['stamps'][0])])


def test_topic_selection():
    T = Topic
    one = [T(1, DEPTH, 'sensor_msgs/msg/Image'), T(2, INFO, 'sensor_msgs/msg/CameraInfo'),
           T(3, '/odom', 'nav_msgs/msg/Odometry')]
    assert select_topics(one, None, None) == (DEPTH, INFO)
    two = one + [T(4, '/camera/color/image_raw', 'sensor_msgs/msg/Image', count=5),
                 T(5, '/camera/color/camera_info', 'sensor_msgs/msg/CameraInfo')]
    assert select_topics(two, None, None) == (DEPTH, INFO)   # 'depth' name, same namespace
    three = two + [T(6, '/cam2/depth/image', 'sensor_msgs/msg/Image', count=7)]
    with pytest.raises(ProcessBagError, match='--depth-topic') as e:
        select_topics(three, None, None)
    assert '/cam2/depth/image (7 msgs)' in str(e.value) and DEPTH in str(e.value)
    with pytest.raises(ProcessBagError, match='--info-topic'):
        select_topics(three, '/cam2/depth/image', None)
    assert select_topics(three, '/cam2/depth/image', INFO) == ('/cam2/depth/image', INFO)
    with pytest.raises(ProcessBagError, match='not in the bag'):
        select_topics(one, '/nope', None)
    with pytest.raises(ProcessBagError, match='nav_msgs/msg/Odometry'):
        select_topics(one, '/odom', None)
    with pytest.raises(ProcessBagError, match='0 sensor_msgs/msg/CameraInfo'):
        select_topics(one[:1], None, None)


def test_progress_lines_without_a_terminal():
    lines = []
    p = _Progress(10, True, lines.append, period=0.0)
    for _ in range(3):
        p.update()
    p.close()
    assert len(lines) == 3 and 'ETA' in lines[-1] and '3/10 frames' in lines[-1]
    assert 'frames/s' in lines[-1]


def test_ctrl_c_while_the_model_loads_leaves_nothing(tmp_path):
    """SIGINT during model loading: one line, exit 130, no traceback, no empty output
    folder (the run had written nothing)."""
    import signal
    import subprocess
    import sys
    bag = REPO / 'smpl_depth_ros' / 'data' / 'sample_bag'
    out = tmp_path / 'out'
    # (SIGINT at its default in the child: a shell's background job starts with it
    # ignored, and Python then keeps ignoring it)
    proc = subprocess.Popen([sys.executable, '-m', 'smpl_depth_ros.offline', str(bag),
                             '--out', str(out), '--device', 'cpu'],
                            stderr=subprocess.PIPE, text=True, cwd=str(REPO),
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    for line in proc.stderr:
        if 'loading the model' in line:
            break
    proc.send_signal(signal.SIGINT)
    err = proc.stderr.read()
    assert proc.wait(60) == offline.EXIT_INTERRUPTED, err
    assert 'Traceback' not in err and 'interrupted while loading the model' in err, err
    assert not out.exists()


def test_two_people_get_tf_trees_and_stable_ids_in_the_output_bag(tmp_path):
    """A two-person sequence (synth_bag --persons 2): the output bag's /tf holds, per
    frame, the body_<id> frame of each person (parented to the camera frame, at the
    fitted pelvis) and its joint frames; the IDs stay the same through the sequence and
    are those of ~/bodies/tracked."""
    import contextlib
    import io
    from smpl_depth_ros.tools import synth_bag
    bag = tmp_path / 'two'
    with contextlib.redirect_stdout(io.StringIO()):
        assert synth_bag.main(['--out', str(bag), '--frames', '5', '--seed', '5',
                               '--sequence', '--persons', '2']) == 0
        assert main([str(bag), '--out', str(tmp_path / 'out'), '--device', 'cpu',
                     '--quiet', '-p', 'max_persons=3']) == 0
    gt = np.load(synth_bag.gt_path(bag))
    out = read_decoded(tmp_path / 'out' / 'bag')
    tf, tracked = out['/tf'], out['/reconstructor/bodies/tracked']
    assert len(tf) == len(tracked) == 5
    ids0 = sorted(str(n) for n in tracked[0][1].name)
    assert len(ids0) == 2
    for (t, msg), (_, tr) in zip(tf, tracked):
        names = sorted(str(n) for n in tr.name)
        assert names == ids0
        frames = {x.child_frame_id: x for x in msg.transforms}
        for b in names:
            root = frames[b]
            assert root.header.frame_id == FRAME
            tid = b[len('body_'):]
            assert frames[f'head_{tid}'].header.frame_id == f'neck_{tid}'
            assert frames[f'left_hip_{tid}'].header.frame_id == b
        # each body frame sits at one true pelvis (within 15 cm)
        i = list(gt['stamps']).index(t)
        for b in names:
            p = frames[b].transform.translation
            d = np.linalg.norm(gt['joints'][i][:, 0] - [p.x, p.y, p.z], axis=1)
            assert d.min() < 0.15, d


def test_output_bags_carry_chunk_crcs_and_damaged_chunks_are_reported(cli_run, tmp_path):
    """rosbags writes no MCAP chunk CRCs; process_bag fills them in. A byte flipped inside
    a chunk of such a bag is then caught (rosbags checks the CRCs it finds): the messages
    before that chunk are read, then the reader stops with a BagReadError."""
    import shutil
    import zlib
    from smpl_depth_ros.bagio import mcap_chunks
    from smpl_depth_ros.offline import BagInput, BagReadError
    out, _ = cli_run
    f = storage_file(out / 'bag')
    buf = f.read_bytes()
    chunks = list(mcap_chunks(buf))
    assert len(chunks) >= 3
    assert all(crc != 0 and crc == zlib.crc32(rec) for _, crc, _, _, rec in chunks)
    with BagInput(out / 'bag') as src:
        n_all = sum(1 for _ in src.messages())
    bad = tmp_path / 'bad'
    shutil.copytree(out / 'bag', bad)
    _, _, t0, pos, _ = chunks[len(chunks) // 2]
    raw = bytearray(buf)
    raw[pos + 200] ^= 0xFF  # inside the chunk's (uncompressed) records
    storage_file(bad).write_bytes(bytes(raw))
    got = []
    with BagInput(bad) as src:
        with pytest.raises(BagReadError, match='checksum mismatch'):
            for _, t, _ in src.messages():
                got.append(t)
    assert 0 < len(got) < n_all and max(got) < t0


def test_a_lens_distorted_camera_is_undistorted_offline(core, tmp_path):
    """A bag of an Azure Kinect's own depth images (depth/image_raw with its
    rational_polynomial camera_info): made pinhole before use, the meshes land on the true
    bodies and the labels written to the output bag lie on the raw images' body pixels;
    the same images on a topic named image_rect are taken as rectified (said once)."""
    from smpl_depth_ros.ros import adapters as A
    from smpl_depth_ros.synth.poses import PoseSampler
    from smpl_depth_ros.synth.sensors import LENSES, SENSORS
    from smpl_depth_ros.tools.sweep import sweep_frames
    frames = list(sweep_frames(core.body, PoseSampler(core.body), SENSORS['azure_kinect_nfov'],
                               2.0, 3.0, 2, 202, lens='azure_kinect'))
    model, D = LENSES['azure_kinect']
    f = A.rosbags_factory()

    def bag(name, topic):
        msgs = []
        for i, fr in enumerate(frames):
            t = (i + 1) * 10**8
            h, w = fr['depth'].shape
            info = A.camera_info_msg(fr['K'], (w, h), A.make_header(stamp_ns=t, frame_id=FRAME,
                                                                    msgs=f), f, D=D, model=model)
            image = A.depth_to_image_msg(fr['depth'], A.make_header(stamp_ns=t, frame_id=FRAME,
                                                                    msgs=f), '16UC1', f)
            msgs += [('/k4a/depth/camera_info', 'sensor_msgs/msg/CameraInfo', t,
                      f.serialize(info, 'sensor_msgs/msg/CameraInfo')),
                     (topic, 'sensor_msgs/msg/Image', t,
                      f.serialize(image, 'sensor_msgs/msg/Image'))]
        return write_bag(tmp_path / name, msgs)
    said = []
    summary = process_bag(bag('raw', '/k4a/depth/image_raw'), tmp_path / 'out',
                          reconstructor=core, progress=False, log=said.append)
    assert summary['processed'] == 2
    assert sum('made pinhole before use' in m for m in said) == 1, said
    out = read_decoded(tmp_path / 'out' / 'bag')
    labels, meshes = out['/reconstructor/segmentation/labels'], out['/reconstructor/mesh']
    faces = core.body.faces_numpy().reshape(-1)
    for k, fr in enumerate(frames):
        v = np.full(fr['vertices'].shape, np.nan)
        v[faces] = mesh_points(meshes[k][1])
        assert np.nanmean(np.linalg.norm(v - fr['vertices'], axis=1)) < 0.04
        ours, truth = A.image_to_array(labels[k][1]) > 0, fr['labels'] > 0
        assert ours.shape == truth.shape and (ours & truth).sum() / (ours | truth).sum() > 0.7
    said.clear()
    process_bag(bag('rect', '/k4a/depth/image_rect'), tmp_path / 'out2', reconstructor=core,
                progress=False, log=said.append)
    assert sum('taken as rectified' in m for m in said) == 1, said
