"""The parameter schema (smpl_depth_ros.params): one declaration per parameter in
config.py, one validation for the node and the command-line tools, the params file."""
from dataclasses import asdict, fields
from pathlib import Path

import pytest

from smpl_depth_ros import params as P
from smpl_depth_ros.config import FitConfig, NodeOptions, OutputOptions, PipelineConfig
from smpl_depth_ros.offline import config_from_params

PARAMS_FILE = Path(__file__).resolve().parents[1] / 'config' / 'reconstructor.yaml'


def test_every_config_field_is_declared_once_with_a_description():
    names = []
    for cls, prefix in ((PipelineConfig, ''), (FitConfig, 'fit.'), (OutputOptions, ''),
                        (NodeOptions, '')):
        for f in fields(cls):
            if f.name == 'fit' and cls is PipelineConfig:
                continue
            names.append(prefix + f.name)
            p = P.SCHEMA[prefix + f.name]
            assert p.doc and p.default == f.default, p.name
            assert type(p.default) in (bool, int, float, str), p.name
            if p.range:
                assert p.range[0] <= p.default <= p.range[1], p.name
            if p.choices:
                assert p.default in p.choices, p.name
    assert len(names) == len(set(names)) == len(P.SCHEMA)
    # Fitting knobs are all expert ones; the node shows a short list of the rest.
    assert all(p.advanced for p in P.SCHEMA.values() if p.group == 'fit')
    plain = [p.name for p in P.SCHEMA.values() if not p.advanced]
    assert 'max_persons' in plain and 'sensor' in plain and len(plain) < 25
    assert P.SCHEMA['fit.iterations'].ros_name == 'advanced.fit.iterations'
    assert P.SCHEMA['depth_min'].ros_name == 'depth_min'
    assert P.check(P.defaults()) is None


def test_params_file_every_value_reaches_the_config():
    params = P.load_params_file(PARAMS_FILE)
    assert params['backend'] == 'anny' and params['advanced.fit.iterations'] > 0  # flattened
    cfg, opts, ignored = config_from_params(params)
    values = P.values_of(cfg, OutputOptions(**opts))
    for name, value in params.items():
        p = P.lookup(name)
        assert p is not None, name
        if p.group != 'node':
            assert values[p.name] == value, name
    assert set(ignored) == {'qos_reliability', 'qos_depth', 'cpu_threads',
                            'advanced.diagnostics_period_s', 'advanced.warn_throttle_s'}


def test_sections_and_both_name_forms(tmp_path):
    f = tmp_path / 'p.yaml'
    f.write_text('/**:\n  ros__parameters:\n    depth_max: 5\n    advanced:\n      fit:\n'
                 '        iterations: 7\n'
                 '/robot/reconstructor:\n  ros__parameters:\n    depth_max: 4.5\n'
                 'other_node:\n  ros__parameters:\n    depth_max: 1.0\n')
    cfg, _, _ = P.from_params(P.load_params_file(f))
    assert cfg.depth_max == 4.5 and cfg.fit.iterations == 7
    # The short names the command-line tools document work as well.
    over = P.parse_overrides(['tracking=false', 'fit.solver:=lbfgs', 'mesh_decimation=0.5',
                              'advanced.shape_sample_every=0', 'min_person_pixels=100'])
    cfg, outputs, _ = P.from_params(over)
    assert cfg.tracking is False and cfg.fit.solver == 'lbfgs'
    assert outputs.mesh_decimation == 0.5
    assert cfg.shape_sample_every == 0 and cfg.min_person_pixels == 100
    cfg, _, _ = P.from_params(P.parse_overrides(['fit.lambda_shape=1e-5']))
    assert cfg.fit.lambda_shape == 1e-5  # a string to YAML 1.1, a number to ROS
    base = PipelineConfig(max_persons=3)
    assert P.from_params({'depth_max': 5.0}, base=base)[0].max_persons == 3


