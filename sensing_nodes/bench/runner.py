"""sensing_bench (`make bench`): every benchmark of the package in one run, one JSON, one table.

Each area's module in sensing_nodes.bench (imported here by name, so the import graph shows
every benchmark `make bench` runs) has run(quick) -> dict of figures measured in that run
(rates and the ratios between implementations measured side by side); the ICP areas are
bench/icp's speed.run, accuracy.run_kiss_area and speed.run_fast_lidar. The graph's real-time
factor and latency come from a sensing_demo run. Nothing here asserts a time: the machines are
shared and noisy, so only ratios measured in one run mean much.
"""

from __future__ import annotations

import argparse
import json
import platform
import subprocess
import sys
import tempfile
import time
from datetime import datetime, timezone
from pathlib import Path

from sensing_nodes.bench import (
    allan,
    bags,
    dead_reckoning,
    doctor,
    fusion,
    graph_cpu,
    lines,
    messages,
    pipeline,
    sim,
)
from sensing_nodes.bench.icp import accuracy as icp_accuracy
from sensing_nodes.bench.icp import speed as icp_speed

# Each area's figures, in the order they run (the graph's, from sensing_demo, last).
AREA_RUNS = {
    'sim': sim.run, 'dead_reckoning': dead_reckoning.run, 'lines': lines.run,
    'icp': icp_speed.run, 'icp_kiss': icp_accuracy.run_kiss_area,
    'icp_fast_lidar': icp_speed.run_fast_lidar, 'allan': allan.run,
    'graph_cpu': graph_cpu.run,
    'pipeline': pipeline.run, 'fusion': fusion.run, 'bags': bags.run, 'messages': messages.run,
    'doctor': doctor.run,
}
AREAS = list(AREA_RUNS)


def demo_figures(quick: bool, extra: tuple[str, ...] = ()) -> dict:
    """Real-time factor, latency and dropped scans of the whole graph, from a sensing_demo run
    (with `extra` options)."""
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / 'run'
        demo = Path(sys.argv[0]).resolve().parent / 'sensing_demo'
        cmd = [str(demo) if demo.is_file() else 'sensing_demo', '--out', str(out), '--quiet',
               '--duration', '40' if quick else '130', *extra]
        result = subprocess.run(cmd, capture_output=True, text=True)
        if result.returncode != 0:
            return {'error': result.stderr.strip().splitlines()[-1:] or ['sensing_demo failed']}
        report = json.loads((out / 'report.json').read_text())
    scans = report['scans']
    return {
        'real_time_factor': report['real_time_factor'],
        'latency_p50_ms': report['latency_ms']['p50'],
        'latency_p99_ms': report['latency_ms']['p99'],
        'scans_published': scans['published_by_sim'],
        'scans_matched': scans['processed_by_icp_matcher'],
        'scans_lines': scans['processed_by_line_extractor'],
        'fused_final_position_error_m': report['estimates']['fused'].get('final_position_error_m'),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog='sensing_bench', description=__doc__.split('\n\n')[0])
    parser.add_argument('--quick', action='store_true', help='smaller runs (a smoke test)')
    parser.add_argument('--out', type=Path, default=Path('bench_results.json'),
                        help='JSON output file (default bench_results.json)')
    parser.add_argument(
        '--only', nargs='*', choices=AREAS + ['graph'], help='run only these areas'
    )
    args = parser.parse_args(argv)

    results: dict = {
        'when': datetime.now(timezone.utc).isoformat(timespec='seconds'),
        'machine': f'{platform.machine()}, {platform.python_implementation()} '
                   f'{platform.python_version()}',
        'quick': args.quick,
    }
    for area in args.only or AREAS + ['graph']:
        print(f'[bench] {area} ...', flush=True)
        start = time.monotonic()
        try:
            if area == 'graph':
                figures = demo_figures(args.quick)
                # The processing nodes in one process (sensing_graph), allowed up to 20x (the
                # demo is paced by the fused output: it runs as fast as the machine allows; a
                # cap of 10x itself reached only 9.1x, the pacing's own slack).
                one = demo_figures(args.quick, ('--one-process', '--rate', '20'))
                figures.update({f'one_process_rate_20_{k}': v for k, v in one.items()
                                if k in ('error', 'real_time_factor', 'scans_published',
                                         'scans_matched', 'scans_lines')})
            else:
                figures = AREA_RUNS[area](quick=args.quick)
        except Exception as exc:  # a failing area must not hide the others' figures
            figures = {'error': f'{type(exc).__name__}: {exc}'}
        figures['bench_seconds'] = round(time.monotonic() - start, 1)
        results[area] = figures
    args.out.write_text(json.dumps(results, indent=2, default=float) + '\n')

    print(f'\n{"area":<16}{"figure":<44}{"value":>14}')
    for area in args.only or AREAS + ['graph']:
        for key, value in results[area].items():
            if isinstance(value, float):
                value = f'{value:.4g}'
            print(f'{area:<16}{key:<44}{str(value):>14}')
    print(f'\nwrote {args.out}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
