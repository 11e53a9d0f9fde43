"""Declaring parameters with descriptors and ranges, and failing clearly at start-up."""

from __future__ import annotations

import dataclasses
import sys
from typing import Any, TypeVar

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


@dataclasses.dataclass(frozen=True)
class Param:
    """One field of a core config dataclass as a ROS parameter: its name, description and
    inclusive range (the default is the dataclass's own, never copied)."""

    field: str
    description: str
    name: str = ''          # the parameter's name when it differs from the field's
    minimum: float | None = None
    maximum: float | None = None

    @property
    def parameter(self) -> str:
        return self.name or self.field


Config = TypeVar('Config')


def declare_config(node: Node, defaults: Config, params: tuple[Param, ...],
                   declared: dict[str, str] | None = None) -> Config:
    """Declare a parameter per Param with the default from `defaults` (a dataclass) and return
    the dataclass with the values given; ParameterError, naming the parameter, for each value
    its `problems()` refuses (`declared`: field -> parameter for fields the caller declared
    itself and put into `defaults`)."""
    values = {p.field: declare(node, p.parameter, getattr(defaults, p.field), p.description,
                               minimum=p.minimum, maximum=p.maximum) for p in params}
    config = dataclasses.replace(defaults, **values)
    names = {**(declared or {}), **{p.field: p.parameter for p in params}}
    for field, problem, value in config.problems():
        require(False, names.get(field, field), problem, value)
    return config
