"""A DDS probe: one process under test, started and stopped through graph/processes on a
benchmark's own domain (this machine only), fed by a driver node in a private rclpy context that
publishes until the process answers, then at a rate paced by wall time."""

from __future__ import annotations

import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path

from sensing_nodes.graph.processes import Graph, isolated_environment


class DdsProbe:
    """`with DdsProbe(name, command, domain_offset, driver) as probe:` the process (its Popen:
    probe.process) and the driver (probe.node, spun by probe's single-threaded executor) on the
    domain pid_domain_id('bench', domain_offset); on leaving, the process is stopped (SIGINT,
    then killed) and the driver's context shut down."""

    def __init__(self, name: str, command: list[str], domain_offset: int, driver: str) -> None:
        self.name, self.command, self.domain_offset, self.driver = (
            name, command, domain_offset, driver)

    def __enter__(self) -> DdsProbe:
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.node import Node

        self._tmp = tempfile.TemporaryDirectory()
        self.graph = Graph(Path(self._tmp.name), isolated_environment(
            None, self.domain_offset, kind='bench', localhost=True))
        self.context = self.node = None
        try:
            self.process = self.graph.start_command(self.name, self.command)
            self.context = rclpy.Context()
            rclpy.init(context=self.context)
            self.node = Node(self.driver, context=self.context)
            self.executor = SingleThreadedExecutor(context=self.context)
            self.executor.add_node(self.node)
        except BaseException:
            self.__exit__()
            raise
        return self

    def __exit__(self, *exc) -> None:
        import rclpy

        self.graph.stop()
        if self.node is not None:
            self.node.destroy_node()
        if self.context is not None:
            rclpy.try_shutdown(context=self.context)
        self._tmp.cleanup()

    def log_tail(self, chars: int = 500) -> str:
        return self.graph.log(self.name).read_text()[-chars:]

    def publish_until_answered(self, publish: Callable[[], None], answered: Callable[[], bool],
                               timeout_s: float) -> bool:
        """publish() every 0.05 s (spinning in between) until answered() or timeout_s: whether
        the process answered (its subscription matched, its start-up done)."""
        deadline = time.monotonic() + timeout_s
        while not answered() and time.monotonic() < deadline:
            publish()
            self.executor.spin_once(timeout_sec=0.05)
        return answered()

    def paced(self, rate_hz: float, spin_s: float) -> Iterator[tuple[int, float]]:
        """(k, wall s since the first call) for k = 1, 2, ... once the wall clock reaches k /
        rate_hz s after the first call, spinning the driver in between (at most spin_s at a
        time); a caller behind time gets the next k at once. The caller publishes message k
        and stops iterating when done."""
        start = time.monotonic()
        k = 1
        while True:
            due = start + k / rate_hz
            now = time.monotonic()
            while now < due:
                self.executor.spin_once(timeout_sec=min(due - now, spin_s))
                now = time.monotonic()
            yield k, now - start
            k += 1

    def spin_until(self, done: Callable[[], bool], timeout_s: float) -> None:
        """Spin the driver until done() or timeout_s: the process's last answers taken in."""
        deadline = time.monotonic() + timeout_s
        while not done() and time.monotonic() < deadline:
            self.executor.spin_once(timeout_sec=0.05)
