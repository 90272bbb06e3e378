"""The live node's parameters offline: a set of them (params file, `-p`; either name form,
`smpl_depth_ros.params`) as the `PipelineConfig` and output options of a run."""
from __future__ import annotations

from dataclasses import asdict
from typing import Any

from smpl_depth_ros import params as P
from smpl_depth_ros.config import OutputOptions, PipelineConfig

# The node's output parameters, which matter offline (its QoS, threads and diagnostics
# parameters do not: threads follow --workers).
NODE_OPTIONS = asdict(OutputOptions())


def config_from_params(params: dict[str, Any], base: PipelineConfig | None = None
                       ) -> tuple[PipelineConfig, dict[str, Any], list[str]]:
    """(PipelineConfig, the output options as a dict, the live-only names given, which are
    ignored offline). ParamError names unknown parameters and invalid values, as the node
    would."""
    cfg, outputs, _ = P.from_params(params, base)
    return cfg, asdict(outputs), P.given_in(params, 'node')
