"""Replay reports: PNG figures in the spirit of the report's Figs. 5.10-5.19 and an HTML index.

matplotlib is an optional extra (``plot``); without it the report has the tables only.
"""
import html

import numpy as np

from youbot_fdi.app.incidents import replays_alarm
from youbot_fdi.faults import Level
from youbot_fdi.fdi.residuals import FAMILIES
from youbot_fdi.naming import wheel_suffix


def pyplot():
    """matplotlib.pyplot on the Agg backend, or None when matplotlib is not installed."""
    try:
        import matplotlib
        matplotlib.use('Agg')
        import matplotlib.pyplot as plt
    except ImportError:
        return None
    return plt


def plot_friction_sweep(sweep, path):
    """Report Fig. 5.10: RMSE of the current-driven prediction against the viscous friction."""
    plt = pyplot()
    if plt is None:
        return None
    values, rmse = sweep
    fig, ax = plt.subplots(figsize=(6, 4), constrained_layout=True)
    ax.plot(values, rmse, 'o-')
    best = int(np.argmin(rmse))
    ax.plot(values[best], rmse[best], 'r*', markersize=14, label=f'best D = {values[best]:.3f}')
    ax.set(xlabel='viscous friction D [N·m·s/rad]', ylabel='RMSE of predicted wheel speed [rad/s]',
           title='Friction sweep (report Fig. 5.10)')
    ax.legend()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def _series(residuals):
    """Plot data from a :class:`~youbot_fdi.fdi.residuals.ResidualBatch` (or None)."""
    if residuals is None:
        return {'time': np.empty(0), 't0': 0.0}
    time = residuals.stamp
    data = {'time': time - time[0], 't0': time[0], 'velocity': residuals.velocity,
            'torque': residuals.torque, 'command_speed': residuals.command_speed,
            'velocity_mode': residuals.velocity_mode}
    for family in FAMILIES:
        data[family] = residuals.values[family]
        data[family + '_bound'] = residuals.bounds[family]
    return data


def _figures(directory, model, data, events):
    plt = pyplot()
    if plt is None or not len(data['time']):
        return []
    written = []
    t = data['time']
    names = model.wheel_names
    fig, axes = plt.subplots(len(names), 1, figsize=(11, 2.2 * len(names)), sharex=True,
                             constrained_layout=True)
    for w, ax in enumerate(np.atleast_1d(axes)):
        ax.plot(t, data['velocity'][:, w], lw=1, label='measured')
        ax.plot(t, data['velocity'][:, w] - data['observer'][:, w], lw=1, label='predicted from currents')
        if data['velocity_mode'].any():
            ax.plot(t, np.where(data['velocity_mode'], data['command_speed'][:, w], np.nan), lw=1,
                    label='predicted from commands')
        ax.set_ylabel(f'{wheel_suffix(names[w])} [rad/s]')
    np.atleast_1d(axes)[0].legend(fontsize=8)
    np.atleast_1d(axes)[-1].set_xlabel('time [s]')
    fig.suptitle('Measured vs predicted wheel speed (kinematic convention; report Figs. 5.11-5.18)')
    path = directory / 'speeds.png'
    fig.savefig(path, dpi=90)
    plt.close(fig)
    written.append(path)

    for family in FAMILIES:
        fig, axes = plt.subplots(len(names), 1, figsize=(11, 2.0 * len(names)), sharex=True,
                                 constrained_layout=True)
        for w, ax in enumerate(np.atleast_1d(axes)):
            ax.plot(t, data[family][:, w], lw=1, label=f'{family}_{wheel_suffix(names[w])}')
            ax.fill_between(t, -data[family + '_bound'][:, w], data[family + '_bound'][:, w],
                            color='0.85', label='bound')
            for event in events:
                if event.wheel == names[w] and event.level == Level.ERROR:
                    ax.axvline(event.stamp - data['t0'], color='r', lw=1)
            ax.legend(fontsize=7, loc='upper right')
        np.atleast_1d(axes)[-1].set_xlabel('time [s]')
        fig.suptitle(f'{family} residuals with their adaptive bounds (red: alarms)')
        path = directory / f'residuals_{family}.png'
        fig.savefig(path, dpi=90)
        plt.close(fig)
        written.append(path)

    fig, ax = plt.subplots(figsize=(11, 2.5), constrained_layout=True)
    rows = list(names) + ['base']
    for event in events:
        row = rows.index(event.wheel) if event.wheel in rows else len(rows) - 1
        color = 'r' if event.level == Level.ERROR else 'g'
        ax.plot(event.stamp - data['t0'], row, 'o', color=color)
        ax.annotate(event.fault if event.level == Level.ERROR else 'OK', (event.stamp - data['t0'], row),
                    textcoords='offset points', xytext=(4, 4), fontsize=8)
    ax.set_yticks(range(len(rows)), rows)
    ax.set_xlim(t[0], t[-1])
    ax.set(xlabel='time [s]', title='Fault events')
    path = directory / 'timeline.png'
    fig.savefig(path, dpi=90)
    plt.close(fig)
    written.append(path)
    return written


