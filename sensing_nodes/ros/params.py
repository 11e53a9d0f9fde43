"""Declaring parameters with descriptors and ranges, and failing clearly at start-up."""

from __future__ import annotations

import sys
from typing import Any

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.node import Node

_BIG = sys.float_info.max


class ParameterError(ValueError):
    """A parameter value the node cannot run with; raised once at start-up."""

    def __init__(self, name: str, problem: str, value: Any = None) -> None:
        detail = f' (got {value!r})' if value is not None else ''
        super().__init__(f"parameter '{name}' {problem}{detail}")
        self.name = name


def declare(
    node: Node,
    name: str,
    default: Any,
    description: str,
    *,
    minimum: float | None = None,
    maximum: float | None = None,
) -> Any:
    """Declare a read-only parameter with a description and optional inclusive range; return its
    value.

    A value outside the range makes rclpy raise at declaration, which run_node reports.
    """
    descriptor = ParameterDescriptor(description=description, read_only=True)
    if minimum is not None or maximum is not None:
        if isinstance(default, bool) or not isinstance(default, (int, float)):
            raise TypeError(f'range given for non-numeric parameter {name}')
        if isinstance(default, int):
            descriptor.integer_range = [IntegerRange(
                from_value=int(minimum if minimum is not None else -(2**63)),
                to_value=int(maximum if maximum is not None else 2**63 - 1),
                step=0,
            )]
        else:
            descriptor.floating_point_range = [FloatingPointRange(
                from_value=float(minimum if minimum is not None else -_BIG),
                to_value=float(maximum if maximum is not None else _BIG),
                step=0.0,
            )]
    return node.declare_parameter(name, default, descriptor).value


def require(condition: bool, name: str, problem: str, value: Any = None) -> None:
    """Raise ParameterError(name, problem) unless condition holds."""
    if not condition:
        raise ParameterError(name, problem, value)
