"""report.json and a self-contained report.html (plots inline as PNG data)."""

from __future__ import annotations

import base64
import html
import io
from pathlib import Path
from typing import Any

import numpy as np

from sensing_nodes.core.diagnosis.check import (
    OK,
    PROBLEM,
    SKIPPED,
    WARNING,
    Check,
    _json,
    number,
    plural,
    worst,
)
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


STYLES = ('-', '--', '-.', ':')


def _moves(track: tuple[np.ndarray, np.ndarray]) -> bool:
    """A pose track that translates (an IMU-only fused output stays at the origin)."""
    return bool(np.ptp(track[1][:, :2], axis=0).max() > 0.05) if len(track[1]) else False


def _trajectories(d: Diagnosis, plt) -> None:
    """Each input and the fused output; the fused drawn wide and pale underneath, the inputs
    in dashes of their own on top, so that lines lying on each other stay visible."""
    tracks = {n: tr for n, tr in d.pose_tracks.items() if _moves(tr)}
    if not tracks:
        return
    anchor = tracks.get('fused') or tracks.get('scan matching') or next(iter(tracks.values()))
    fig, ax = plt.subplots(figsize=(7, 6))
    for i, (name, track) in enumerate(tracks.items()):
        p = _anchored(track, anchor)
        if p is None:
            continue
        if name == 'fused':
            ax.plot(p[:, 0], p[:, 1], lw=6.0, alpha=0.3, color='black', label=name, zorder=1)
        else:
            ax.plot(p[:, 0], p[:, 1], lw=1.3, ls=STYLES[i % len(STYLES)], label=name, zorder=2)
    ax.set_aspect('equal', adjustable='datalim')
    ax.legend(loc='best', fontsize=8)
    _finish(d, 'trajectories', fig, ax, 'x (m)', 'y (m)',
            'Each input (dashed) and the fused output (wide, grey), anchored at its start')


def _headings(d: Diagnosis, plt) -> None:
    """Heading over time of every yaw source and the fused output (a bag without
    trajectories: an IMU alone)."""
    series = {('gyro heading of ' + n if d.imu is not None and n == d.imu.topic else n): tr
              for n, tr in d.tracks.items()}
    if d.orientation_yaw is not None:
        series['orientation of ' + d.imu.topic] = d.orientation_yaw
    if 'fused' in d.pose_tracks and len(d.pose_tracks['fused'][0]) > 1:
        t, p = d.pose_tracks['fused']
        series['fused'] = (t, np.unwrap(p[:, 2]))
    if not series:
        return
    start = min(int(t[0]) for t, _ in series.values())
    fig, ax = plt.subplots(figsize=(9, 3.5))
    for i, (name, (t, yaw)) in enumerate(series.items()):
        wide = name == 'fused'
        ax.plot((t - start) * 1e-9, np.degrees(yaw - yaw[0]), label=name,
                lw=5.0 if wide else 1.2, alpha=0.3 if wide else 1.0,
                color='black' if wide else None, ls='-' if wide else STYLES[i % len(STYLES)])
    ax.legend(loc='best', fontsize=8)
    _finish(d, 'headings', fig, ax, 'time (s)', 'heading from its start (deg)',
            'Heading of each source over time, each from its own start')


