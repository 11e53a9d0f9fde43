"""Start-up and shutdown shared by every node executable."""

from __future__ import annotations

import sys
from typing import Callable

import rclpy
from rclpy.exceptions import (
    InvalidParameterTypeException,
    InvalidParameterValueException,
    ParameterException,
)
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node

from sensing_nodes.ros.params import ParameterError

EXIT_BAD_PARAMETER = 2

_PARAMETER_ERRORS = (
    ParameterError,
    InvalidParameterValueException,
    InvalidParameterTypeException,
    ParameterException,
)


def run_node(make_node: Callable[[], Node], args: list[str] | None = None) -> int:
    """Create the node, spin until shutdown; a bad parameter is reported and exits with 2."""
    rclpy.init(args=args)
    node = None
    try:
        try:
            node = make_node()
        except _PARAMETER_ERRORS as exc:
            name = getattr(make_node, '__name__', 'node')
            print(f'[{name}] invalid parameter: {exc}', file=sys.stderr, flush=True)
            return EXIT_BAD_PARAMETER
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return 0
