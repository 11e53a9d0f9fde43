"""report.json and a self-contained report.html (plots inline as PNG data)."""

from __future__ import annotations

import base64
import html
import io
from pathlib import Path
from typing import Any

import numpy as np

from sensing_nodes.core.diagnosis.check import OK, PROBLEM, SKIPPED, WARNING, Check, worst
from sensing_nodes.core.geometry import se2
from sensing_nodes.doctor.diagnosis import PROG, Diagnosis, pose_at
from sensing_nodes.doctor.preset import commands

# --- the report -----------------------------------------------------------------------------

def _png(fig) -> str:
    buffer = io.BytesIO()
    fig.savefig(buffer, format='png', dpi=90)
    return base64.b64encode(buffer.getvalue()).decode('ascii')


def _anchored(track: tuple[np.ndarray, np.ndarray], anchor: tuple[np.ndarray, np.ndarray]
              ) -> np.ndarray | None:
    """A pose track expressed in the anchor track's frame, coinciding at its first stamp."""
    from sensing_nodes.core.evaluation.metrics import express_in_reference_frame

    t, p = track
    at = pose_at(t, p, anchor[0][:1])[0]
    if not np.isfinite(at).all():
        return None
    origin = se2.compose(tuple(anchor[1][0]), se2.inverse(tuple(at)))
    return express_in_reference_frame(origin, p)


def _finish(d: Diagnosis, name: str, fig, ax, xlabel: str, ylabel: str, title: str) -> None:
    """Label and grid a plot, keep it as d.plots[name] (inline PNG) and close it."""
    import matplotlib.pyplot as plt

    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.grid(alpha=0.3, which='both')
    ax.set_title(title)
    fig.tight_layout()
    d.plots[name] = _png(fig)
    plt.close(fig)


def make_plots(d: Diagnosis) -> None:
    """Trajectories of every input and the fused output, yaw rates, Allan deviation."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    if d.pose_tracks:
        anchor = d.pose_tracks.get('fused') or d.pose_tracks.get('scan matching') or \
            next(iter(d.pose_tracks.values()))
        fig, ax = plt.subplots(figsize=(7, 6))
        for name, track in d.pose_tracks.items():
            p = _anchored(track, anchor)
            if p is not None:
                ax.plot(p[:, 0], p[:, 1], lw=2.0 if name == 'fused' else 1.0, label=name)
        ax.set_aspect('equal', adjustable='datalim')
        ax.legend(loc='best', fontsize=8)
        _finish(d, 'trajectories', fig, ax, 'x (m)', 'y (m)',
                'Each input and the fused output, anchored at the fused output\'s start')
    if len(d.tracks) > 1:
        fig, ax = plt.subplots(figsize=(9, 3.5))
        for name, (t, yaw) in d.tracks.items():
            edges = np.arange(t[0], t[-1], 100_000_000)
            if edges.size < 3:
                continue
            y = np.interp(edges - t[0], t - t[0], yaw)
            ax.plot((edges[1:] - d.survey.times[next(iter(d.survey.times))].record_ns[0]) * 1e-9,
                    np.degrees(np.diff(y) / 0.1), lw=0.8, label=name)
        ax.legend(loc='best', fontsize=8)
        _finish(d, 'yaw rates', fig, ax, 'bag time (s)', 'yaw rate (deg/s)',
                'Yaw rate of each source (0.1 s means): time offsets show as shifts')
    noise = next((c for c in d.checks if c.name == 'gyro_noise' and c.verdict != SKIPPED), None)
    if noise is not None:
        fig, ax = plt.subplots(figsize=(6, 4))
        ax.loglog(noise.details['allan_tau_s'], noise.details['allan_dev_rad_s'], 'o-', ms=3)
        _finish(d, 'gyro Allan deviation', fig, ax, 'cluster time tau (s)',
                'Allan deviation (rad/s)',
                f'Gyro z (base_link) Allan deviation while still: {noise.subject}')


def report_json(d: Diagnosis, status: int) -> dict[str, Any]:
    """Every check, verdict and number, the inputs, the preset and the fused comparison."""
    counts = {v: sum(c.verdict == v for c in d.checks) for v in (OK, WARNING, PROBLEM, SKIPPED)}
    return {'tool': PROG, 'bag': d.survey.path, 'duration_s': d.survey.duration_s,
            'exit_status': status, 'verdict': worst(d.checks), 'counts': counts,
            'topics': {t: {'type': ty, 'count': n} for t, (ty, n) in d.survey.topics.items()},
            'base_frame': d.base_frame, 'checks': [c.as_dict() for c in d.checks],
            'preset': {'nodes': list(d.nodes), 'remaps': d.remaps, 'parameters': d.preset,
                       'commands': commands(d, Path('params.yaml'))},
            'time_offsets_s': d.offsets, 'offset_reference': d.offset_reference,
            'noise': d.noise, 'fused': d.fused, 'timings_s': d.timings}


COLOURS = {OK: '#d9f2d9', WARNING: '#fff0c2', PROBLEM: '#f8d0d0', SKIPPED: '#eeeeee'}


def _number(c: Check) -> str:
    if c.value is None:
        return ''
    v = c.value
    shown = f'{v:.4g}' if isinstance(v, float) else str(v)
    return f'{shown} {html.escape(c.unit)}'


def report_html(d: Diagnosis, report: dict[str, Any]) -> str:
    """One self-contained page: the verdicts, the checks, the plots (inline PNG), the preset
    and the fused output against each input."""
    e = html.escape
    rows = ''.join(
        f'<tr style="background:{COLOURS[c.verdict]}"><td>{e(c.subject)}</td><td>{e(c.name)}'
        f'</td><td><b>{e(c.verdict)}</b></td><td>{_number(c)}</td><td>{e(c.limit)}</td>'
        f'<td>{e(c.advice)}</td></tr>' for c in d.checks)
    topics = ''.join(f'<tr><td>{e(t)}</td><td>{e(v["type"])}</td><td>{v["count"]}</td></tr>'
                     for t, v in sorted(report['topics'].items()))
    compared = ''.join(
        f'<tr><td>{e(n)}</td><td>{v.get("rms_position_error_m", float("nan")):.4f}</td>'
        f'<td>{v.get("final_position_error_m", float("nan")):.4f}</td>'
        f'<td>{v["rms_heading_error_deg"]:.3f}</td><td>{v["final_heading_error_deg"]:.3f}</td>'
        '</tr>' for n, v in d.fused.get('compared', {}).items())
    findings = ''.join(
        f'<li style="background:{COLOURS[c.verdict]}"><b>{e(c.verdict)}</b> {e(c.subject)} '
        f'({e(c.name)}, {_number(c)}): {e(c.advice)}</li>'
        for verdict in (PROBLEM, WARNING) for c in d.checks if c.verdict == verdict) or \
        '<li>nothing to change</li>'
    plots = ''.join(f'<h3>{e(title)}</h3><img alt="{e(title)}" src="data:image/png;base64,'
                    f'{data}">' for title, data in d.plots.items())
    counts = report['counts']
    return f"""<!DOCTYPE html>
