"""sensing_doctor's speed over a 10-minute bag (the aim: under a minute on a 2-core
machine).

A bag is recorded with `sensor_sim --record` (600 s of the default route, seed 5; 60 s with
--quick), then `sensing_doctor BAG --out DIR --quiet` runs as a child process: the whole tool,
process start, the checks, the preset through the nodes offline and the report included. Its
wall and CPU time (user + system of the child) are reported with each section's wall time from
report.json and the load average: compare figures from one run only.
"""

from __future__ import annotations

import json
import sys
import tempfile
from pathlib import Path

from sensing_nodes.bench.pipeline import executable, record_sim_bag, timed_child


def run(quick: bool = False) -> dict:
    """Record the bag, run the doctor over it, return its time figures."""
    duration_s = 60.0 if quick else 600.0
    with tempfile.TemporaryDirectory() as tmp:
        bag, out = Path(tmp) / 'bag', Path(tmp) / 'out'
        record_sim_bag(bag, duration_s)
        run_ = timed_child([executable('sensing_doctor'), str(bag), '--out', str(out),
                            '--quiet'])
        if run_.result.returncode not in (0, 1):
            return {'error': (run_.result.stderr.strip().splitlines() or ['failed'])[-1]}
        report = json.loads((out / 'report.json').read_text())
    return {
        'doctor_bag_seconds': duration_s,
        'doctor_wall_seconds': round(run_.wall_s, 2),
        'doctor_cpu_seconds': round(run_.cpu_s, 2),
        'doctor_exit_status': run_.result.returncode,
        'doctor_section_wall_seconds': {k: round(v, 2) for k, v in report['timings_s'].items()},
        'doctor_load_average_1min_start': round(run_.load_start, 2),
        'doctor_load_average_1min_end': round(run_.load_end, 2),
    }


if __name__ == '__main__':
    print(json.dumps(run(quick='--quick' in sys.argv), indent=1))
