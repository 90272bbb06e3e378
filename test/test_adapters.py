"""Message <-> array adapters, for rclpy messages and rosbags dataclasses alike.

Every message built here also goes through its system's serialiser (rclpy's
`serialize_message` / rosbags' `serialize_cdr`) and back, so the tests see what a
subscriber or a bag reader would see. rclpy needs no running context for that.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from smpl_depth_ros.body.parts import labels_to_rgb
from smpl_depth_ros.ros import adapters as A
from smpl_depth_ros.ros import body_msgs, markers
from smpl_depth_ros.stamps import cdr_stamp_ns, stamp_to_ns
from smpl_depth_ros.types import BodyParams, InputError

rclpy_serialization = pytest.importorskip('rclpy.serialization')

ROSBAGS = A.rosbags_factory()
SYSTEMS = {'rclpy': A.as_factory(None), 'rosbags': ROSBAGS}
MSGTYPES = {
    'Image': 'sensor_msgs/msg/Image', 'CameraInfo': 'sensor_msgs/msg/CameraInfo',
    'JointState': 'sensor_msgs/msg/JointState', 'Marker': 'visualization_msgs/msg/Marker',
    'MarkerArray': 'visualization_msgs/msg/MarkerArray',
    'DiagnosticArray': 'diagnostic_msgs/msg/DiagnosticArray',
}


def wire(msg, f: A.MsgFactory):
    """Serialise and deserialise `msg` in its own system."""
    name = type(msg).__name__.split('__')[-1]
    msgtype = MSGTYPES[name]
    if f.is_rosbags:
        ts = f.typestore
        return ts.deserialize_cdr(ts.serialize_cdr(msg, msgtype), msgtype)
    raw = rclpy_serialization.serialize_message(msg)
    return rclpy_serialization.deserialize_message(raw, f.cls(msgtype))


@pytest.fixture(params=list(SYSTEMS))
def msgs(request) -> A.MsgFactory:
    return SYSTEMS[request.param]


def _depth(h=37, w=53, seed=0):
    rng = np.random.default_rng(seed)
    d = rng.uniform(0.4, 7.5, (h, w)).astype(np.float32)
    d[rng.random((h, w)) < 0.1] = 0.0
    return d


# -- depth images ----------------------------------------------------------------------
@pytest.mark.parametrize('encoding', ['16UC1', '32FC1'])
@pytest.mark.parametrize('bigendian', [False, True])
@pytest.mark.parametrize('pad', [0, 7])
def test_depth_round_trip(msgs, encoding, bigendian, pad):
    d = _depth()
    bpp = 2 if encoding == '16UC1' else 4
    step = d.shape[1] * bpp + pad
    hdr = A.make_header(stamp_ns=1_700_000_000_123_456_789, frame_id='cam', msgs=msgs)
    m = wire(A.depth_to_image_msg(d, hdr, encoding, msgs, step=step, bigendian=bigendian),
             msgs)
    assert (m.encoding, m.width, m.height, m.step, bool(m.is_bigendian)) == \
        (encoding, d.shape[1], d.shape[0], step, bigendian)
    assert stamp_to_ns(m.header.stamp) == 1_700_000_000_123_456_789
    assert m.header.frame_id == 'cam'
    out = A.image_to_depth(m)
    assert out.dtype == np.float32 and out.shape == d.shape
    if encoding == '16UC1':
        np.testing.assert_allclose(out, np.round(d * 1000) / 1000, atol=1e-6)
    else:
        np.testing.assert_array_equal(out, d)


def test_depth_mm_message(msgs):
    """Sensor millimetres go out as they are (no trip through metres)."""
    mm = np.random.default_rng(2).integers(0, 65536, (5, 7)).astype(np.uint16)
    m = wire(A.depth_mm_to_image_msg(mm, A.make_header(stamp_ns=3, frame_id='cam', msgs=msgs),
                                     msgs), msgs)
    assert (m.encoding, m.width, m.height, m.step) == ('16UC1', 7, 5, 14)
    np.testing.assert_array_equal(A.image_to_depth(m), mm.astype(np.float32) * 0.001)
    with pytest.raises(ValueError):
        A.depth_mm_to_image_msg(mm.astype(np.float32))


def test_depth_reader_against_hand_made_bytes(msgs):
    """Big-endian 16UC1 with a padded step, bytes written by hand (not by our writer)."""
    rows = [np.array([1000, 2500, 0], '>u2').tobytes() + b'\xff\xff',
            np.array([65535, 1, 300], '>u2').tobytes() + b'\xff\xff']
    data = np.frombuffer(b''.join(rows), np.uint8)
    m = msgs.new('sensor_msgs/msg/Image', height=2, width=3, encoding='16UC1',
                 is_bigendian=1, step=8, data=msgs.seq(data, np.uint8))
    np.testing.assert_allclose(A.image_to_depth(m), [[1.0, 2.5, 0.0], [65.535, 0.001, 0.3]],
                               rtol=1e-6)
    le = np.frombuffer(np.array([1.5, np.nan, -2.0, np.inf], '<f4').tobytes(), np.uint8)
    m = msgs.new('sensor_msgs/msg/Image', height=1, width=4, encoding='32FC1',
                 is_bigendian=0, step=16, data=msgs.seq(le, np.uint8))
    # Invalid samples (NaN, inf, negative) read as 0.
    np.testing.assert_array_equal(A.image_to_depth(m), [[1.5, 0.0, 0.0, 0.0]])


def test_16uc1_writer_clips_and_zeros_invalid(msgs):
    d = np.array([[np.nan, -1.0, 70.0, 1.2344]], np.float32)
    out = A.image_to_depth(A.depth_to_image_msg(d, None, '16UC1', msgs))
    np.testing.assert_allclose(out, [[0.0, 0.0, 65.535, 1.234]], atol=1e-6)


@pytest.mark.parametrize('encoding', ['rgb8', 'mono8', '16SC1', 'bgr8', '', '64FC1'])
def test_wrong_encoding(msgs, encoding):
    m = A.depth_to_image_msg(_depth(), None, '16UC1', msgs)
    m.encoding = encoding
    with pytest.raises(InputError) as e:
        A.image_to_depth(m)
    assert e.value.reason == 'encoding'
    assert f"'{encoding}'" in str(e.value) and '16UC1' in str(e.value) and \
        '32FC1' in str(e.value)


def test_size_errors(msgs):
    m = A.depth_to_image_msg(_depth(), None, '32FC1', msgs)
    m.step = m.width * 4 - 1
    with pytest.raises(InputError, match='step') as e:
        A.image_to_depth(m)
    assert e.value.reason == 'size_mismatch'
    m = A.depth_to_image_msg(_depth(), None, '32FC1', msgs)
    m.data = m.data[:len(m.data) - 4]
    with pytest.raises(InputError, match='bytes') as e:
        A.image_to_depth(m)
    assert e.value.reason == 'size_mismatch'
    m.height, m.width = 0, 0
    with pytest.raises(InputError, match='empty') as e:
        A.image_to_depth(m)
    assert e.value.reason == 'size_mismatch'
    m = A.depth_to_image_msg(_depth(100, 120), None, '16UC1', msgs)
    with pytest.raises(InputError) as e:
        A.image_to_depth(m, max_pixels=100 * 119)
    assert e.value.reason == 'too_large' and '120x100' in str(e.value)
    assert A.image_to_depth(m, max_pixels=100 * 120).shape == (100, 120)
    # Padded rows: the last row needs no padding, and the message says what is needed.
    d = _depth(3, 4)
    m = A.depth_to_image_msg(d, None, '16UC1', msgs)
    raw = np.asarray(m.data, np.uint8).reshape(3, 8)
    m.step = 12
    m.data = np.concatenate([raw[0], [0] * 4, raw[1], [0] * 4, raw[2]]).astype(np.uint8)
    np.testing.assert_allclose(A.image_to_depth(m), A.image_to_depth(
        A.depth_to_image_msg(d, None, '16UC1', msgs)))
    m.data = m.data[:-1]
    with pytest.raises(InputError, match='needs at least 32 bytes') as e:
        A.image_to_depth(m)
    assert 'got 31' in str(e.value)


def test_strided_array_as_image_data(msgs):
    """A sliced (non-contiguous) numpy array as Image.data reads like its copy."""
    d = _depth(6, 10)
    m = A.depth_to_image_msg(d, None, '16UC1', msgs)
    raw = np.asarray(m.data, np.uint8)
    spread = np.zeros(raw.size * 2, np.uint8)
    spread[::2] = raw
    m.data = spread[::2]  # rosbags messages keep it as it is; rclpy copies it
    assert not isinstance(m.data, np.ndarray) or not m.data.flags['C_CONTIGUOUS']
    np.testing.assert_array_equal(A.image_to_depth(m), A.image_to_depth(
        A.depth_to_image_msg(d, None, '16UC1', msgs)))


# -- camera info -----------------------------------------------------------------------
def test_camera_info(msgs):
    K = np.array([[525.0, 0, 319.5], [0, 526.0, 239.5], [0, 0, 1]])
    D = [0.1, -0.2, 0.0, 0.0, 0.01]
    hdr = A.make_header(stamp_ns=5, frame_id='cam', msgs=msgs)
    m = wire(A.camera_info_msg(K, (640, 480), hdr, msgs, D=D), msgs)
    K2, D2, size = A.camera_info_to_K(m)
    np.testing.assert_array_equal(K2, K)
    np.testing.assert_array_equal(D2, D)
    assert size == (640, 480)
    m = wire(A.camera_info_msg(K, (640, 480), hdr, msgs), msgs)
    assert A.camera_info_to_K(m)[1].size == 0


def test_camera_info_lens(msgs):
    """The lens of a camera_info (model, D, P) and what its depth topic's name says:
    none for a camera without distortion, P for the rectified image (K when P is unset)."""
    K = np.array([[504.0, 0, 320.0], [0, 504.0, 288.0], [0, 0, 1]])
    D = [4.7, 3.2, 0.0, 0.0001, 0.17, 5.1, 4.8, 0.89]
    m = wire(A.camera_info_msg(K, (640, 576), None, msgs, D=D, model='rational_polynomial'),
             msgs)
    m.p = np.array([[500.0, 0, 321, 0], [0, 500.0, 290, 0], [0, 0, 1, 0]]).reshape(-1)
    cam = A.camera_info_intrinsics(m)
    np.testing.assert_array_equal(cam.K, K)
    assert cam.P[0, 0] == 500.0 and cam.P[1, 2] == 290.0 and cam.size == (640, 576)
    raw, rect = cam.lens('/k4a/depth/image_raw'), cam.lens('/k4a/depth/image_rect')
    assert raw.model == 'rational_polynomial' and list(raw.D) == D
    assert raw.undo('auto') and not rect.undo('auto') and rect.undo('always')
    m.p = np.zeros(12)
    np.testing.assert_array_equal(A.camera_info_intrinsics(m).P, K)
    plain = wire(A.camera_info_msg(K, (640, 576), None, msgs, D=np.zeros(5)), msgs)
    assert A.camera_info_intrinsics(plain).lens('/depth/image_raw') is None


def test_camera_info_bad_K(msgs):
    m = A.camera_info_msg(np.zeros((3, 3)), (640, 480), None, msgs)
    with pytest.raises(InputError, match='all zeros') as e:
        A.camera_info_to_K(m)
    assert e.value.reason == 'bad_intrinsics'
    K = np.array([[-5.0, 0, 3], [0, 5, 3], [0, 0, 1]])
    with pytest.raises(InputError) as e:
        A.camera_info_to_K(A.camera_info_msg(K, (6, 6), None, msgs))
    assert e.value.reason == 'bad_intrinsics'
    # A last row other than [0, 0, 1] (negated, tiny, infinite): rejected, and the message
    # shows the values as they were given, not rescaled ones.
    for k22 in (-1.0, 1e-12, np.inf, 2.0):
        K = np.array([[525.0, 0, 320], [0, 525, 240], [0, 0, k22]])
        with pytest.raises(InputError) as e:
            A.camera_info_to_K(A.camera_info_msg(K, (640, 480), None, msgs))
        assert e.value.reason == 'bad_intrinsics'
        assert '525.0' in str(e.value) and repr(float(k22)).replace('inf', 'inf') in str(e.value)


# -- segmentation ----------------------------------------------------------------------
def test_labels_to_image_msgs(msgs):
    labels = np.random.default_rng(1).integers(0, 15, (21, 33)).astype(np.uint8)
    hdr = A.make_header(stamp_ns=42, frame_id='cam', msgs=msgs)
    rgb, ids = (wire(m, msgs) for m in A.labels_to_image_msgs(labels, hdr, msgs))
    assert (rgb.encoding, rgb.width, rgb.height, rgb.step) == ('rgb8', 33, 21, 99)
    assert (ids.encoding, ids.width, ids.height, ids.step) == ('mono8', 33, 21, 33)
    for m in (rgb, ids):
        assert stamp_to_ns(m.header.stamp) == 42 and m.header.frame_id == 'cam'
    np.testing.assert_array_equal(A.image_to_array(rgb), labels_to_rgb(labels))
    np.testing.assert_array_equal(A.image_to_array(ids), labels)


# -- markers ---------------------------------------------------------------------------
@pytest.fixture(scope='module')
def anny():
    from smpl_depth_ros.body.anny_model import AnnyBody
    return AnnyBody()


@pytest.fixture(scope='module')
def anny_posed(anny):
    with torch.no_grad():
        out = anny(**anny.zero_params(1))
    return out.vertices[0].numpy(), out.joints[0].numpy()


def test_mesh_marker(msgs, anny, anny_posed):
    v, _ = anny_posed
    faces = anny.faces_numpy()
    hdr = A.make_header(stamp_ns=7, frame_id='cam', msgs=msgs)
    m = wire(markers.mesh_marker(v, faces, hdr, ns='mesh', id=3, lifetime_s=1.25, msgs=msgs), msgs)
    M = msgs.cls('visualization_msgs/msg/Marker')
    assert m.type == M.TRIANGLE_LIST and m.action == M.ADD and (m.ns, m.id) == ('mesh', 3)
    assert (m.lifetime.sec, m.lifetime.nanosec) == (1, 250_000_000)
    assert stamp_to_ns(m.header.stamp) == 7 and m.header.frame_id == 'cam'
    assert m.pose.orientation.w == 1.0 and m.color.a > 0
    pts = np.array([[p.x, p.y, p.z] for p in m.points])
    assert len(pts) == 3 * len(faces)
    np.testing.assert_allclose(pts, v[faces.reshape(-1)], atol=1e-6)


def test_decimation(anny, anny_posed):
    v, _ = anny_posed
    faces = anny.faces_numpy()
    for target in (2000, 1200, 500, 100):
        d = markers.decimate_faces(v, faces, target)
        assert 0.5 * target < len(d) <= target
        assert d.min() >= 0 and d.max() < len(v)
        assert np.all((d[:, 0] != d[:, 1]) & (d[:, 1] != d[:, 2]) & (d[:, 0] != d[:, 2]))
        np.testing.assert_array_equal(d, markers.decimate_faces(v, faces, target))  # deterministic
    assert markers.decimate_faces(v, faces, len(faces)) is not None
    np.testing.assert_array_equal(markers.decimate_faces(v, faces, 10 ** 6), faces)
    m = markers.mesh_marker(v, faces, None, decimate_faces=1000)
    assert len(m.points) == 3 * len(markers.decimate_faces(v, faces, 1000))


def test_skeleton_markers(msgs, anny, anny_posed):
    _, j = anny_posed
    parents = anny.joint_parents.numpy()
    hdr = A.make_header(stamp_ns=9, frame_id='cam', msgs=msgs)
    arr = wire(markers.skeleton_markers(j, parents, hdr, msgs=msgs), msgs)
    M = msgs.cls('visualization_msgs/msg/Marker')
    spheres = [m for m in arr.markers if m.type == M.SPHERE_LIST]
    lines = [m for m in arr.markers if m.type == M.LINE_LIST]
    assert len(spheres) == len(lines) == 1
    assert len(spheres[0].points) == len(j)
    assert len(lines[0].points) == 2 * int((parents >= 0).sum())
    assert all(m.header.frame_id == 'cam' for m in arr.markers)
    seg = np.array([[p.x, p.y, p.z] for p in lines[0].points]).reshape(-1, 2, 3)
    child = np.flatnonzero(parents >= 0)
    np.testing.assert_allclose(seg[:, 0], j[child], atol=1e-6)
    np.testing.assert_allclose(seg[:, 1], j[parents[child]], atol=1e-6)


# -- body parameters -------------------------------------------------------------------
def _random_params(body, seed=0) -> BodyParams:
    rng = np.random.default_rng(seed)
    return BodyParams(pose=rng.normal(0, 0.3, (body.num_pose_joints, 3)).astype(np.float32),
                      shape=rng.uniform(0, 1, body.num_shape).astype(np.float32),
                      global_orient=rng.normal(0, 1, 3).astype(np.float32),
                      transl=rng.normal(0, 2, 3).astype(np.float32))


def _check_params_round_trip(body, msgs):
    p = _random_params(body)
    hdr = A.make_header(stamp_ns=11, frame_id='cam', msgs=msgs)
    m = wire(body_msgs.params_to_joint_state(p, body, hdr, msgs), msgs)
    assert stamp_to_ns(m.header.stamp) == 11 and m.header.frame_id == 'cam'
    names = list(m.name)
    assert names[:6] == ['transl.x', 'transl.y', 'transl.z',
                         'global_orient.rx', 'global_orient.ry', 'global_orient.rz']
    assert names[6:9] == [f'{body.joint_names[1]}.{a}' for a in ('rx', 'ry', 'rz')]
    assert names[-body.num_shape:] == [f'shape.{s}' for s in body.shape_names]
    assert len(m.position) == len(names) == 6 + 3 * body.num_pose_joints + body.num_shape
    assert len(m.velocity) == 0 and len(m.effort) == 0
    d = body_msgs.joint_state_to_params(m)
    assert d['joint_names'] == tuple(body.joint_names[1:])
    assert d['shape_names'] == tuple(body.shape_names)
    for k in ('pose', 'shape', 'global_orient', 'transl'):
        np.testing.assert_array_equal(d[k], getattr(p, k))  # float32 -> float64 -> float32
    # The decoded arrays drive the body model directly.
    with torch.no_grad():
        out = body(torch.as_tensor(d['pose'])[None], torch.as_tensor(d['shape'])[None],
                   torch.as_tensor(d['global_orient'])[None], torch.as_tensor(d['transl'])[None])
    assert out.vertices.shape == (1, body.num_vertices, 3)


def test_joint_state_round_trip_anny(msgs, anny):
    _check_params_round_trip(anny, msgs)


def test_joint_state_round_trip_smpl(msgs, tmp_path_factory):
    pytest.importorskip('smpl_depth_ros.body.smpl_model')
    helpers = Path(__file__).with_name('test_smpl_backend.py')
    if not helpers.exists():
        pytest.skip('the SMPL test helpers (test_smpl_backend.make_model) are not there')
    from test_smpl_backend import make_model
    from smpl_depth_ros.body.smpl_model import SMPLBody
    path = tmp_path_factory.mktemp('smpl') / 'SMPL_NEUTRAL.npz'
    np.savez(path, **make_model())
    body = SMPLBody(str(path))
    assert body.name == 'smpl'
    _check_params_round_trip(body, msgs)


def test_joint_state_accepts_person_result(anny):
    from smpl_depth_ros.types import PersonResult
    p = _random_params(anny, 2)
    person = PersonResult(params=p, vertices=np.zeros((anny.num_vertices, 3), np.float32),
                          joints=np.zeros((len(anny.joint_names), 3), np.float32),
                          bbox=(0, 0, 1, 1), mask=np.zeros((2, 2), bool), residual_m=0.01,
                          num_points=10)
    d = body_msgs.joint_state_to_params(body_msgs.params_to_joint_state(person, anny))
    np.testing.assert_array_equal(d['pose'], p.pose)


def test_joint_state_decoder_errors(msgs, anny):
    m = body_msgs.params_to_joint_state(_random_params(anny), anny, None, msgs)
    bad = msgs.new('sensor_msgs/msg/JointState', name=list(m.name),
                   position=msgs.seq(np.asarray(m.position)[:-1], np.float64))
    with pytest.raises(ValueError, match='positions'):
        body_msgs.joint_state_to_params(bad)
    names = [n for n in m.name if n != 'left_knee.ry']
    pos = [x for n, x in zip(m.name, m.position) if n != 'left_knee.ry']
    bad = msgs.new('sensor_msgs/msg/JointState', name=names,
                   position=msgs.seq(pos, np.float64))
    with pytest.raises(ValueError, match='left_knee.ry'):
        body_msgs.joint_state_to_params(bad)
    with pytest.raises(ValueError, match='joints'):
        body_msgs.params_to_joint_state(BodyParams(np.zeros((3, 3)), np.zeros(6),
                                                   np.zeros(3), np.zeros(3)), anny)


# -- diagnostics and headers -----------------------------------------------------------
def test_diagnostics(msgs):
    hdr = A.make_header(stamp_ns=3_000_000_001, msgs=msgs)
    arr = wire(A.diagnostics(hdr, [('node: input', A.WARN, 'bad', {'reason': 'encoding',
                                                                   'count': 3, 'ok': True,
                                                                   'latency_ms': 12.3456})],
                             msgs), msgs)
    assert stamp_to_ns(arr.header.stamp) == 3_000_000_001
    (s,) = arr.status
    assert A.diagnostic_level(s) == A.WARN and s.name == 'node: input' and s.message == 'bad'
    assert A.diagnostic_values(s) == {'reason': 'encoding', 'count': '3', 'ok': 'true',
                                      'latency_ms': '12.35'}


def test_headers_cross_systems():
    rb = A.make_header(stamp_ns=12_345_678_901, frame_id='cam', msgs=ROSBAGS)
    rc = A.make_header(rb)  # a rosbags header into an rclpy message
    assert type(rc).__module__.startswith('std_msgs')
    assert stamp_to_ns(rc.stamp) == 12_345_678_901 and rc.frame_id == 'cam'
    m = A.depth_to_image_msg(np.ones((2, 2)), rb)  # rclpy image, rosbags header
    assert m.header.frame_id == 'cam'
    with pytest.raises(TypeError):
        A.as_factory(42)


@pytest.mark.parametrize('n', [0, 1, 7, 7362])
@pytest.mark.parametrize('kind', ['rosbags', 'rclpy'])
def test_marker_cdr_equals_full_serialisation(n, kind):
    f = A.rosbags_factory() if kind == 'rosbags' else A.as_factory(None)
    xyz = np.random.default_rng(n).normal(size=(n, 3))
    m = markers.mesh_marker(np.zeros((0, 3)), np.zeros((0, 3), np.int64), msgs=f,
                            header=A.make_header(None, f, stamp_ns=123456789012, frame_id='cam'))
    fast = markers.marker_cdr(m, xyz, f)
    m.points = f.points(xyz)
    full = f.serialize(m, 'visualization_msgs/msg/Marker')
    if kind == 'rosbags':
        assert fast == full
    # (rclpy's serializer leaves padding bytes uninitialised: compare decoded messages.)
    ts = A.rosbags_factory().typestore
    back, ref = (ts.deserialize_cdr(b, 'visualization_msgs/msg/Marker') for b in (fast, full))
    assert len(back.points) == n and back.header.frame_id == 'cam'
    assert back.points == ref.points and back.header == ref.header
    assert (back.ns, back.id, back.type, back.color, back.scale, back.lifetime) == \
        (ref.ns, ref.id, ref.type, ref.color, ref.scale, ref.lifetime)


def test_cdr_stamp_ns_reads_the_header_of_serialized_messages(msgs, anny, anny_posed):
    v, _ = anny_posed
    hdr = A.make_header(stamp_ns=1_700_000_123_000_000_042, frame_id='cam', msgs=msgs)
    for m, t in ((markers.mesh_marker(v, anny.faces_numpy(), hdr, ns='mesh', id=0,
                                      msgs=msgs),
                  'visualization_msgs/msg/Marker'),
                 (A.depth_to_image_msg(np.ones((4, 5), np.float32), header=hdr, msgs=msgs),
                  'sensor_msgs/msg/Image')):
        assert cdr_stamp_ns(msgs.serialize(m, t)) == 1_700_000_123_000_000_042
    with pytest.raises(ValueError):
        cdr_stamp_ns(b'\x00')


@pytest.mark.parametrize('kind', ['rosbags', 'rclpy'])
def test_marker_array_cdr_equals_full_serialisation(kind):
    f = A.rosbags_factory() if kind == 'rosbags' else A.as_factory(None)
    rng = np.random.default_rng(0)
    blocks = [rng.normal(size=(n, 3)) for n in (5, 0, 301)]
    h = A.make_header(None, f, stamp_ns=5, frame_id='cam')
    marks = [markers.mesh_marker(np.zeros((0, 3)), np.zeros((0, 3), np.int64), h, id=i, msgs=f)
             for i in range(3)] + markers.delete_markers([('body_mesh', 9)], h, msgs=f)
    arr = f.new('visualization_msgs/msg/MarkerArray', markers=marks)
    fast = markers.marker_array_cdr(arr, blocks, f)
    for m, b in zip(arr.markers, blocks):
        m.points = f.points(b)
    full = f.serialize(arr, 'visualization_msgs/msg/MarkerArray')
    if kind == 'rosbags':
        assert fast == full
    ts = A.rosbags_factory().typestore
    back, ref = (ts.deserialize_cdr(b, 'visualization_msgs/msg/MarkerArray')
                 for b in (fast, full))
    assert [len(m.points) for m in back.markers] == [5, 0, 301, 0]
    assert [m.points for m in back.markers] == [m.points for m in ref.markers]
    assert [(m.id, m.action, m.ns) for m in back.markers] == \
        [(m.id, m.action, m.ns) for m in ref.markers]


@pytest.mark.parametrize('kind', ['rosbags', 'rclpy'])
def test_bodies_params_round_trip_with_ids_and_confidence(anny, kind):
    from types import SimpleNamespace
    f = SYSTEMS[kind]
    rng = np.random.default_rng(1)
    P, S, J = anny.num_pose_joints, anny.num_shape, len(anny.joint_names)
    persons = [SimpleNamespace(
        params=BodyParams(pose=rng.normal(size=(P, 3)).astype(np.float32),
                          shape=rng.normal(size=S).astype(np.float32),
                          global_orient=rng.normal(size=3).astype(np.float32),
                          transl=rng.normal(size=3).astype(np.float32)),
        track_id=tid, joint_confidence=rng.uniform(size=J).astype(np.float32))
        for tid in (3, 11)]
    msg = wire(body_msgs.bodies_to_joint_state(persons, anny, msgs=f), f)
    back = body_msgs.joint_state_to_bodies(msg)
    assert sorted(back) == [3, 11]
    for p in persons:
        b = back[p.track_id]
        np.testing.assert_allclose(b['pose'], p.params.pose, atol=1e-6)
        np.testing.assert_allclose(b['transl'], p.params.transl, atol=1e-6)
        np.testing.assert_allclose(b['joint_confidence'], p.joint_confidence, atol=1e-6)
        assert b['confidence_joint_names'] == tuple(anny.joint_names)
    tracked = wire(body_msgs.tracked_ids_msg(persons, msgs=f), f)
    assert list(tracked.name) == ['body_3', 'body_11']
    with pytest.raises(ValueError):
        body_msgs.joint_state_to_bodies(
            wire(body_msgs.params_to_joint_state(persons[0], anny, msgs=f), f))


def test_body_transforms_rebuild_the_joint_positions(anny):
    """Chaining each joint frame's transform from the camera gives back the joint's
    position and rotation."""
    from scipy.spatial.transform import Rotation
    rng = np.random.default_rng(2)
    J = len(anny.joint_names)
    R = Rotation.random(J, random_state=3).as_matrix()
    x = rng.normal(size=(J, 3))
    parents = anny.joint_parents.numpy()
    tfs = body_msgs.body_transforms(4, R, x, parents, anny.joint_names, msgs=ROSBAGS,
                                    header=A.make_header(None, ROSBAGS, frame_id='cam'))
    by = {t.child_frame_id: t for t in tfs}
    names = ['body_4'] + [f'{n}_4' for n in anny.joint_names[1:]]
    world = {'cam': (np.eye(3), np.zeros(3))}

    def pose_of(name):
        if name not in world:
            t = by[name]
            Rp, xp = pose_of(t.header.frame_id)
            q, v = t.transform.rotation, t.transform.translation
            Rl = Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix()
            world[name] = (Rp @ Rl, xp + Rp @ np.array([v.x, v.y, v.z]))
        return world[name]

    for j, n in enumerate(names):
        Rw, xw = pose_of(n)
        np.testing.assert_allclose(xw, x[j], atol=1e-9)
        np.testing.assert_allclose(Rw, R[j], atol=1e-9)