@pytest.mark.parametrize('params, match', [
    ({'fit.lambda_shape': 'abc'}, 'number'),
    ({'fit.iteratons': 3}, r'unknown parameter\(s\): fit.iteratons'),
    ({'advanced.depth_min': 1.0}, 'unknown parameter'),   # not an expert knob
    ({'max_persons': 1.5}, 'integer'),
    ({'tracking': 'yes'}, 'true/false'),
    ({'depth_min': 7.0}, 'smaller than depth_max'),
    ({'max_persons': 0}, r'max_persons must be in \[1, 100\]'),      # the node's ranges,
    ({'mesh_decimation': 0.0}, 'mesh_decimation must be in'),         # offline too
    ({'fit.icp_front_cos': 2.0}, 'fit.icp_front_cos must be in'),
    ({'fit.solver': 'newton'}, 'fit.solver must be one of fast, lbfgs'),
    ({'sensor': 'kinect_v9'}, 'sensor must be one of'),
    ({'qos_reliability': 'sometimes'}, 'qos_reliability must be one of'),
])
def test_invalid_values_are_named(params, match):
    with pytest.raises(P.ParamError, match=match):
        P.from_params(params)


def test_bad_yaml_in_overrides_and_params_files(tmp_path):
    """A control character in `-p` and a non-mapping ros__parameters give the usage error
    (not yaml's ReaderError / AttributeError)."""
    with pytest.raises(P.ParamError, match='not a YAML value'):
        P.parse_overrides(['depth_min=\x1b'])
    with pytest.raises(P.ParamError, match='name=value'):
        P.parse_overrides(['depth_min'])
    p = tmp_path / 'p.yaml'
    p.write_text('/**:\n  ros__parameters: 1\n')
    with pytest.raises(P.ParamError, match='must be a mapping'):
        P.load_params_file(p)
    with pytest.raises(P.ParamError, match='cannot read'):
        P.load_params_file(tmp_path / 'missing.yaml')


def test_values_round_trip_through_the_dataclasses():
    cfg = PipelineConfig().with_overrides(max_persons=2, iterations=4)
    values = P.values_of(cfg)
    assert values['max_persons'] == 2 and values['fit.iterations'] == 4
    back, outputs, node = P.split(values)
    assert back == cfg and outputs == OutputOptions() and node == NodeOptions()
    assert asdict(back)['fit']['iterations'] == 4


def test_ros_descriptors_carry_the_declarations():
    from rcl_interfaces.msg import ParameterType

    from smpl_depth_ros.ros.parameters import descriptor
    d = descriptor(P.SCHEMA['fit.iterations'])
    assert d.name == 'advanced.fit.iterations' and not d.read_only
    assert d.type == ParameterType.PARAMETER_INTEGER
    assert (d.integer_range[0].from_value, d.integer_range[0].to_value) == (0, 10_000)
    d = descriptor(P.SCHEMA['backend'])
    assert d.read_only and 'one of: anny, smpl' in d.additional_constraints
    assert d.description == P.SCHEMA['backend'].doc
    d = descriptor(P.SCHEMA['depth_min'])
    assert d.floating_point_range[0].to_value == 100.0


def test_the_oak_node_declares_its_parameters_the_same_way():
    pytest.importorskip('depthai')
    from smpl_depth_ros.ros import oak
    from smpl_depth_ros.ros.oak_camera_node import SCHEMA, validate
    assert all(p.restart for p in SCHEMA.values() if p.group == 'camera')
    assert not SCHEMA['frame_id'].restart and not SCHEMA['warn_throttle_s'].restart
    values = {n: p.default for n, p in SCHEMA.items()}
    assert validate(values) is None
    assert 'decimation must be in [1, 4]' in validate(dict(values, decimation=5))
    assert 'preset must be one of' in validate(dict(values, preset='fastest'))
    assert 'max_range' in oak.validate(oak.OakConfig(min_range=3.0, max_range=2.0))
