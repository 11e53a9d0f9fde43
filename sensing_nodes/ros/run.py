"""Start-up and shutdown shared by every node executable."""

from __future__ import annotations

import faulthandler
import os
import signal
import sys
from typing import Callable

import rclpy
from rclpy.exceptions import (
    InvalidParameterTypeException,
    InvalidParameterValueException,
    ParameterException,
)
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node

from sensing_nodes.parameters import ParameterError

EXIT_BAD_PARAMETER = 2

_PARAMETER_ERRORS = (
    ParameterError,
    InvalidParameterValueException,
    InvalidParameterTypeException,
    ParameterException,
)


EXECUTORS = ('events', 'single', 'multi')


def executor_kind(kind: str | None = None) -> str:
    """The executor make_executor(kind) makes: kind, else the environment's
    SENSING_NODES_EXECUTOR, else 'events'."""
    kind = kind or os.environ.get('SENSING_NODES_EXECUTOR', 'events')
    if kind not in EXECUTORS:
        raise ValueError(f'executor {kind!r}: one of {", ".join(EXECUTORS)}')
    return kind


def make_executor(kind: str | None = None, threads: int | None = None):
    """rclpy's C++-backed EventsExecutor (several times the message throughput of the Python
    SingleThreadedExecutor, which matters at 1 kHz IMU input); kind (default: the environment's
    SENSING_NODES_EXECUTOR) 'single' selects the classic one, 'multi' a MultiThreadedExecutor
    with `threads` workers (rclpy's default: the CPU count)."""
    kind = executor_kind(kind)
    if kind == 'single':
        return SingleThreadedExecutor()
    if kind == 'multi':
        from rclpy.executors import MultiThreadedExecutor

        return MultiThreadedExecutor(num_threads=threads)
    from rclpy.experimental import EventsExecutor

    return EventsExecutor()


def spin_until_quiet(executor, arrivals: Callable[[], int], quiet_s: float, timeout_s: float,
                     step_s: float = 0.01, done: Callable[[], bool] | None = None) -> None:
    """Spin until arrivals() has not changed for quiet_s wall seconds, or timeout_s has passed:
    the graph's last answers are in (the tools' drain after the last input); or, sooner, until
    done() holds."""
    import time

    deadline = time.monotonic() + timeout_s
    quiet_since, seen = time.monotonic(), arrivals()
    while time.monotonic() - quiet_since < quiet_s and time.monotonic() < deadline \
            and not (done is not None and done()):
        executor.spin_once(timeout_sec=step_s)
        if arrivals() != seen:
            quiet_since, seen = time.monotonic(), arrivals()


def spin_until_shutdown(executor, context=None) -> None:
    """Spin until the context (default: rclpy's) shuts down. Not executor.spin(): the
    EventsExecutor's of rclpy 7.1 neither fires timers nor returns on shutdown. Not a spin_once
    loop either: that is one Python round trip per event, where spin_until_future_complete on
    a future nothing completes runs the events in C++ for 0.1 s at a time (a relay's CPU per
    message at 1 kHz 100-108 -> 88-93 us; none measurable at 250 Hz, where events seldom
    queue: docs/performance.md)."""
    from rclpy.task import Future

    never = Future()
    while rclpy.ok(context=context):
        executor.spin_until_future_complete(never, timeout_sec=0.1)


def ignore_further_interrupts() -> None:
    """From here on (a node's teardown) SIGINT is ignored. A Ctrl-C on `ros2 launch` reaches a
    node twice, from the terminal and forwarded by launch; raised as KeyboardInterrupt inside
    rclpy's C++ destroy_node, the second aborted the process (exit -6; seen under load). SIGTERM
    and SIGKILL still end it."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def run_node(make_node: Callable[[], Node], args: list[str] | None = None) -> int:
    """Create the node, spin until shutdown; a bad parameter is reported and exits with 2."""
    # A crash inside the C++ executor or a message library then leaves a Python stack in the log.
    faulthandler.enable()
    rclpy.init(args=args)
    node = None
    try:
        try:
            node = make_node()
        except _PARAMETER_ERRORS as exc:
            name = getattr(make_node, '__name__', 'node')
            print(f'[{name}] invalid parameter: {exc}', file=sys.stderr, flush=True)
            return EXIT_BAD_PARAMETER
        executor = make_executor()
        executor.add_node(node)
        spin_until_shutdown(executor, node.context)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except Exception:
        if node is None or rclpy.ok(context=node.context):
            raise
        # A callback run while a signal was shutting the context down (a timer publishing on a
        # publisher that just became invalid: RCLError) is the shutdown, not the node's error.
    finally:
        ignore_further_interrupts()
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return 0
