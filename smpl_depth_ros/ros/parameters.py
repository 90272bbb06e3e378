"""ROS parameter descriptors from the parameter schema (`smpl_depth_ros.params.Param`):
type, description, range (enforced by rclpy too), choices, read-only. Both nodes declare
their parameters through this."""
from __future__ import annotations

from rcl_interfaces.msg import (FloatingPointRange, IntegerRange, ParameterDescriptor,
                                ParameterType)

from smpl_depth_ros.params import Param, constraints


def descriptor(p: Param) -> ParameterDescriptor:
    """The descriptor of `p`, declared under `p.ros_name`; a restart parameter is read-only."""
    d = ParameterDescriptor(name=p.ros_name, description=p.doc, read_only=p.restart)
    if p.kind is bool:
        d.type = ParameterType.PARAMETER_BOOL
    elif p.kind is int:
        d.type = ParameterType.PARAMETER_INTEGER
        if p.range:
            d.integer_range = [IntegerRange(from_value=int(p.range[0]),
                                            to_value=int(p.range[1]), step=1)]
    elif p.kind is float:
        d.type = ParameterType.PARAMETER_DOUBLE
        if p.range:
            d.floating_point_range = [FloatingPointRange(
                from_value=float(p.range[0]), to_value=float(p.range[1]), step=0.0)]
    else:
        d.type = ParameterType.PARAMETER_STRING
    d.additional_constraints = constraints(p)
    return d


def declare(node, schema: dict[str, Param]) -> dict[str, object]:
    """Declare every parameter of `schema` on `node`; their values, by schema name."""
    node.declare_parameters('', [(p.ros_name, p.default, descriptor(p))
                                 for p in schema.values()])
    return {n: node.get_parameter(p.ros_name).value for n, p in schema.items()}
