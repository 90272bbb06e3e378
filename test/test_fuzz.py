"""Fuzzing the inputs a user's bad day brings (hypothesis): random Image and CameraInfo
messages, depth arrays and intrinsics into the pipeline's validation, `-p` overrides and
params files, and damaged bags. Every input ends in a result or the documented error
(`InputError` with a reason; `ProcessBagError` / `BagReadError` offline), within 2 s and
without allocating far beyond the input's size.

The default profile fits CI (the same examples every run); a longer, random one:

    HYPOTHESIS_PROFILE=long .venv/bin/python -m pytest -q test/test_fuzz.py
"""
from __future__ import annotations

import os
import shutil
import time
import tracemalloc
from pathlib import Path

import numpy as np
import pytest

hypothesis = pytest.importorskip('hypothesis')
from hypothesis import HealthCheck, given, settings, strategies as st  # noqa: E402

from smpl_depth_ros.ros import adapters as A  # noqa: E402
from smpl_depth_ros.types import InputError  # noqa: E402

settings.register_profile('ci', max_examples=150, deadline=None, derandomize=True,
                          suppress_health_check=[HealthCheck.too_slow,
                                                 HealthCheck.function_scoped_fixture])
settings.register_profile('long', max_examples=5000, deadline=None,
                          suppress_health_check=[HealthCheck.too_slow,
                                                 HealthCheck.function_scoped_fixture])
settings.load_profile(os.environ.get('HYPOTHESIS_PROFILE', 'ci'))

F = A.rosbags_factory()
MAX_S = 2.0
ENCODINGS = ['16UC1', '32FC1', 'mono16', 'mono8', 'rgb8', '16SC1', '', 'bgr8', '64FC1']


def bounded(fn, limit_bytes: int):
    """fn() under a wall-time and allocation bound; returns its result or exception."""
    tracemalloc.start()
    t0 = time.perf_counter()
    try:
        try:
            out = fn()
        except Exception as e:  # noqa: BLE001 - the caller checks which
            out = e
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    dt = time.perf_counter() - t0
    assert dt < MAX_S, f'{dt:.2f} s'
    assert peak < limit_bytes, f'{peak / 1e6:.1f} MB allocated (bound {limit_bytes / 1e6:.1f})'
    return out


dims = st.one_of(st.integers(0, 700), st.sampled_from([2**16, 2**31 - 1, 2**32 - 1]))


@given(h=dims, w=dims, step=st.one_of(st.integers(0, 3000), st.just(2**32 - 1)),
       enc=st.one_of(st.sampled_from(ENCODINGS), st.text(max_size=12)),
       big=st.integers(0, 2), data=st.binary(max_size=6000))
def test_image_adapter_gives_depth_or_input_error(h, w, step, enc, big, data):
    msg = F.new('sensor_msgs/msg/Image', height=h, width=w, step=step, encoding=enc,
                is_bigendian=big, data=np.frombuffer(data, np.uint8))
    out = bounded(lambda: A.image_to_depth(msg, max_pixels=4096 * 4096),
                  20 * len(data) + 2_000_000)
    if isinstance(out, Exception):
        assert isinstance(out, InputError) and out.reason, repr(out)
    else:
        assert out.shape == (h, w) and out.dtype == np.float32


@given(h=dims, w=dims, shape=st.sampled_from(['zero', 'fine', 'bad']),
       K=st.lists(st.floats(allow_nan=True, allow_infinity=True, width=64), min_size=9,
                  max_size=9),
       D=st.lists(st.floats(width=64), max_size=8))
def test_camera_info_adapter_gives_intrinsics_or_input_error(h, w, shape, K, D):
    if shape == 'fine':
        K = [525.0, 0, w / 2, 0, 525.0, h / 2, 0, 0, 1]
    msg = F.new('sensor_msgs/msg/CameraInfo', height=h, width=w,
                k=np.asarray(K, np.float64), d=np.asarray(D, np.float64))
    out = bounded(lambda: A.camera_info_to_K(msg), 1_000_000)
    if isinstance(out, Exception):
        assert isinstance(out, InputError) and out.reason, repr(out)
    else:
        Kout = out[0]
        assert Kout.shape == (3, 3) and np.isfinite(Kout).all()


@given(h=st.integers(0, 64), w=st.integers(0, 64),
       fill=st.sampled_from(['zeros', 'nan', 'inf', 'neg', 'random', 'huge']),
       fx=st.one_of(st.floats(-1e12, 1e12), st.sampled_from([np.nan, np.inf, 0.0])),
       cx=st.one_of(st.floats(-1e6, 1e6), st.just(np.nan)), seed=st.integers(0, 1000))