def _errors_over_time(d: Diagnosis, plt) -> None:
    """The fused output against each input over time: position and heading difference."""
    if 'fused' not in d.pose_tracks or len(d.pose_tracks['fused'][0]) < 3:
        return
    ft, fp = d.pose_tracks['fused']
    ft, fp = ft[1:], fp[1:]
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(9, 5.5), sharex=True)
    start = int(ft[0])
    for i, (name, track) in enumerate(d.pose_tracks.items()):
        if name == 'fused':
            continue
        p = _anchored(track, (ft, fp))
        if p is None:
            continue
        at = pose_at(track[0], p, ft)
        ok = np.isfinite(at).all(axis=1)
        ls = STYLES[i % len(STYLES)]
        if _moves(track):
            top.plot((ft[ok] - start) * 1e-9, np.hypot(*(fp[ok, :2] - at[ok, :2]).T), ls=ls,
                     lw=1.2, label=name)
        bottom.plot((ft[ok] - start) * 1e-9,
                    np.degrees(np.angle(np.exp(1j * (fp[ok, 2] - at[ok, 2])))), ls=ls, lw=1.2,
                    label=name)
    for name, (t, yaw) in list(d.tracks.items()) + (
            [('orientation of ' + d.imu.topic, d.orientation_yaw)]
            if d.orientation_yaw is not None else []):
        if name in d.pose_tracks:
            continue
        y = np.interp((ft - t[0]) * 1e-9, (t - t[0]) * 1e-9, yaw)
        inside = (ft >= t[0]) & (ft <= t[-1])
        if inside.sum() < 2:
            continue
        first = np.flatnonzero(inside)[0]
        diff = np.unwrap(fp[inside, 2]) - np.unwrap(fp[:, 2])[first] - (y[inside] - y[first])
        label = ('gyro heading of ' + name) if d.imu is not None and name == d.imu.topic else name
        bottom.plot((ft[inside] - start) * 1e-9, np.degrees(diff), lw=1.2, ls=':', label=label)
    top.set_ylabel('position (m)')
    top.grid(alpha=0.3)
    if top.lines:
        top.legend(loc='best', fontsize=8)
    else:
        top.set_visible(False)
    bottom.legend(loc='best', fontsize=8)
    top.set_title('The fused output minus each input over time (each anchored at the start)')
    _finish(d, 'error over time', fig, bottom, 'time (s)', 'heading (deg)',
            '')


