"""A downstream consumer of a running graph, standing in for slam_toolbox or nav2: a plain rclpy
process that knows nothing of sensing_nodes (it imports only rclpy and ROS messages). It listens
to /tf, /tf_static, the scans, the odometry and the graph's raw inputs until the graph has been
quiet for --quiet-s (or --timeout-s passes), then prints one JSON verdict on stdout:

- tree: the parent of each frame (from /tf and /tf_static) and whether the scans' frame chains
  up to the fixed frame through the base frame (odom -> base_link -> laser);
- every scan stamp can be transformed: a fixed -> base sample at or after it within --within-s
  (and one at or before it, which interpolation needs too);
- per transform (parent -> child), how many /tf stamps were ahead of the newest input stamp
  (/clock, the scans, the raw inputs) this process had received when the transform arrived;
- per transform, how many stamps repeated the previous one (tf2 drops a repeat with a
  TF_REPEATED_DATA warning; two owners of one frame show up here too).

Run by test/test_downstream_consumer.py as a subprocess.
"""

from __future__ import annotations

import argparse
import bisect
import json
import sys
import time

import rclpy
from nav_msgs.msg import Odometry
from rclpy.node import Node
from rclpy.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    QoSProfile,
    ReliabilityPolicy,
    qos_profile_sensor_data,
)
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import Imu, JointState, LaserScan
from tf2_msgs.msg import TFMessage

# As tf2_ros's listener: /tf reliable volatile, /tf_static transient local (a deep queue: the
# consumer must not lose samples to its own slowness).
TF = QoSProfile(reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE,
                history=HistoryPolicy.KEEP_LAST, depth=1000)
TF_STATIC = QoSProfile(reliability=ReliabilityPolicy.RELIABLE,
                       durability=DurabilityPolicy.TRANSIENT_LOCAL,
                       history=HistoryPolicy.KEEP_LAST, depth=100)
RELIABLE = QoSProfile(reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST,
                      depth=1000)


def ns(stamp) -> int:
    return stamp.sec * 1_000_000_000 + stamp.nanosec