#: Bins of the operating-point figure (the bound's median per bin is drawn).
OPERATING_POINT_BINS = 40


def _binned_band(ax, x, bound):
    """The bound's median per quantile bin of ``x``, drawn as a band around 0."""
    finite = np.isfinite(x) & np.isfinite(bound)
    if np.count_nonzero(finite) <= OPERATING_POINT_BINS:
        return
    x, bound = x[finite], bound[finite]
    edges = np.quantile(x, np.linspace(0.0, 1.0, OPERATING_POINT_BINS + 1))
    which = np.clip(np.searchsorted(edges, x) - 1, 0, OPERATING_POINT_BINS - 1)
    filled = [b for b in range(OPERATING_POINT_BINS) if np.any(which == b)]
    typical = np.array([np.median(bound[which == b]) for b in filled])
    ax.fill_between([np.median(x[which == b]) for b in filled], -typical, typical,
                    color='tab:blue', alpha=0.15, label='bound (median)')


def _operating_point_figure(directory, model, residuals, correction):
    """The torque residual and its bound against the operating point of each wheel (its mean
    speed and its acceleration over the interval), with the learned correction's parts and the
    ranges its calibration covered (issue 12); ``correction`` None: the physics alone. Returns
    the path, or None without data."""
    plt = pyplot()
    if plt is None or residuals is None or len(residuals) < 2:
        return None
    names, n = model.wheel_names, len(model.wheel_names)
    interval = np.diff(residuals.stamp)[:, None]
    points = (0.5 * (residuals.velocity[1:] + residuals.velocity[:-1]),
              np.diff(residuals.velocity, axis=0) / np.where(interval > 0.0, interval, np.nan))
    value, bound = residuals.values['torque'][1:], residuals.bounds['torque'][1:]
    outside = residuals.outside_calibration[1:].astype(np.int64)
    fig, axes = plt.subplots(2, n, figsize=(3.4 * n, 6.4), sharey=True, constrained_layout=True,
                             squeeze=False)
    rows = (('mean wheel speed [rad/s]', 'friction', 'speed_range', (0, 1, 2)),
            ('wheel acceleration [rad/s²]', 'inertial', 'acceleration_range', (3,)))
    for row, (label, part, span, columns) in enumerate(rows):
        x = points[row]
        for w in range(n):
            ax = axes[row, w]
            flagged = (outside >> w & 1).astype(bool)
            ax.plot(x[~flagged, w], value[~flagged, w], '.', ms=1.5, color='0.45', label='residual')
            if flagged.any():
                ax.plot(x[flagged, w], value[flagged, w], '.', ms=2, color='tab:orange',
                        label='outside calibration: physics only')
            _binned_band(ax, x[:, w], bound[:, w])
            if correction is not None and np.any(correction.weights[w, list(columns)] != 0.0):
                grid = np.zeros((200, n))
                grid[:, w] = np.linspace(np.nanmin(x[:, w]), np.nanmax(x[:, w]), len(grid))
                ax.plot(grid[:, w], getattr(correction, part)(grid)[:, w], color='tab:green',
                        lw=1.5, label=f'learned {part} part')
                covered = getattr(correction, span)
                if covered is not None:
                    low, high = covered[w]
                    widen = correction.range_margin * (high - low)
                    ax.axvspan(low - widen, high + widen, color='tab:green', alpha=0.07,
                               label='calibrated range')
            ax.set(xlabel=f'{wheel_suffix(names[w])}: {label}')
        axes[row, 0].set_ylabel('torque residual [N·m]')
        axes[row, 0].legend(fontsize=7, loc='upper left', markerscale=4)
    fig.suptitle('Torque residual and bound against the operating point'
                 + (' with the learned correction' if correction is not None else ' (physics only)'))
    path = directory / 'operating_point.png'
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def write_report(directory, model, pipeline, events, source):
    """Write figures and ``index.html`` for a replay; returns the index path."""
    directory.mkdir(parents=True, exist_ok=True)
    residuals = pipeline.residuals()
    data = _series(residuals)
    figures = _figures(directory, model, data, events)
    figure = _operating_point_figure(directory, model, residuals, pipeline.generator.correction)
    figures += [figure] if figure is not None else []
    rows = ''.join(f'<tr><td>{e.stamp:.3f}</td><td>{e.level}</td><td>{html.escape(str(e.wheel))}'
                   f'</td><td>{e.fault}</td><td>{html.escape(", ".join(e.residuals))}</td>'
                   f'<td>{html.escape(e.detail)}</td></tr>' for e in events)
    images = ''.join(f'<h2>{p.stem}</h2><img src="{p.name}" style="max-width:100%">' for p in figures)
    page = (f'<!doctype html><html><head><meta charset="utf-8"><title>youbot-fdi replay</title>'
            f'<style>body{{font-family:sans-serif;margin:2em}}td,th{{padding:2px 8px;'
            f'border-bottom:1px solid #ddd}}</style></head><body>'
            f'<h1>youbot-fdi replay of {html.escape(str(source))}</h1>'
            f'<p>profile {html.escape(model.profile.name)}, {len(data["time"])} samples, '
            f'{len(events)} events.</p><table><tr><th>stamp [s]</th><th>level</th><th>wheel</th>'
            f'<th>fault</th><th>residuals</th><th>detail</th></tr>{rows}</table>{images}'
            f'{"" if figures else "<p>(figures need matplotlib)</p>"}</body></html>')
    index = directory / 'index.html'
    index.write_text(page)
    return index


