"""sensing_doctor: diagnose a robot's bag without ground truth, and write a preset for this
package's nodes.

    sensing_doctor BAG [--out DIR] [--params-file FILE ...] [--joint-topic T] [--scan-topic T]
                       [--imu-topic T] [--odom-topic T] [--left-joint N --right-joint N]
                       [--no-fusion] [--quiet]

Finds the inputs by type (LaserScan, Imu, JointState, Odometry, /tf, /tf_static), checks each
(timing, REP 103 axes and the IMU mount, REP 117 ranges, wheel geometry and laser mount against
scan matching, covariances, time offsets, two publishers of a transform) against what the
nodes are told (--params-file: a robot preset; default the package's config/ files, and
/tf_static), and writes DIR/report.html, DIR/report.json and DIR/params.yaml (a preset
loadable by sensing_replay --launch --params-file and sensing_pipeline --params-file). The
report ends with the preset run through the nodes offline (sensing_pipeline's code) and the
fused output against each input. Checks, methods and limits: docs/doctor.md.

Exit status: 0 the bag can be used (warnings allowed), 1 problems found, 2 the bag cannot be
read (the reason named).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from sensing_nodes.bags.sensor_streams import SensorBagError, stderr_progress
from sensing_nodes.core.diagnosis.check import OK, PROBLEM, SKIPPED, WARNING, plural
from sensing_nodes.doctor.diagnosis import EXIT_BAD_INPUT, PROG, Diagnosis
from sensing_nodes.doctor.preset import commands
from sensing_nodes.doctor.run import diagnose, write_outputs
from sensing_nodes.paths import config_file


def print_summary(d: Diagnosis, out: Path, status: int) -> None:
    """The verdict first (usable with params.yaml, the fused figures), then the problems
    params.yaml fixes apart from those it cannot, the warnings, the counts and the files."""
    from sensing_nodes.doctor.fused import figures
    from sensing_nodes.doctor.report import verdict

    v = verdict(d)
    answer = {True: 'yes', False: 'no', None: 'not run'}[v['usable_with_params_yaml']]
    print(f'{PROG}: usable with {out / "params.yaml"}: {answer} ({v["why"]})')
    for name, f in v['fused_against'].items():
        why = v['distrusted'].get(name)
        print(f'  fused against {name}: {figures(f)}' + (f' (not followed: {why})' if why else ''))
    problems = [c for c in d.checks if c.verdict == PROBLEM and c.name != 'fused']
    for title, group in (('fixed by params.yaml', [c for c in problems if c.fix]),
                         ('not fixable by params.yaml', [c for c in problems if not c.fix])):
        if group:
            print(f'{plural(len(group), "problem")} {title}:')
        for c in group:
            print(f'  PROBLEM {c.subject}: {c.name}: {c.advice}'
                  + (f' -> {c.fix}' if c.fix and 'params.yaml' not in c.advice else ''))
    for c in d.checks:
        if c.verdict == WARNING:
            print(f'  WARNING {c.subject}: {c.name}: {c.advice}')
    counts = {v: sum(c.verdict == v for c in d.checks) for v in (PROBLEM, WARNING, OK, SKIPPED)}
    print(f'{PROG}: {plural(counts[PROBLEM], "problem")}, {plural(counts[WARNING], "warning")}, '
          f'{counts[OK]} ok, {counts[SKIPPED]} not judged; wrote {out / "report.html"}, '
          f'{out / "report.json"}, {out / "params.yaml"} (exit {status})')


def print_robot_commands(d: Diagnosis, out: Path) -> None:
    """The commands that run the preset on the robot itself (docs/doctor.md)."""
    run = commands(d, (out / 'params.yaml').resolve())
    print(f'{PROG}: on the robot (a ROS 2 workspace): {run["ros2 launch"]}')
    print(f'{PROG}: or the same nodes in one process: {run["sensing_graph"]}')


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog=PROG, description=__doc__.split('\n\n')[0])
    parser.add_argument('bag', type=Path, help='rosbag2 folder (MCAP or sqlite3) or ROS 1 .bag')
    parser.add_argument('--out', type=Path, help='folder for report.html, report.json, '
                        'params.yaml (default: doctor_<bag name>)')
    parser.add_argument('--params-file', action='append', default=[], type=Path,
                        help='what the nodes are told today (a robot preset); repeatable; '
                        'default: the package\'s config/ files')
    for kind in ('joint', 'scan', 'imu', 'odom'):
        parser.add_argument(f'--{kind}-topic', help=f'the {kind} topic, where the bag has '
                            'several candidates')
    parser.add_argument('--left-joint', help='left wheel joint name')
    parser.add_argument('--right-joint', help='right wheel joint name')
    parser.add_argument('--no-fusion', action='store_true',
                        help='skip running the preset through the nodes')
    parser.add_argument('--quiet', action='store_true', help='no progress on stderr')
    args = parser.parse_args(argv)
    for i, f in enumerate(args.params_file):
        if not f.is_file():
            named = config_file(f'robots/{f}.yaml')
            if not named.is_file():
                parser.error(f'--params-file {f}: no such file or robot preset')
            args.params_file[i] = named
    out = args.out or Path(f'doctor_{args.bag.name.removesuffix(".bag")}')
    progress = None if args.quiet else stderr_progress(PROG)
    try:
        d = diagnose(args.bag, args, progress)
    except SensorBagError as exc:
        print(f'{PROG}: error: cannot use the bag: {exc}', file=sys.stderr)
        return EXIT_BAD_INPUT
    status = write_outputs(d, out, not args.no_fusion)
    print_summary(d, out, status)
    print_robot_commands(d, out)
    return status


if __name__ == '__main__':
    sys.exit(main())
