"""Running node executables as processes and exchanging messages with them over real DDS."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Callable

import rclpy
from hypothesis import Phase

BIN = Path(sys.executable).parent
REPO = Path(__file__).resolve().parents[1]

# Hypothesis over DDS: shrinking re-runs a node for each candidate (minutes per failure), so a
# failing example is reported as generated.
NO_SHRINK = (Phase.explicit, Phase.generate)


def _ros_value(value: Any) -> str:
    if isinstance(value, bool):
        return 'true' if value else 'false'
    if isinstance(value, (list, tuple)):
        return '[' + ','.join(_ros_value(v) for v in value) + ']'
    if isinstance(value, str):
        return value if value else "''"
    return repr(value)


class NodeProcess:
    """An executable from the venv run as its own process, its output kept in a log file.

    Use as a context manager; on exit it is stopped with SIGINT (then SIGKILL).
    """

    def __init__(
        self,
        executable: str,
        params: dict[str, Any] | None = None,
        remaps: dict[str, str] | None = None,
        params_file: str | Path | None = None,
        extra_args: list[str] | None = None,
        env: dict[str, str] | None = None,
    ) -> None:
        self.cmd = [str(BIN / executable), *(extra_args or []), '--ros-args']
        if params_file:
            self.cmd += ['--params-file', str(params_file)]
        for name, value in (params or {}).items():
            self.cmd += ['-p', f'{name}:={_ros_value(value)}']
        for src, dst in (remaps or {}).items():
            self.cmd += ['-r', f'{src}:={dst}']
        self.env = {**os.environ, **(env or {})}
        self._log = tempfile.NamedTemporaryFile('w+', prefix=f'{executable}-', suffix='.log')
        self.proc: subprocess.Popen | None = None

    def start(self) -> NodeProcess:
        self.proc = subprocess.Popen(
            self.cmd, stdout=self._log, stderr=subprocess.STDOUT, env=self.env,
            start_new_session=True)
        return self

    def __enter__(self) -> NodeProcess:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def stop(self, timeout: float = 10.0) -> int | None:
        if self.proc is None:
            return None
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        return self.proc.returncode

    def wait(self, timeout: float) -> int:
        assert self.proc is not None
        return self.proc.wait(timeout)

    def output(self) -> str:
        self._log.flush()
        return Path(self._log.name).read_text(errors='replace')


def run_to_exit(executable: str, args: list[str], timeout: float = 60.0,
                env: dict[str, str] | None = None) -> subprocess.CompletedProcess:
    """Run an executable to completion, capturing its output (for bad-parameter exits and
    tools); `env` adds to (or overrides) this process's environment."""
    return subprocess.run(
        [str(BIN / executable), *args], capture_output=True, text=True, timeout=timeout,
        env=None if env is None else {**os.environ, **env})


def spin_until(node, condition: Callable[[], bool], timeout: float) -> bool:
    """Spin the probe node until condition() holds or timeout (wall s) passes."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if condition():
            return True
        rclpy.spin_once(node, timeout_sec=0.05)
    return condition()


class Collector:
    """Subscribes the probe to a topic and keeps every message received."""

    def __init__(self, node, msg_type, topic: str, qos) -> None:
        self.messages: list[Any] = []
        self._node = node
        self._sub = node.create_subscription(msg_type, topic, self.messages.append, qos)

    def matched(self) -> bool:
        """Whether a writer of the topic has matched this reader (the node's output can reach
        it)."""
        return self._sub.get_publisher_count() > 0

    def wait_for(self, count: int, timeout: float) -> list[Any]:
        spin_until(self._node, lambda: len(self.messages) >= count, timeout)
        return self.messages

    def close(self) -> None:
        self._node.destroy_subscription(self._sub)


def publish_paced(node, publisher, messages, pause_s: float = 0.002) -> None:
    """Publish messages one by one, paced like a live driver (best effort must not overrun the
    reader) and draining the probe's own subscriptions in between."""
    for msg in messages:
        publisher.publish(msg)
        time.sleep(pause_s)
        for _ in range(3):
            rclpy.spin_once(node, timeout_sec=0)