INCIDENT_PAGE = 'incident.html'
#: Units of the residual families on the incident page (command: rad/s in velocity mode, N·m in
#: current mode).
FAMILY_UNITS = {'torque': 'N·m', 'observer': 'rad/s', 'command': 'rad/s | N·m', 'encoder': 'rad'}
EVIDENCE_SHOWN = 3.0  # the evidence axis ends at this many thresholds (an alarm is from 1)


def _incident_figure(model, data, evidence, sidecar, events):
    """One PNG (bytes) of an incident: every wheel's speed and current torque, then the alarmed
    wheel's residual of each family against its bound and its evidence; alarms marked red."""
    import io
    plt = pyplot()
    if plt is None or not len(data['time']):
        return None
    names = model.wheel_names
    alarmed = sidecar['event'].get('wheel')
    w = names.index(alarmed) if alarmed in names else None
    alarm_stamp = float(sidecar['event'].get('stamp', data['t0']))
    t = data['time'] + data['t0'] - alarm_stamp  # [s] from the alarm
    rows = 2 + (len(FAMILIES) + 1 if w is not None else 0)
    fig, axes = plt.subplots(rows, 1, figsize=(11, 1.9 * rows), sharex=True, constrained_layout=True)
    for k, name in enumerate(names):
        axes[0].plot(t, data['velocity'][:, k], lw=1, label=wheel_suffix(name))
        axes[1].plot(t, data['torque'][:, k], lw=1, label=wheel_suffix(name))
    axes[0].set_ylabel('speed [rad/s]')
    axes[1].set_ylabel('torque [N·m]')
    axes[0].legend(fontsize=7, loc='upper right', ncol=len(names))
    if w is not None:
        suffix = wheel_suffix(alarmed)
        for k, family in enumerate(FAMILIES):
            ax = axes[2 + k]
            ax.fill_between(t, -data[family + '_bound'][:, w], data[family + '_bound'][:, w],
                            color='0.85', label='bound')
            ax.plot(t, data[family][:, w], lw=1, label=f'{family}_{suffix}')
            ax.set_ylabel(f'{family} [{FAMILY_UNITS.get(family, "")}]')
            ax.legend(fontsize=7, loc='upper right')
        ax = axes[-1]
        if evidence is not None and len(evidence) == len(t):
            for k, family in enumerate(FAMILIES):
                ax.plot(t, evidence[:, k, w], lw=1, label=family)
        ax.axhline(1.0, color='r', lw=0.8, ls='--', label='threshold')
        ax.set_ylim(0.0, EVIDENCE_SHOWN)
        ax.set_ylabel(f'evidence {suffix}\n[thresholds, to {EVIDENCE_SHOWN:g}]')
        ax.legend(fontsize=7, loc='upper left', ncol=len(FAMILIES) + 1)
    for ax in axes:
        for event in events:
            if event.level == Level.ERROR:
                ax.axvline(event.stamp - alarm_stamp, color='r', lw=1)
    axes[-1].set_xlabel(f'time [s] from the alarm at stamp {alarm_stamp:.3f} s (red: alarms of '
                        'the replay)')
    buffer = io.BytesIO()
    fig.savefig(buffer, format='png', dpi=80)
    plt.close(fig)
    return buffer.getvalue()


