"""The live node's parameters offline: its params YAML and `-p` overrides mapped onto a
`PipelineConfig` and the node's output options."""
from __future__ import annotations

from dataclasses import fields
from pathlib import Path
from typing import Any

from smpl_depth_ros.config import FitConfig, PipelineConfig
from smpl_depth_ros.offline.errors import ProcessBagError
from smpl_depth_ros.ros.outputs import OUTPUT_PARAMS
from smpl_depth_ros.sensor_noise import check_sensor

# Node parameters that matter offline (the rest are about QoS and live diagnostics).
NODE_OPTIONS = {k: v for k, (v, _) in OUTPUT_PARAMS.items()}
NODE_ONLY = {'qos_reliability', 'qos_depth', 'diagnostics_period_s', 'warn_throttle_s',
             'cpu_threads'}  # offline: threads follow --workers


# -- parameters -------------------------------------------------------------------------
def _flatten(d: dict, prefix: str = '') -> dict[str, Any]:
    out = {}
    for k, v in d.items():
        name = f'{prefix}{k}'
        if isinstance(v, dict):
            out.update(_flatten(v, name + '.'))
        else:
            out[name] = v
    return out


def load_params_file(path: str | Path, node_name: str = 'reconstructor') -> dict[str, Any]:
    """The node's parameters from a ROS 2 params YAML, flattened ('fit.iterations').

    Sections keyed ``/**`` (or ``**``) apply, then the ones naming the node (``reconstructor``,
    ``/reconstructor``, ``/<ns>/reconstructor``, ``/**/reconstructor``), later ones winning,
    as in ROS.
    """
    import yaml
    try:
        with open(path) as f:
            data = yaml.safe_load(f) or {}
    except (OSError, yaml.YAMLError) as e:
        raise ProcessBagError(f'cannot read params file {path}: {e}') from None
    if not isinstance(data, dict):
        raise ProcessBagError(f'params file {path}: expected a mapping at the top level')
    generic, specific = {}, {}
    for key, section in data.items():
        if not isinstance(section, dict) or 'ros__parameters' not in section:
            continue
        params = section['ros__parameters'] or {}
        if not isinstance(params, dict):
            raise ProcessBagError(f'params file {path}: {key}: ros__parameters must be a '
                                  f'mapping, got {type(params).__name__}')
        params = _flatten(params)
        k = str(key).strip('/')
        if k in ('**', ''):
            generic.update(params)
        elif k.split('/')[-1] == node_name:
            specific.update(params)
    return {**generic, **specific}


def _coerce(name: str, value, default):
    if isinstance(default, bool):
        if not isinstance(value, bool):
            raise ProcessBagError(f'parameter {name} must be true/false, got {value!r}')
        return value
    if isinstance(default, int):
        if isinstance(value, bool) or not isinstance(value, int):
            raise ProcessBagError(f'parameter {name} must be an integer, got {value!r}')
        return value
    if isinstance(default, float):
        if isinstance(value, str):  # YAML 1.1 reads 1e-5 (no dot) as a string; ROS doesn't
            try:
                value = float(value)
            except ValueError:
                pass
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ProcessBagError(f'parameter {name} must be a number, got {value!r}')
        return float(value)
    if not isinstance(value, str):
        raise ProcessBagError(f'parameter {name} must be a string, got {value!r}')
    return value


def config_from_params(params: dict[str, Any], base: PipelineConfig | None = None
                       ) -> tuple[PipelineConfig, dict[str, Any], list[str]]:
    """Map node parameter names onto (PipelineConfig, node options, ignored names).

    Core names are PipelineConfig fields and 'fit.<FitConfig field>'; node options are
    `NODE_OPTIONS`; QoS/diagnostics parameters of the live node are ignored; anything else
    is an error (a typo would otherwise pass silently).
    """
    cfg = base or PipelineConfig()
    core = {f.name: getattr(cfg, f.name) for f in fields(PipelineConfig) if f.name != 'fit'}
    fit = {f.name: getattr(cfg.fit, f.name) for f in fields(FitConfig)}
    opts = dict(NODE_OPTIONS)
    ignored, unknown = [], []
    for name, value in params.items():
        if name in core:
            core[name] = _coerce(name, value, core[name])
        elif name.startswith('fit.') and name[4:] in fit:
            fit[name[4:]] = _coerce(name, value, fit[name[4:]])
        elif name in opts:
            opts[name] = _coerce(name, value, NODE_OPTIONS[name])
        elif name in NODE_ONLY:
            ignored.append(name)
        else:
            unknown.append(name)
    if unknown:
        raise ProcessBagError(f'unknown parameter(s): {", ".join(sorted(unknown))}')
    out = PipelineConfig(**core, fit=FitConfig(**fit))
    if out.device not in ('auto', 'cpu', 'cuda'):
        raise ProcessBagError(f"device must be 'auto', 'cpu' or 'cuda', got {out.device!r}")
    if out.segmentation not in ('model', 'network'):
        raise ProcessBagError("segmentation must be 'model' or 'network', got "
                              f'{out.segmentation!r}')
    if check_sensor(out.sensor):
        raise ProcessBagError(check_sensor(out.sensor))
    if not out.depth_min < out.depth_max:
        raise ProcessBagError(f'depth_min ({out.depth_min}) must be smaller than depth_max '
                              f'({out.depth_max})')
    if not 0.0 < opts['mesh_decimation'] <= 1.0:
        raise ProcessBagError(f"mesh_decimation must be in (0, 1], got {opts['mesh_decimation']}")
    return out, opts, ignored


def parse_param_overrides(items) -> dict[str, Any]:
    """['name=value', 'name:=value'] -> {name: YAML-typed value}."""
    import yaml
    out = {}
    for item in items or ():
        sep = ':=' if ':=' in item else '='
        name, ok, value = item.partition(sep)
        if not ok or not name:
            raise ProcessBagError(f"-p expects name=value, got {item!r}")
        try:
            out[name.strip()] = yaml.safe_load(value) if value.strip() else ''
        except yaml.YAMLError as e:
            raise ProcessBagError(f'-p {name.strip()}: {value!r} is not a YAML value '
                                  f'({type(e).__name__})') from None
    return out