def make_plots(d: Diagnosis) -> None:
    """Per bag kind: trajectories of every input and the fused output (a robot that drives),
    heading over time (every bag; the one for an IMU alone), the fused output's error against
    each input over time, yaw rates, the Allan deviation."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    _trajectories(d, plt)
    _headings(d, plt)
    _errors_over_time(d, plt)
    if len(d.tracks) > 1:
        fig, ax = plt.subplots(figsize=(9, 3.5))
        for i, (name, (t, yaw)) in enumerate(d.tracks.items()):
            edges = np.arange(t[0], t[-1], 100_000_000)
            if edges.size < 3:
                continue
            y = np.interp(edges - t[0], t - t[0], yaw)
            ax.plot((edges[1:] - d.survey.times[next(iter(d.survey.times))].record_ns[0]) * 1e-9,
                    np.degrees(np.diff(y) / 0.1), lw=0.8, ls=STYLES[i % len(STYLES)], label=name)
        ax.legend(loc='best', fontsize=8)
        _finish(d, 'yaw rates', fig, ax, 'bag time (s)', 'yaw rate (deg/s)',
                'Yaw rate of each source (0.1 s means): time offsets show as shifts, a gain '
                'as a scale')
    noise = next((c for c in d.checks if c.name == 'gyro_noise' and c.verdict != SKIPPED), None)
    if noise is not None:
        fig, ax = plt.subplots(figsize=(6, 4))
        ax.loglog(noise.details['allan_tau_s'], noise.details['allan_dev_rad_s'], 'o-', ms=3)
        _finish(d, 'gyro Allan deviation', fig, ax, 'cluster time tau (s)',
                'Allan deviation (rad/s)',
                f'Gyro z (base_link) Allan deviation while still: {noise.subject}')


def verdict(d: Diagnosis) -> dict[str, Any]:
    """The verdict a user acts on: usable with params.yaml (the fused run went through and
    follows every input it does not name a reason to distrust), the preset's figures against
    each input, and the problems it fixes apart from those it cannot."""
    fused = next((c for c in d.checks if c.name == 'fused'), None)
    problems = [c for c in d.checks if c.verdict == PROBLEM and c.name != 'fused']
    if fused is None or fused.verdict == SKIPPED:
        usable, why = None, 'not run (--no-fusion)' if fused is None else fused.advice
    elif fused.verdict == PROBLEM:
        usable, why = False, fused.advice
    elif fused.verdict == WARNING:
        usable, why = False, ('the fused output departs from '
                              + ', '.join(d.fused.get('unexplained', []))
                              + ' and no check explains it (the fused check says more)')
    else:
        usable, why = True, 'the fused output follows every input it does not name a reason ' \
            'to distrust'
    return {'usable_with_params_yaml': usable, 'why': why,
            'fused_against': {n: {k: v for k, v in f.items()}
                              for n, f in d.fused.get('compared', {}).items()},
            'distrusted': d.fused.get('distrusted', {}),
            'fixed_by_preset': [_line(c) + ('' if 'params.yaml' in c.advice else f' -> {c.fix}')
                                for c in problems if c.fix],
            'not_fixable': [_line(c) for c in problems if not c.fix]}


def _line(c: Check) -> str:
    return f'{c.subject}: {c.name}: {c.advice}'


def report_json(d: Diagnosis, status: int) -> dict[str, Any]:
    """Every check, verdict and number, the inputs, the preset and the fused comparison."""
    counts = {v: sum(c.verdict == v for c in d.checks) for v in (OK, WARNING, PROBLEM, SKIPPED)}
    return {'tool': PROG, 'bag': d.survey.path, 'duration_s': round(d.survey.duration_s, 3),
            'exit_status': status, 'verdict': worst(d.checks), 'counts': counts,
            'usable': _json(verdict(d)),
            'topics': {t: {'type': ty, 'count': n} for t, (ty, n) in d.survey.topics.items()},
            'base_frame': d.base_frame, 'checks': [c.as_dict() for c in d.checks],
            'preset': {'nodes': list(d.nodes), 'remaps': d.remaps, 'parameters': d.preset,
                       'commands': commands(d, Path('params.yaml'))},
            'time_offsets_s': _json(d.offsets), 'offset_reference': d.offset_reference,
            'noise': _json(d.noise), 'fused': _json(d.fused), 'timings_s': _json(d.timings)}


COLOURS = {OK: '#d9f2d9', WARNING: '#fff0c2', PROBLEM: '#f8d0d0', SKIPPED: '#eeeeee'}


def _number(c: Check) -> str:
    shown = number(c.value) if isinstance(c.value, (int, float)) else ''
    return f'{shown} {html.escape(c.unit)}' if shown else ''


def _cell(value: float | None) -> str:
    return number(value) or '-'


def _pose_text(pose: dict | None) -> str:
    if not pose:
        return 'none'
    return f'x {pose["x_m"]:.3f} m, y {pose["y_m"]:.3f} m, yaw {pose["yaw_deg"]:.1f} deg'


def report_html(d: Diagnosis, report: dict[str, Any]) -> str:
    """One self-contained page: the verdicts, the checks, the plots (inline PNG), the preset
    and the fused output against each input."""
    e = html.escape
    rows = ''.join(
        f'<tr style="background:{COLOURS[c.verdict]}"><td>{e(c.subject)}</td><td>{e(c.name)}'
        f'</td><td><b>{e(c.verdict if c.verdict != SKIPPED else "not judged")}</b></td>'
        f'<td>{_number(c)}</td><td>{e(c.limit)}</td>'
        f'<td>{e(c.advice)}{e(" -> " + c.fix) if c.fix and "params.yaml" not in c.advice else ""}'
        '</td></tr>' for c in d.checks)
    topics = ''.join(f'<tr><td>{e(t)}</td><td>{e(v["type"])}</td><td>{v["count"]}</td></tr>'
                     for t, v in sorted(report['topics'].items()))
    compared = ''.join(
        f'<tr><td>{e(n)}</td><td>{_cell(v.get("rms_position_error_m"))}</td>'
        f'<td>{_cell(v.get("final_position_error_m"))}</td>'
        f'<td>{_cell(v["rms_heading_error_deg"])}</td><td>{_cell(v["final_heading_error_deg"])}'
        f'</td><td>{e(d.fused.get("distrusted", {}).get(n, ""))}</td></tr>'
        for n, v in d.fused.get('compared', {}).items())
    usable = report['usable']
    answer = {True: 'yes', False: 'no', None: 'not run'}[usable['usable_with_params_yaml']]
    fixed = ''.join(f'<li>{e(x)}</li>' for x in usable['fixed_by_preset']) or '<li>none</li>'
    unfixable = ''.join(f'<li>{e(x)}</li>' for x in usable['not_fixable']) or '<li>none</li>'
    findings = ''.join(
        f'<li style="background:{COLOURS[c.verdict]}"><b>{e(c.verdict)}</b> {e(c.subject)} '
        f'({e(c.name)}, {_number(c)}): {e(c.advice)}</li>'
        for c in d.checks if c.verdict == WARNING) or '<li>none</li>'
    plots = ''.join(f'<h3>{e(title)}</h3><img alt="{e(title)}" src="data:image/png;base64,'
                    f'{data}">' for title, data in d.plots.items())
    counts = report['counts']
    return f"""<!DOCTYPE html>