class Consumer(Node):
    def __init__(self, args) -> None:
        super().__init__('downstream_consumer')
        self.args = args
        self.newest_input_ns: int | None = None
        self.last_arrival = None
        self.static_parents: dict[str, str] = {}
        self.dynamic_parents: dict[str, set[str]] = {}
        self.samples: dict[tuple[str, str], list[int]] = {}   # (parent, child) -> stamps
        self.duplicates: dict[str, int] = {}        # 'parent->child' -> repeated stamps
        self.future: dict[str, int] = {}            # 'parent->child' -> stamps ahead of inputs
        self.future_first: list[dict] = []
        self.tf_count = 0
        self.scans: list[int] = []
        self.scan_frames: set[str] = set()
        self.odometry = 0
        self.create_subscription(TFMessage, '/tf', self.on_tf, TF)
        self.create_subscription(TFMessage, '/tf_static', self.on_tf_static, TF_STATIC)
        self.create_subscription(LaserScan, args.scan_topic, self.on_scan, qos_profile_sensor_data)
        self.create_subscription(Odometry, args.odom_topic, self.on_odometry, RELIABLE)
        self.create_subscription(Clock, '/clock', lambda m: self.on_input(ns(m.clock)), RELIABLE)
        self.create_subscription(JointState, '/joint_states',
                                 lambda m: self.on_input(ns(m.header.stamp)),
                                 qos_profile_sensor_data)
        self.create_subscription(Imu, '/imu/data_raw', lambda m: self.on_input(ns(m.header.stamp)),
                                 qos_profile_sensor_data)

    def on_input(self, stamp: int) -> None:
        self.last_arrival = time.monotonic()
        if self.newest_input_ns is None or stamp > self.newest_input_ns:
            self.newest_input_ns = stamp

    def on_scan(self, msg: LaserScan) -> None:
        self.on_input(ns(msg.header.stamp))
        self.scans.append(ns(msg.header.stamp))
        self.scan_frames.add(msg.header.frame_id.lstrip('/'))

    def on_odometry(self, msg: Odometry) -> None:
        self.last_arrival = time.monotonic()
        self.odometry += 1

    def on_tf(self, msg: TFMessage) -> None:
        self.last_arrival = time.monotonic()
        for t in msg.transforms:
            self.tf_count += 1
            parent, child = t.header.frame_id.lstrip('/'), t.child_frame_id.lstrip('/')
            stamp = ns(t.header.stamp)
            self.dynamic_parents.setdefault(child, set()).add(parent)
            stamps = self.samples.setdefault((parent, child), [])
            pair = f'{parent}->{child}'
            if stamps and stamps[-1] == stamp:
                self.duplicates[pair] = self.duplicates.get(pair, 0) + 1
            stamps.append(stamp)
            if self.newest_input_ns is None or stamp > self.newest_input_ns:
                self.future[pair] = self.future.get(pair, 0) + 1
                if len(self.future_first) < 5:
                    self.future_first.append({'pair': pair, 'stamp_ns': stamp,
                                              'newest_input_ns': self.newest_input_ns})

    def on_tf_static(self, msg: TFMessage) -> None:
        for t in msg.transforms:
            self.static_parents[t.child_frame_id.lstrip('/')] = t.header.frame_id.lstrip('/')

    def verdict(self) -> dict:
        a = self.args
        parents = {c: sorted(p) for c, p in self.dynamic_parents.items()}
        parents.update({c: [p] for c, p in self.static_parents.items()})
        chains = {}
        for frame in sorted(self.scan_frames):
            chain, current = [frame], frame
            while current in parents and len(parents[current]) == 1 and len(chain) < 20:
                current = parents[current][0]
                chain.append(current)
            chains[frame] = list(reversed(chain))
        tree_ok = bool(chains) and all(
            c[:2] == [a.fixed_frame, a.base_frame] and len(c) == 3 for c in chains.values())
        stamps = sorted(self.samples.get((a.fixed_frame, a.base_frame), []))
        within = int(a.within_s * 1e9)
        no_later, no_earlier = [], []
        for s in self.scans:
            i = bisect.bisect_left(stamps, s)
            if i == len(stamps) or stamps[i] - s > within:
                no_later.append(s)
            if not (i < len(stamps) and stamps[i] == s) and i == 0:
                no_earlier.append(s)
        return {
            'scans': len(self.scans), 'scan_frames': sorted(self.scan_frames),
            'odometry': self.odometry, 'tf_transforms': self.tf_count,
            'parents': parents, 'chains': chains, 'tree_ok': tree_ok,
            'odom_base_samples': len(stamps),
            'scans_without_sample_after': len(no_later),
            'scans_without_sample_after_first': no_later[:5],
            'scans_without_sample_before': len(no_earlier),
            'future_stamps': self.future, 'future_first': self.future_first,
            'repeated_stamps': self.duplicates,
            'multiple_parents': sorted(c for c, p in parents.items() if len(p) > 1),
        }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--fixed-frame', default='odom')
    parser.add_argument('--base-frame', default='base_link')
    parser.add_argument('--scan-topic', default='/scan')
    parser.add_argument('--odom-topic', default='/odometry/filtered')
    parser.add_argument('--within-s', type=float, default=0.1)
    parser.add_argument('--quiet-s', type=float, default=4.0)
    parser.add_argument('--timeout-s', type=float, default=300.0)
    args = parser.parse_args()
    rclpy.init(args=['downstream_consumer'])
    node = Consumer(args)
    print('ready', file=sys.stderr, flush=True)
    deadline = time.monotonic() + args.timeout_s
    while time.monotonic() < deadline:
        rclpy.spin_once(node, timeout_sec=0.05)
        if node.last_arrival is not None and time.monotonic() - node.last_arrival > args.quiet_s:
            break
    print(json.dumps(node.verdict()), flush=True)
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


if __name__ == '__main__':
    sys.exit(main())
