"""synth_bag and bagio: real rosbag2 bags in tmp_path, read back with rosbags (no ROS)."""
import json

import numpy as np
import pytest
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore

from smpl_depth_ros import bagio, depth_codec
from smpl_depth_ros.synth.camera import CAMERAS
from smpl_depth_ros.tools import synth_bag

ARGS = ['--frames', '3', '--seed', '5', '--width', '160', '--height', '120']


def _read(path):
    out = {bagio.DEPTH_TOPIC: [], bagio.INFO_TOPIC: []}
    with AnyReader([path], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as reader:
        for conn, t, raw in reader.messages():
            msg = reader.deserialize(raw, conn.msgtype)
            out[conn.topic].append((t, msg, conn.msgtype))
    return out


@pytest.fixture(scope='module')
def bags(tmp_path_factory):
    root = tmp_path_factory.mktemp('bags')
    paths = {}
    for storage in ('mcap', 'sqlite3'):
        for enc in ('16UC1', '32FC1'):
            p = root / f'{storage}_{enc}'
            assert synth_bag.main(['--out', str(p), '--storage', storage, '--encoding', enc]
                                  + ARGS) == 0
            paths[storage, enc] = p
    return paths


@pytest.mark.parametrize('storage', ['mcap', 'sqlite3'])
def test_round_trip(bags, storage):
    depths = {}
    for enc in ('16UC1', '32FC1'):
        path = bags[storage, enc]
        gt = np.load(synth_bag.gt_path(str(path)))
        msgs = _read(path)
        imgs, infos = msgs[bagio.DEPTH_TOPIC], msgs[bagio.INFO_TOPIC]
        assert len(imgs) == len(infos) == 3 == len(gt['stamps'])
        stamps = []
        for (t, img, typ), (t2, info, typ2) in zip(imgs, infos):
            assert typ == 'sensor_msgs/msg/Image' and typ2 == 'sensor_msgs/msg/CameraInfo'
            s = img.header.stamp.sec * 1_000_000_000 + img.header.stamp.nanosec
            assert s == t == t2
            assert info.header.stamp == img.header.stamp
            assert img.header.frame_id == info.header.frame_id == bagio.FRAME_ID
            assert img.encoding == enc and img.is_bigendian == 0
            assert (img.width, img.height) == (160, 120) == (info.width, info.height)
            assert img.step == 160 * (2 if enc == '16UC1' else 4)
            np.testing.assert_allclose(info.k.reshape(3, 3), gt['K'])
            np.testing.assert_allclose(info.p.reshape(3, 4)[:, :3], gt['K'])
            np.testing.assert_array_equal(info.r.reshape(3, 3), np.eye(3))
            assert info.distortion_model == 'plumb_bob' and not np.any(info.d)
            stamps.append(s)
        np.testing.assert_array_equal(stamps, gt['stamps'])
        # 1/rate apart without drift: start + round(i * 1e9 / rate)
        np.testing.assert_array_equal(gt['stamps'] - gt['stamps'][0],
                                      [round(i * 1e9 / 30) for i in range(3)])
        depths[enc] = np.stack([depth_codec.bytes_to_depth(m.data, m.width, m.height,
                                                           m.encoding, m.step, m.is_bigendian)
                                for _, m, _ in imgs])
        # Ground truth lines up with the depth.
        assert gt['labels'].shape == gt['vertex_ids'].shape == (3, 120, 160)
        assert (gt['labels'][depths[enc] == 0] == 0).all()
        assert (gt['vertex_ids'][depths[enc] == 0] == -1).all()
        assert (gt['vertex_ids'] >= 0).sum() > 100
    np.testing.assert_array_equal(depths['16UC1'] > 0, depths['32FC1'] > 0)
    assert np.abs(depths['16UC1'] - depths['32FC1']).max() <= 0.0005 + 1e-6


def test_gt_sidecar_contents(bags):
    gt = np.load(synth_bag.gt_path(str(bags['mcap', '16UC1'])))
    N, V = 3, gt['vertices'].shape[1]
    assert gt['vertices'].shape == (N, V, 3) and gt['vertices'].dtype == np.float32
    assert gt['faces'].max() == V - 1
    J = len(gt['joint_names'])
    assert gt['joints'].shape == (N, J, 3) and gt['pose'].shape == (N, J - 1, 3)
    assert gt['global_orient'].shape == gt['transl'].shape == (N, 3)
    assert gt['shape'].ndim == 2 and gt['stamps'].dtype == np.int64
    assert str(gt['body_model']) == 'anny' and str(gt['topology']).startswith('anny')
    assert int(gt['seed']) == 5 and str(gt['camera']) == 'kinect_v1'
    assert (int(gt['width']), int(gt['height'])) == (160, 120)
    assert gt['vertex_ids'].dtype == np.int32 and gt['labels'].dtype == np.uint8
    assert gt['stamps'][0] == synth_bag.start_stamp_ns(5)
    # Same seed and settings -> same ground truth in every bag.
    gt2 = np.load(synth_bag.gt_path(str(bags['sqlite3', '32FC1'])))
    np.testing.assert_array_equal(gt['vertices'], gt2['vertices'])
    np.testing.assert_array_equal(gt['vertex_ids'], gt2['vertex_ids'])


def test_sequence_bag_and_iter(tmp_path, capsys):
    out = tmp_path / 'seq'
    assert synth_bag.main(['--out', str(out), '--sequence', '--no-noise', '--rate', '10']
                          + ARGS) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary['frames'] == 3 and summary['path'] == str(out)
    gt = np.load(synth_bag.gt_path(str(out)))
    read = list(bagio.iter_depth_bag(out))
    assert [s for s, _, _ in read] == gt['stamps'].tolist()
    assert np.all(np.diff(gt['stamps']) == 100_000_000)
    for (_, depth, K), vids in zip(read, gt['vertex_ids']):
        np.testing.assert_allclose(K, gt['K'])
        assert ((vids >= 0) <= (depth > 0)).all()
    assert np.linalg.norm(np.diff(gt['joints'][:, 0], axis=0), axis=1).max() < 0.1
    # Refuses to overwrite.
    assert synth_bag.main(['--out', str(out)] + ARGS) == 2


def test_write_depth_bag_helper(tmp_path):
    cam = CAMERAS['oak_d'].scaled(64, 40)
    rng = np.random.default_rng(0)
    frames = [(1_000 + i, np.where(rng.random((40, 64)) < 0.2, 0,
                                   rng.uniform(0.3, 9, (40, 64))).astype(np.float32))
              for i in range(4)]
    for enc in ('16UC1', '32FC1'):
        p = tmp_path / enc
        assert bagio.write_depth_bag(p, iter(frames), cam, enc, 'sqlite3') == 4
        for (s, d, K), (s0, d0) in zip(bagio.iter_depth_bag(p), frames):
            assert s == s0
            np.testing.assert_allclose(K, cam.K)
            np.testing.assert_allclose(d, d0, atol=0.0005 + 1e-6 if enc == '16UC1' else 0)
    with pytest.raises(ValueError):
        bagio.write_depth_bag(tmp_path / 'bad', iter(frames), CAMERAS['oak_d'])


def test_bytes_round_trip_padding_and_endianness():
    d = np.array([[0.0, 1.2346], [np.nan, 65.6]], np.float32)
    data, step = depth_codec.depth_to_bytes(d, '16UC1', nan_invalid=True, bigendian=True)
    back = depth_codec.bytes_to_depth(data, 2, 2, '16UC1', step, bigendian=True)
    np.testing.assert_allclose(back, [[0, 1.235], [0, 65.535]], atol=1e-6)
    data, step = depth_codec.depth_to_bytes(d, '32FC1', nan_invalid=True)
    padded = np.zeros((2, step + 4), np.uint8)
    padded[:, :step] = data.reshape(2, step)
    back = depth_codec.bytes_to_depth(padded.reshape(-1), 2, 2, '32FC1', step + 4)
    np.testing.assert_array_equal(back, np.nan_to_num(d, nan=0.0))
    with pytest.raises(ValueError):
        depth_codec.bytes_to_depth(data[:-1], 2, 2, '32FC1')


def test_sensor_preset_bags(tmp_path, capsys):
    """--sensor takes the preset's camera and noise model; --poses broad and
    --depth-range reach the frames; both are recorded in the ground truth."""
    out = tmp_path / 'd435'
    assert synth_bag.main(['--out', str(out), '--frames', '2', '--seed', '3', '--sensor',
                           'realsense_d435', '--width', '424', '--height', '240',
                           '--poses', 'broad', '--depth-range', '3.0', '3.5',
                           '--strength', '1.5']) == 0
    info = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert info['sensor'] == 'realsense_d435' and info['size'] == [424, 240]
    gt = np.load(synth_bag.gt_path(str(out)))
    assert str(gt['sensor']) == 'realsense_d435' and str(gt['poses']) == 'broad'
    assert float(gt['strength']) == 1.5
    root = gt['joints'][:, 0, 2]
    assert ((root > 2.95) & (root < 3.55)).all(), root
    msgs = _read(out)
    assert msgs[bagio.INFO_TOPIC][0][1].k[0] == pytest.approx(212.0)
    # a depth range the camera cannot see is refused, not silently clipped
    assert synth_bag.main(['--out', str(tmp_path / 'az'), '--sensor', 'azure_kinect_nfov',
                           '--depth-range', '4.5', '5.0']) == 2