<html><head><meta charset="utf-8"><title>{PROG}: {e(d.survey.path)}</title>
<style>body{{font-family:sans-serif;max-width:1200px;margin:1em auto;padding:0 1em}}
table{{border-collapse:collapse;width:100%;font-size:90%}}td,th{{border:1px solid #bbb;
padding:3px 6px;vertical-align:top;text-align:left}}pre{{background:#f4f4f4;padding:8px;
white-space:pre-wrap;overflow-wrap:anywhere}}img{{max-width:100%}}
.verdict{{font-size:130%;padding:6px;background:{'#d9f2d9' if answer == 'yes' else '#f8d0d0'}}}
</style></head><body>
<h1>{PROG}: {e(Path(d.survey.path).name)}</h1>
<p>{e(d.survey.path)}, {d.survey.duration_s:.1f} s; base frame <code>{e(d.base_frame)}</code>;
{plural(counts[PROBLEM], 'problem')}, {plural(counts[WARNING], 'warning')}, {counts[OK]} ok,
{counts[SKIPPED]} not judged (exit status {report['exit_status']}).</p>
<p class="verdict"><b>Usable with params.yaml: {answer}</b>: {e(usable['why'])}.</p>
<h2>The preset's fused output against each input</h2>
<p>The nodes {e(', '.join(d.nodes))} run offline over the bag with params.yaml
(sensing_pipeline's code), each input anchored at the fused output's second stamp (the first is
the filter's initial state). Without ground truth this is self-consistency: where inputs
disagree the fused output follows the one the preset trusts, and the last column says why it
departs from another. Final pose: {e(_pose_text(d.fused.get('final_pose')))}.</p>
<table><tr><th>input</th><th>RMS position (m)</th><th>final position (m)</th>
<th>RMS heading (deg)</th><th>final heading (deg)</th><th>not followed because</th></tr>
{compared}</table>
<h2>Problems params.yaml fixes (the configuration differs from the bag)</h2><ul>{fixed}</ul>
<h2>Problems params.yaml cannot fix (the data, or the robot's own declarations)</h2>
<ul>{unfixable}</ul>
<h2>Warnings</h2><ul>{findings}</ul>
<h2>Plots</h2>{plots}
<h2>The preset (params.yaml)</h2>
<p><button onclick="navigator.clipboard.writeText(document.getElementById('preset').innerText)">
copy</button> (or save it from the report's folder: params.yaml)</p>
<pre id="preset">{e(d.preset_text)}</pre>
<h2>Every check</h2><table><tr><th>input</th><th>check</th><th>verdict</th><th>value</th>
<th>limit</th><th>what it means, what to change</th></tr>{rows}</table>
<h2>Topics</h2><table><tr><th>topic</th><th>type</th><th>messages</th></tr>{topics}</table>
</body></html>
"""
