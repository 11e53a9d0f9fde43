"""Run the fusion core over a recorded bag (ROS 1 or rosbag2, read with rosbags) with a
complementary_fusion parameter file, as the node would fuse it, and print the final pose.

    python -m sensing_nodes.tools.fuse_bag BAG --params config/fusion_jackal_test2.yaml \
        [--expect X Y --tolerance M]

Inputs are taken from the topics the parameter file names (wheel_odom.topic, imu.topic,
scan_match.topic); messages are converted, validated and retimed (delay_s) by the node's own
converter, processed in stamp order (wheel, IMU, scan at equal stamps). Exit 1 when --expect is
given and the final position is further than --tolerance from it.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np
import yaml
from rosbags.highlevel import AnyReader

from sensing_nodes.core.evaluation.fusion import inputs_from_params
from sensing_nodes.core.fusion.complementary import InputRecord
from sensing_nodes.core.fusion.ekf import EkfFusion, EkfSettings
from sensing_nodes.core.geometry.imu_mount import mount_rotation
from sensing_nodes.ros.fusion_readings import IMU, SCAN, WHEEL, ReadingConverter

RANK = {WHEEL: 0, IMU: 1, SCAN: 2}
DEFAULT_TOPICS = {WHEEL: '/wheel/odom', IMU: '/imu/data', SCAN: '/scan_match/keyframe_odom'}


def load_params(path: str | Path) -> dict:
    """The complementary_fusion parameters of a node parameter file (dotted keys nested)."""
    with open(path) as f:
        data = yaml.safe_load(f)
    return data['complementary_fusion']['ros__parameters']


def fuse_bag(bag: str | Path, params: dict) -> dict:
    """Fuse every input message of the bag; the final pose (m, rad), its covariance and the
    counts of messages read, rejected and gated per input."""
    configs = inputs_from_params(params)
    ekf_params = params.get('ekf', {})
    settings = EkfSettings(**{k: float(v) for k, v in ekf_params.items()
                              if k in EkfSettings.__dataclass_fields__})
    fusion = EkfFusion(configs, settings)
    imu = params.get('imu', {})
    converter = ReadingConverter(
        'ekf', fusion.inputs, imu.get('source', 'integrated'),
        mount_rotation(*(float(imu.get(f'mount_{a}_rad', 0.0)) for a in ('roll', 'pitch', 'yaw'))),
        bool(params.get('level_with_imu_tilt', False)))
    topics = {params.get(name, {}).get('topic', DEFAULT_TOPICS[name]): name
              for name in fusion.inputs}
    records = {name: InputRecord(name) for name in fusion.inputs}
    rejected: dict[str, int] = {}
    events = []
    with AnyReader([Path(bag)]) as reader:
        connections = [c for c in reader.connections if c.topic in topics]
        missing = set(topics) - {c.topic for c in connections}
        if missing:
            raise SystemExit(f'fuse_bag: {bag} has no topic(s) {sorted(missing)}')
        for connection, _, raw in reader.messages(connections=connections):
            msg = reader.deserialize(raw, connection.msgtype)
            name = topics[connection.topic]
            events.append((converter.stamp_ns(name, msg), RANK[name],
                           len(events), name, msg))
    events.sort(key=lambda e: e[:3])
    for stamp, _, _, name, msg in events:
        records[name].received += 1
        reading, problem = converter.reading(name, msg, stamp, records[name])
        if reading is None:
            rejected[name] = rejected.get(name, 0) + 1
            continue
        fusion.update(name, reading)
    state = fusion.state
    return {'final_pose': list(state.pose), 'final_covariance': state.covariance.tolist(),
            'stamp_ns': state.stamp_ns,
            'received': {n: r.received for n, r in records.items()},
            'rejected': rejected, 'gated': dict(fusion.gated)}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('bag')
    parser.add_argument('--params', required=True, help='complementary_fusion parameter file')
    parser.add_argument('--expect', nargs=2, type=float, metavar=('X', 'Y'))
    parser.add_argument('--tolerance', type=float, default=0.1383)
    args = parser.parse_args(argv)
    result = fuse_bag(args.bag, load_params(args.params))
    if args.expect:
        x, y = result['final_pose'][:2]
        result['distance_to_expected_m'] = math.hypot(x - args.expect[0], y - args.expect[1])
    print(json.dumps(result, indent=1, default=lambda v: np.asarray(v).tolist()))
    if args.expect and result['distance_to_expected_m'] > args.tolerance:
        print(f"fuse_bag: final position {result['distance_to_expected_m']:.4f} m from the "
              f'expected one (> {args.tolerance} m)', file=sys.stderr)
        return 1
    return 0


if __name__ == '__main__':
    sys.exit(main())
