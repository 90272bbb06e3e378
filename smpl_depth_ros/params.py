"""The parameter schema, generated from the declarations in `config.py` (no ROS).

Every parameter is declared once, as a field of `PipelineConfig`, `FitConfig`,
`OutputOptions` or `NodeOptions` with its description, range or choices, restart flag and
`advanced` flag (`config.param`). From those this module derives:

* the names: a core parameter is its field name (`depth_min`), a fitting one
  `fit.<field>`; the live node declares expert knobs under `advanced.`
  (`advanced.fit.iterations`, `advanced.min_person_pixels`), and the command-line tools
  take either form;
* one validation (`check`): types, ranges, choices and the rules between parameters, the
  same for the node (at start-up and on every change), `process_bag`, `evaluate` and
  `sweep`;
* the params YAML (`params_yaml`, what `config/reconstructor.yaml` holds), its reader
  (`load_params_file`) and the `-p name=value` reader (`parse_overrides`);
* the mapping of a set of values onto the dataclasses (`split`, `from_params`).
"""
from __future__ import annotations

from dataclasses import MISSING, dataclass, fields
from pathlib import Path
from typing import Any

from smpl_depth_ros.config import FitConfig, NodeOptions, OutputOptions, PipelineConfig

ADVANCED = 'advanced.'
GROUPS = ('core', 'fit', 'output', 'node')   # PipelineConfig, FitConfig, OutputOptions, NodeOptions
_CLASSES = {'core': PipelineConfig, 'fit': FitConfig, 'output': OutputOptions,
            'node': NodeOptions}


class ParamError(ValueError):
    """An unknown parameter or an invalid value; the message names it."""


@dataclass(frozen=True)
class Param:
    """One parameter, as declared in config.py."""

    name: str              # 'depth_min', 'fit.iterations'
    group: str             # one of GROUPS
    attr: str              # the dataclass field
    default: Any
    doc: str
    range: tuple | None
    choices: tuple | None
    restart: bool
    advanced: bool

    @property
    def ros_name(self) -> str:
        """The live node's name: expert knobs under `advanced.`."""
        return ADVANCED + self.name if self.advanced else self.name

    @property
    def kind(self) -> type:
        return type(self.default)


def build_schema(classes: dict[str, type], prefixes: dict[str, str] | None = None
                 ) -> dict[str, Param]:
    """The parameters declared (`config.param`) in the dataclasses `classes` (group ->
    class), named `<prefix><field>` (`prefixes`: group -> prefix, default none)."""
    out = {}
    for group, cls in classes.items():
        for f in fields(cls):
            if 'doc' not in f.metadata:   # PipelineConfig.fit: the FitConfig group
                continue
            m = f.metadata
            choices = m['choices']() if callable(m['choices']) else m['choices']
            name = (prefixes or {}).get(group, '') + f.name
            assert f.default is not MISSING and name not in out, name
            out[name] = Param(name, group, f.name, f.default, m['doc'], m['range'],
                              tuple(choices) if choices else None, m['restart'],
                              m['advanced'])
    return out


def check_declared(schema: dict[str, Param], values: dict[str, Any]) -> str | None:
    """Why values (by name, all of `schema`) break a declared range or choice, or None."""
    for name, p in schema.items():
        v = values[name]
        if p.choices and v not in p.choices:
            return f"{name} must be one of {', '.join(p.choices)}; got {v!r}"
        if p.range and not p.range[0] <= v <= p.range[1]:
            return f'{name} must be in [{p.range[0]}, {p.range[1]}], got {v}'
    return None


# The reconstructor's parameters (the node, process_bag, evaluate, sweep).
SCHEMA: dict[str, Param] = build_schema(_CLASSES, {'fit': 'fit.'})
_BY_ROS_NAME = {p.ros_name: p for p in SCHEMA.values()}


def lookup(name: str) -> Param | None:
    """The parameter called `name` (its own name or the node's `advanced.` form)."""
    return SCHEMA.get(name) or _BY_ROS_NAME.get(name)


def defaults() -> dict[str, Any]:
    """Every parameter's default, by name."""
    return {n: p.default for n, p in SCHEMA.items()}


def values_of(config: PipelineConfig | None = None, outputs: OutputOptions | None = None,
              node: NodeOptions | None = None) -> dict[str, Any]:
    """The values of the given dataclasses (defaults for those not given), by name."""
    objs = {'core': config or PipelineConfig(), 'output': outputs or OutputOptions(),
            'node': node or NodeOptions()}
    objs['fit'] = objs['core'].fit
    return {n: getattr(objs[p.group], p.attr) for n, p in SCHEMA.items()}


# -- values ---------------------------------------------------------------------------------
def coerce(name: str, value) -> Any:
    """`value` as parameter `name`'s type (ints for floats, YAML 1.1's '1e-5' strings), or
    ParamError. `name` must be known."""
    kind = lookup(name).kind
    if kind is bool:
        if not isinstance(value, bool):
            raise ParamError(f'parameter {name} must be true/false, got {value!r}')
        return value
    if kind is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ParamError(f'parameter {name} must be an integer, got {value!r}')
        return value
    if kind is float:
        if isinstance(value, str):  # YAML 1.1 reads 1e-5 (no dot) as a string; ROS doesn't
            try:
                value = float(value)
            except ValueError:
                pass
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ParamError(f'parameter {name} must be a number, got {value!r}')
        return float(value)
    if not isinstance(value, str):
        raise ParamError(f'parameter {name} must be a string, got {value!r}')
    return value


