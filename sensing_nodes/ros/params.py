"""A node's parameters declared from its table (sensing_nodes/parameters.py): read-only, with
descriptions and ranges, the values turned into the node's settings dataclass and checked by its
problems() at start-up (ParameterError: run_node reports it and exits with 2). A managed node's
(ros/processing_node.py) are writable while it is unconfigured and are checked at configure."""

from __future__ import annotations

import sys
from typing import Any, TypeVar

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.node import Node

from sensing_nodes.parameters import Parameter, ParameterError, ParameterTable
from sensing_nodes.ros.processing_node import ProcessingNode

_BIG = sys.float_info.max

Config = TypeVar('Config')


def declare(node: Node, parameter: Parameter) -> Any:
    """Declare one parameter (read-only, its description and inclusive range) and return its
    value; one the node has declared already is read. A value outside the range makes rclpy
    raise at declaration, which run_node reports.

    A managed node's is writable, of any type and unbounded for rclpy (its range in the
    descriptor's text): a bad value must be declared to be set right with `ros2 param set`
    while the node is unconfigured; the table's check refuses it at configure."""
    if node.has_parameter(parameter.name):
        return node.get_parameter(parameter.name).value
    managed = isinstance(node, ProcessingNode) and node.managed
    descriptor = ParameterDescriptor(description=parameter.description, read_only=not managed,
                                     dynamic_typing=parameter.dynamic or managed)
    low, high, default = parameter.minimum, parameter.maximum, parameter.default
    if managed:
        bounds = [f'>= {low:g}' if low is not None else '', f'<= {high:g}' if high is not None
                  else '']
        descriptor.additional_constraints = ', '.join(b for b in bounds if b)
    elif low is not None or high is not None:
        if isinstance(default, bool) or not isinstance(default, (int, float)):
            raise TypeError(f'range given for non-numeric parameter {parameter.name}')
        if isinstance(default, int):
            descriptor.integer_range = [IntegerRange(
                from_value=int(low if low is not None else -(2**63)),
                to_value=int(high if high is not None else 2**63 - 1), step=0)]
        else:
            descriptor.floating_point_range = [FloatingPointRange(
                from_value=float(low if low is not None else -_BIG),
                to_value=float(high if high is not None else _BIG), step=0.0)]
    return node.declare_parameter(parameter.name, default, descriptor).value


def declare_config(node: Node, table: ParameterTable[Config]) -> Config:
    """Declare every parameter of the table and return its dataclass with their values, checked
    (ParameterError naming the parameter)."""
    return table.config({p.name: declare(node, p) for p in table.parameters})


def refuse_retired(node: Node, retired: dict[str, str]) -> None:
    """ParameterError (`problem`) for each retired parameter name a parameter file or override
    still sets: left unread, it would be a setting silently different from the one asked for."""
    for name, problem in retired.items():
        value = node.get_parameter(name).value if node.has_parameter(name) else \
            node.declare_parameter(name, None, ParameterDescriptor(
                description=f'retired: {problem}', dynamic_typing=True)).value
        if value is not None:
            raise ParameterError(name, problem, value)