def test_pipeline_input_validation(h, w, fill, fx, cx, seed):
    from smpl_depth_ros.pipeline import validate_input
    rng = np.random.default_rng(seed)
    d = {'zeros': np.zeros((h, w)), 'nan': np.full((h, w), np.nan),
         'inf': np.full((h, w), np.inf), 'neg': -rng.uniform(0, 5, (h, w)),
         'random': rng.uniform(0, 8, (h, w)), 'huge': np.full((h, w), 1e30)}[fill]
    K = np.array([[fx, 0, cx], [0, fx, h / 2], [0, 0, 1]])
    out = bounded(lambda: validate_input(d.astype(np.float32), K, 4096 * 4096), 2_000_000)
    if isinstance(out, Exception):
        assert isinstance(out, InputError) and out.reason, repr(out)
    else:
        assert out.shape == (h, w) and np.isfinite(out).all() and (out >= 0).all()


_OVERRIDE = st.builds(
    lambda k, v: f'{k}={v}',
    st.sampled_from(['max_persons', 'depth_min', 'fit.iterations', 'sensor', 'tracking',
                     'advanced.fit.iterations', 'advanced.track_gate_m',
                     'publish_tf', 'mesh_decimation', 'qos_depth', 'nope']),
    st.one_of(st.text(max_size=10), st.integers(-5, 10**6).map(str),
              st.floats(allow_nan=True).map(str),
              st.sampled_from(['true', 'false', '[1, 2]', '{a: 1}', '~', 'auto', 'none'])))


@given(items=st.lists(st.one_of(st.text(max_size=40), _OVERRIDE), max_size=5))
def test_parameter_overrides_give_a_config_or_a_usage_error(items):
    from smpl_depth_ros.params import ParamError, from_params, parse_overrides
    out = bounded(lambda: from_params(parse_overrides(items)), 5_000_000)
    assert not isinstance(out, Exception) or isinstance(out, ParamError), repr(out)


@given(text=st.one_of(st.text(max_size=300), st.builds(
    lambda v: '/**:\n  ros__parameters:\n    ' + v, st.text(max_size=120))))
def test_params_files_give_parameters_or_a_usage_error(tmp_path, text):
    from smpl_depth_ros.params import ParamError, from_params, load_params_file
    p = tmp_path / 'p.yaml'
    p.write_text(text)
    out = bounded(lambda: from_params(load_params_file(p)), 5_000_000)
    assert not isinstance(out, Exception) or isinstance(out, ParamError), repr(out)


@pytest.fixture(scope='module')
def small_bag(tmp_path_factory):
    """Three 64x48 depth frames with camera_info, written by bagio (MCAP)."""
    from smpl_depth_ros.bagio import write_depth_bag
    from smpl_depth_ros.synth.camera import get_camera
    cam = get_camera('kinect_v1', 64, 48)
    path = tmp_path_factory.mktemp('fuzz') / 'bag'
    rng = np.random.default_rng(0)
    write_depth_bag(path, ((10**9 * (i + 1), rng.uniform(0.5, 4, (48, 64)).astype(np.float32))
                           for i in range(3)), cam, '16UC1', 'mcap')
    return path


@given(flips=st.lists(st.tuples(st.floats(0, 1, exclude_max=True), st.integers(0, 255)),
                      min_size=1, max_size=8),
       cut=st.one_of(st.none(), st.floats(0, 1)))
def test_damaged_bags_are_read_or_reported(small_bag, tmp_path, flips, cut):
    """Bytes flipped or the file cut short: the reader yields messages (each depth frame
    then decodes or is an InputError) or stops with BagReadError / ProcessBagError."""
    from smpl_depth_ros.offline import BagInput, BagReadError, ProcessBagError
    bag = tmp_path / 'bag'
    if bag.exists():
        shutil.rmtree(bag)
    shutil.copytree(small_bag, bag)
    f = next(p for p in Path(bag).iterdir() if p.suffix == '.mcap')
    raw = bytearray(f.read_bytes())
    for pos, val in flips:
        raw[int(pos * len(raw))] = val
    if cut is not None:
        raw = raw[:int(cut * len(raw))]
    f.write_bytes(bytes(raw))

    def read():
        n = 0
        with BagInput(bag) as src:
            for t, _, data in src.messages():
                if t.msgtype == 'sensor_msgs/msg/Image':
                    try:
                        A.image_to_depth(src.typestore.deserialize_cdr(data, t.msgtype))
                    except InputError:
                        pass
                    except Exception:  # noqa: BLE001 - CDR that does not decode
                        pass  # process_bag counts it as 'deserialize'
                n += 1
        return n
    out = bounded(read, 50 * len(raw) + 20_000_000)
    assert not isinstance(out, Exception) or isinstance(out, (BagReadError, ProcessBagError)), \
        repr(out)
