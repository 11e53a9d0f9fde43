"""The doctor's run: every section over the bag in order, then the files it writes."""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from sensing_nodes.bags.survey import survey_bag
from sensing_nodes.core.diagnosis.check import PROBLEM, worst
from sensing_nodes.doctor.diagnosis import (
    EXIT_OK,
    EXIT_PROBLEMS,
    Diagnosis,
    cross_section,
    find_inputs,
    imu_section,
    motion_tracks,
    noise_section,
    offset_section,
    read_declared,
    refusal_section,
    scan_section,
    tf_section,
    timing_section,
    wheel_columns,
    wheel_section,
)
from sensing_nodes.doctor.fused import fused_section
from sensing_nodes.doctor.preset import build_preset, preset_text
from sensing_nodes.doctor.report import make_plots, report_html, report_json

SECTIONS = (('inputs', find_inputs), ('parameters', read_declared), ('refusals', refusal_section),
            ('timing', timing_section), ('wheels', wheel_section), ('tracks', motion_tracks),
            ('scan matching', scan_section), ('imu', imu_section), ('offsets', offset_section),
            ('cross', cross_section), ('noise', noise_section), ('tf', tf_section),
            ('preset', build_preset))


def diagnose(bag: Path, args: argparse.Namespace,
             progress=None) -> Diagnosis:
    """Read the bag and run every check; SensorBagError when the bag cannot be read."""
    started = time.monotonic()
    d = Diagnosis(survey_bag(bag, progress), args)
    d.timings['read'] = time.monotonic() - started
    for name, section in SECTIONS:
        if name == 'wheels' and d.joints is not None:
            wheel_columns(d)
        started = time.monotonic()
        if progress is not None:
            progress(name)
        section(d)
        d.timings[name] = time.monotonic() - started
    return d


def write_outputs(d: Diagnosis, out: Path, fuse: bool) -> int:
    """params.yaml, the fused comparison, plots, report.json and report.html; the exit status."""
    out.mkdir(parents=True, exist_ok=True)
    d.preset_text = preset_text(d, out)
    (out / 'params.yaml').write_text(d.preset_text)
    if fuse:
        started = time.monotonic()
        fused_bag = out / 'fused_bag'
        if fused_bag.exists():
            import shutil
            shutil.rmtree(fused_bag)
        fused_section(d, out)
        d.timings['fused'] = time.monotonic() - started
    started = time.monotonic()
    make_plots(d)
    d.timings['plots'] = time.monotonic() - started
    status = EXIT_PROBLEMS if worst(d.checks) == PROBLEM else EXIT_OK
    report = report_json(d, status)
    (out / 'report.json').write_text(json.dumps(report, indent=1))
    (out / 'report.html').write_text(report_html(d, report))
    return status