def _held(entry, family):
    """' (held)' for an alarm the decision still holds with its evidence below the threshold
    (it is released after ``release_time`` of excited samples below it)."""
    alarmed = family in entry.get('alarm', ())
    return ' (held)' if alarmed and entry['evidence'][family] < 1.0 else ''


def _freeze_frame_table(freeze):
    """The freeze-frame as an HTML table: per wheel and family, residual / bound and evidence."""
    header = ''.join(f'<th>{f}: r / u</th><th>evidence</th>' for f in FAMILIES)
    rows = ''
    for suffix, entry in (freeze.get('wheels') or {}).items():
        cells = ''.join(
            f'<td>{entry.get("residual", {}).get(f, float("nan")):.4g} / '
            f'{entry.get("bound", {}).get(f, float("nan")):.4g}</td>'
            f'<td{" style=color:red" if f in entry.get("alarm", ()) else ""}>'
            f'{entry["evidence"][f]:.2f}{_held(entry, f)}</td>' for f in FAMILIES)
        rows += f'<tr><td>{html.escape(suffix)}</td>{cells}</tr>'
    return f'<table><tr><th>wheel</th>{header}</tr>{rows}</table>'


def write_incident_page(folder, model, pipeline, events, sidecar):
    """Write ``folder/incident.html``: one self-contained page of an incident replayed with
    ``pipeline`` (signals, residuals against bounds, evidence, the alarm marked, the freeze-frame
    the robot kept); returns its path."""
    import base64
    data = _series(pipeline.residuals())
    png = _incident_figure(model, data, pipeline.evidence(), sidecar, events)
    event = sidecar['event']
    freeze = sidecar.get('freeze_frame') or {}
    parameters = sidecar.get('parameters') or {}
    same = replays_alarm(sidecar, events)
    rows = ''.join(f'<tr><td>{e.stamp:.3f}</td><td>{e.level}</td><td>{html.escape(str(e.wheel))}'
                   f'</td><td>{e.fault}</td><td>{html.escape(e.detail)}</td></tr>' for e in events)
    image = (f'<img src="data:image/png;base64,{base64.b64encode(png).decode()}" '
             f'style="max-width:100%">' if png else '<p>(figures need matplotlib)</p>')
    page = (f'<!doctype html><html><head><meta charset="utf-8"><title>incident '
            f'{html.escape(folder.name)}</title><style>body{{font-family:sans-serif;margin:2em}}'
            f'td,th{{padding:2px 8px;border-bottom:1px solid #ddd}}</style></head><body>'
            f'<h1>{html.escape(str(event.get("fault")))} on {html.escape(str(event.get("wheel") or "base"))}</h1>'
            f'<p>{html.escape(folder.name)}: alarm at stamp {float(event.get("stamp", 0.0)):.3f} s '
            f'({html.escape(str(event.get("detail", "")))}), recorded from '
            f'{float((sidecar.get("window") or {}).get("recorded_before_s", float("nan"))):.1f} s '
            f'before it; load factor '
            f'{freeze.get("load_factor", float("nan"))}, load condition '
            f'{html.escape(str(freeze.get("load_condition", "")))}.</p>'
            f'<p>Ran with youbot_fdi {html.escape(str((sidecar.get("software") or {}).get("youbot_fdi")))}, '
            f'profile {html.escape(str(parameters.get("profile")))}, parameter file '
            f'{html.escape(str(parameters.get("params_file") or "(none: profile defaults)"))} '
            f'{html.escape(str(parameters.get("params_sha256", ""))[:12])}; recording '
            f'{"complete" if sidecar.get("complete") else "cut short (read to its damage)"}.</p>'
            f'<h2>Freeze-frame at the alarm (as the robot saw it)</h2>'
            f'<p>Residual r against its bound u, and the evidence in thresholds (an alarm from 1; '
            f'red: an alarm the decision holds).</p>{_freeze_frame_table(freeze)}'
            f'<h2>Replayed here: {"the same alarm" if same else "NOT the same alarm"}</h2>'
            f'<table><tr><th>stamp [s]</th><th>level</th><th>wheel</th><th>fault</th><th>detail</th>'
            f'</tr>{rows}</table>{image}</body></html>')
    path = folder / INCIDENT_PAGE
    path.write_text(page)
    return path