<html><head><meta charset="utf-8"><title>{PROG}: {e(d.survey.path)}</title>
<style>body{{font-family:sans-serif;max-width:1200px;margin:1em auto;padding:0 1em}}
table{{border-collapse:collapse;width:100%;font-size:90%}}td,th{{border:1px solid #bbb;
padding:3px 6px;vertical-align:top;text-align:left}}pre{{background:#f4f4f4;padding:8px;
overflow-x:auto}}img{{max-width:100%}}</style></head><body>
<h1>{PROG}: {e(Path(d.survey.path).name)}</h1>
<p>{e(d.survey.path)}, {d.survey.duration_s:.1f} s; base frame <code>{e(d.base_frame)}</code>.
<b>Verdict: {e(report['verdict'])}</b> (exit status {report['exit_status']}):
{counts[PROBLEM]} problems, {counts[WARNING]} warnings, {counts[OK]} ok, {counts[SKIPPED]} not
judged.</p>
<h2>What to change</h2><ul>{findings}</ul>
<h2>Every check</h2><table><tr><th>input</th><th>check</th><th>verdict</th><th>value</th>
<th>limit</th><th>what it means, what to change</th></tr>{rows}</table>
<h2>Plots</h2>{plots}
<h2>Topics</h2><table><tr><th>topic</th><th>type</th><th>messages</th></tr>{topics}</table>
<h2>The preset (params.yaml)</h2><pre>{e(d.preset_text)}</pre>
<h2>The preset over the bag: fused output against each input</h2>
<p>The nodes {e(', '.join(d.nodes))} run offline over the bag with the preset
(sensing_pipeline's code); the fused output against each input, anchored at the fused output's
second stamp (the first is the filter's initial state). Without ground truth this is
self-consistency: where inputs disagree, the fused
output sits between them, nearer to the one with less noise.</p>
<table><tr><th>input</th><th>RMS position (m)</th><th>final position (m)</th>
<th>RMS heading (deg)</th><th>final heading (deg)</th></tr>{compared}</table>
<p>Fused final pose: {e(str(d.fused.get('final_pose')))}</p>
</body></html>
"""