def check(values: dict[str, Any]) -> str | None:
    """Why a full set of values (by name, as `defaults()`) is invalid, or None."""
    reason = check_declared(SCHEMA, values)
    if reason:
        return reason
    if not values['depth_min'] < values['depth_max']:
        return (f"depth_min ({values['depth_min']}) must be smaller than depth_max "
                f"({values['depth_max']})")
    if values['device'] == 'cuda':
        import torch
        if not torch.cuda.is_available():
            return "device 'cuda' requested but CUDA is not available"
    return None


def split(values: dict[str, Any]) -> tuple[PipelineConfig, OutputOptions, NodeOptions]:
    """A full set of values (by name) as the dataclasses."""
    kw = {g: {} for g in GROUPS}
    for name, p in SCHEMA.items():
        kw[p.group][p.attr] = values[name]
    return (PipelineConfig(**kw['core'], fit=FitConfig(**kw['fit'])),
            OutputOptions(**kw['output']), NodeOptions(**kw['node']))


def from_params(params: dict[str, Any], base: PipelineConfig | None = None
                ) -> tuple[PipelineConfig, OutputOptions, NodeOptions]:
    """Parameters (any subset, by either name) over `base` and the defaults, coerced and
    checked; ParamError names every unknown parameter (a typo would otherwise pass
    silently) or the first invalid value."""
    values = values_of(base)
    unknown = sorted(n for n in params if lookup(n) is None)
    if unknown:
        raise ParamError(f'unknown parameter(s): {", ".join(unknown)}')
    for name, value in params.items():
        values[lookup(name).name] = coerce(name, value)
    reason = check(values)
    if reason:
        raise ParamError(reason)
    return split(values)


def given_in(params: dict[str, Any], group: str) -> list[str]:
    """The names in `params` that belong to `group` (e.g. the node-only ones offline)."""
    return sorted(n for n in params if (p := lookup(n)) is not None and p.group == group)


# -- text forms -------------------------------------------------------------------------------
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
    """The node's parameters from a ROS 2 params YAML, flattened ('advanced.fit.iterations').

    Sections keyed ``/**`` (or ``**``) apply, then the ones naming the node
    (``reconstructor``, ``/reconstructor``, ``/<ns>/reconstructor``,
    ``/**/reconstructor``), later ones winning, as in ROS.
    """
    import yaml
    try:
        with open(path) as f:
            data = yaml.safe_load(f) or {}
    except (OSError, yaml.YAMLError) as e:
        raise ParamError(f'cannot read params file {path}: {e}') from None
    if not isinstance(data, dict):
        raise ParamError(f'params file {path}: expected a mapping at the top level')
    generic, specific = {}, {}
    for key, section in data.items():
        if not isinstance(section, dict) or 'ros__parameters' not in section:
            continue
        params = section['ros__parameters'] or {}
        if not isinstance(params, dict):
            raise ParamError(f'params file {path}: {key}: ros__parameters must be a '
                             f'mapping, got {type(params).__name__}')
        params = _flatten(params)
        k = str(key).strip('/')
        if k in ('**', ''):
            generic.update(params)
        elif k.split('/')[-1] == node_name:
            specific.update(params)
    return {**generic, **specific}


def parse_overrides(items) -> dict[str, Any]:
    """['name=value', 'name:=value'] -> {name: YAML-typed value}."""
    import yaml
    out = {}
    for item in items or ():
        sep = ':=' if ':=' in item else '='
        name, ok, value = item.partition(sep)
        if not ok or not name:
            raise ParamError(f"-p expects name=value, got {item!r}")
        try:
            out[name.strip()] = yaml.safe_load(value) if value.strip() else ''
        except yaml.YAMLError as e:
            raise ParamError(f'-p {name.strip()}: {value!r} is not a YAML value '
                             f'({type(e).__name__})') from None
    return out


def constraints(p: Param) -> str:
    """The range/choices/restart note of a parameter ('' if none)."""
    notes = []
    if p.choices:
        notes.append('one of: ' + ', '.join(p.choices))
    if p.range:
        notes.append(f'{p.range[0]} to {p.range[1]}')
    if p.restart:
        notes.append('needs a restart')
    return '; '.join(notes)


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
    """The defaults as a ROS 2 `--params-file` (what config/reconstructor.yaml holds):
    `reconstructor --print-params > config/reconstructor.yaml`."""
    out = ['# Parameters of the `reconstructor` node, generated by `reconstructor',
           '# --print-params` from their declarations in smpl_depth_ros/config.py (a test checks',
           '# that they agree). process_bag --params-file and evaluate/sweep read it too. Keyed',
           '# `/**:` so it survives node renames and namespaces:',
           '#   reconstructor --ros-args --params-file config/reconstructor.yaml -p device:=cpu',
           '/**:', '  ros__parameters:']

    def line(indent: str, key: str, p: Param):
        note = constraints(p)
        out.append(f'{indent}{key}: {_yaml_value(p.default)}  # {p.doc}'
                   + (f' [{note}]' if note else ''))

    titles = {'core': 'reconstruction', 'output': 'outputs', 'node': 'live node'}
    for group in ('core', 'output', 'node'):
        out.append(f'    # -- {titles[group]} ' + '-' * (70 - len(titles[group])))
        for p in SCHEMA.values():
            if p.group == group and not p.advanced:
                line('    ', p.name, p)
    out.append('    advanced:  # expert knobs')
    for p in SCHEMA.values():
        if p.advanced and p.group != 'fit':
            line('      ', p.name, p)
    out.append('      fit:  # model fitting')
    for p in SCHEMA.values():
        if p.group == 'fit':
            line('        ', p.attr, p)
    return '\n'.join(out) + '\n'