def publish_until(node, publisher, msg, answered: Callable[[], bool],
                  timeout: float = 20.0, outputs: Collector | None = None) -> bool:
    """Publish msg every 0.2 s until answered() holds: best effort loses whatever is sent before
    the reader has matched this writer. Extra copies arrive as duplicate stamps, which a node
    skips without answering, so with `outputs` (the Collector of the answer) the first copy
    waits until the node's writer has matched that reader too."""
    if not spin_until(node, lambda: publisher.get_subscription_count() > 0, timeout):
        return False
    if outputs is not None:
        if not spin_until(node, outputs.matched, timeout):
            return False
    # Discovery is not symmetric in time: give the node's writers a moment to see our readers
    # too (with `outputs`, to finish matching on their side), or an answer can be lost.
    spin_until(node, lambda: False, 0.5)
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        publisher.publish(msg)
        if spin_until(node, answered, 0.2):
            return True
    return answered()


def assert_every_kind_warned(stream, kinds: dict[str, str | None], examples_per_kind: int) -> None:
    """After a bad-input module's examples: the node is alive, every malformed kind was sent and
    left a [WARN] line matching its key (None: a kind that needs no warning)."""
    import re

    log = stream.node.output()
    assert stream.node.alive(), log
    assert stream.resumed >= examples_per_kind * len(kinds)
    assert stream.kinds_sent == set(kinds), set(kinds) - stream.kinds_sent
    warnings = '\n'.join(line for line in log.splitlines() if '[WARN]' in line)
    for kind in sorted(stream.kinds_sent):
        key = kinds[kind]
        if key is not None:
            assert re.search(re.escape(key), warnings), f'no warning for {kind} ({key}):\n{log}'


def laser_scan(t_ns: int, ranges, frame_id: str = 'laser', angle_min: float = -3.141592653589793,
               increment: float = 0.017453292519943295, range_min: float = 0.12,
               range_max: float = 8.0, intensities=None):
    """A sensor_msgs/LaserScan as a driver would send it (any field may be made malformed)."""
    import numpy as np
    from sensor_msgs.msg import LaserScan

    from sensing_nodes.ros.conversions import float32_array, ns_to_stamp

    msg = LaserScan()
    msg.header.stamp = ns_to_stamp(t_ns)
    msg.header.frame_id = frame_id
    msg.angle_min, msg.angle_increment = float(angle_min), float(increment)
    msg.angle_max = float(angle_min + increment * max(len(ranges) - 1, 0))
    msg.range_min, msg.range_max = float(range_min), float(range_max)
    msg.time_increment, msg.scan_time = 0.0, 0.1
    msg.ranges = float32_array(np.asarray(ranges, dtype=np.float32))
    if intensities is not None:
        msg.intensities = float32_array(np.asarray(intensities, dtype=np.float32))
    return msg


def carmen_pipeline(log: Path, tmp: Path, mode: str = 'keyframe') -> Path:
    """docs/real-data.md's commands on a CARMEN log: carmen_to_bag into tmp/log, then
    icp_matcher (in `mode`: keyframe, with which the fusion's bounds on these logs were
    measured) and the fusion (config/fusion_carmen.yaml) through sensing_pipeline into tmp/out,
    which is returned."""
    from sensing_nodes.paths import config_file
    from sensing_nodes.tools import pipeline
    from sensing_nodes.tools.carmen_to_bag import convert

    convert(log, tmp / 'log')
    assert pipeline.main([
        str(tmp / 'log'), str(tmp / 'out'), '--nodes', 'icp_matcher,complementary_fusion',
        '--remap', '/odom:=/wheel/odom', '--param', 'icp_matcher:laser_x_m:=0.0',
        '--param', 'icp_matcher:max_gap_s:=60.0',
        '--param', 'icp_matcher:odom_max_extrapolation_s:=1.0',
        '--param', f'icp_matcher:mode:={mode}',
        '--params-file', str(config_file('fusion_carmen.yaml')), '--no-progress']) == 0
    return tmp / 'out'
