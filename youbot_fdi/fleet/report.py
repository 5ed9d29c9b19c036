"""The fleet's outputs: ``recordings.csv`` (one row per recording) and ``report.html`` (faults
per robot over time, friction per wheel per robot over time with its trend, flagged wheels)."""
import csv
import datetime
import html
import math
from pathlib import Path

from youbot_fdi.app.report import pyplot
from youbot_fdi.fleet.trend import INTERVAL_SDS, SECONDS_PER_DAY

CSV_NAME = 'recordings.csv'
HTML_NAME = 'report.html'


def _when(stamp):
    if not math.isfinite(stamp):
        return ''
    return datetime.datetime.fromtimestamp(stamp, datetime.UTC).isoformat(timespec='seconds')


def write_csv(rows, path):
    """One line per recording: robot, start (UTC), duration, samples, faults by type and wheel,
    identified friction per wheel and mass, each with its standard deviation, status and error."""
    wheels = max((r.get('wheels') or [] for r in rows), key=len, default=[])
    columns = (['recording', 'robot', 'start', 'duration_s', 'samples', 'faults', 'faults_total']
               + [f'friction_{w}' for w in wheels] + [f'friction_sd_{w}' for w in wheels]
               + ['mass', 'mass_sd', 'status', 'error'])
    with open(path, 'w', newline='', encoding='utf-8') as handle:
        writer = csv.writer(handle)
        writer.writerow(columns)
        for r in sorted(rows, key=lambda r: (r['robot'], r['start'] if math.isfinite(r['start']) else 0.0)):
            friction = list(r['friction']) + [math.nan] * (len(wheels) - len(r['friction']))
            spread = list(r.get('friction_sd', []))
            spread += [math.nan] * (len(wheels) - len(spread))
            writer.writerow([r['recording'], r['robot'], _when(r['start']), _number(r['duration_s']),
                             r['samples'], ';'.join(f'{k}:{v}' for k, v in sorted(r['faults'].items())),
                             sum(r['faults'].values())] + [_number(f) for f in friction]
                            + [_number(f) for f in spread]
                            + [_number(r.get('mass', math.nan)), _number(r.get('mass_sd', math.nan)),
                               r['status'], r['error']])
    return path


def _number(value):
    return '' if not math.isfinite(value) else f'{value:.6g}'


def write_html(rows, trends, directory, settings):
    """``report.html`` with its figures (PNG beside it when matplotlib is installed)."""
    directory = Path(directory)
    figures = _figures(rows, trends, directory)
    flagged = [t for t in trends if t.flagged]
    parts = ['<!doctype html><meta charset="utf-8"><title>youbot-fdi fleet report</title>',
             '<h1>Fleet report</h1>',
             f'<p>{len(rows)} recordings of {len({r["robot"] for r in rows})} robots; '
             f'{sum(r["status"] == "error" for r in rows)} unreadable, '
             f'{sum(r["status"] == "damaged" for r in rows)} damaged (read in part). '
             f'Table: <a href="{CSV_NAME}">{CSV_NAME}</a>.</p>',
             '<h2>Wheels whose friction is rising</h2>',
             f'<p>Flagged: relative rise above {settings.trend_rate:.1%} per day, significant at '
             f'p &lt; {settings.trend_significance:g} (at least {settings.trend_min_recordings} '
             'recordings).</p>',
             _table(['robot', 'wheel', 'recordings', 'mean friction [N·m·s/rad]', 'rise per day',
                     'p-value', 'flagged'],
                    [[t.robot, t.wheel, t.recordings, f'{t.mean:.4g}', f'{t.rate:+.2%}',
                      f'{t.p_value:.3g}', 'YES' if t.flagged else ''] for t in trends]),
             f'<p><b>{len(flagged)} wheel(s) flagged</b>'
             + (': ' + ', '.join(html.escape(f'{t.robot}/{t.wheel}') for t in flagged) if flagged else '')
             + '</p>']
    for title, name in figures:
        parts.append(f'<h2>{html.escape(title)}</h2><img src="{name}" style="max-width:100%">')
    if not figures:
        parts.append('<p>(figures need matplotlib: pip install "youbot_fdi[plot]")</p>')
    errors = [r for r in rows if r['status'] != 'ok']
    if errors:
        parts += ['<h2>Recordings not read whole</h2>',
                  _table(['recording', 'status', 'error'],
                         [[r['recording'], r['status'], r['error']] for r in errors])]
    path = directory / HTML_NAME
    path.write_text('\n'.join(parts), encoding='utf-8')
    return path


def _table(header, rows):
    head = ''.join(f'<th>{html.escape(str(h))}</th>' for h in header)
    body = ''.join('<tr>' + ''.join(f'<td>{html.escape(str(c))}</td>' for c in row) + '</tr>'
                   for row in rows)
    return f'<table border="1" cellpadding="3"><tr>{head}</tr>{body}</table>'


def _figures(rows, trends, directory):
    """[(title, file name)] of the figures written."""
    plt = pyplot()
    usable = [r for r in rows if math.isfinite(r['start'])]
    if plt is None or not usable:
        return []
    origin = min(r['start'] for r in usable)
    robots = sorted({r['robot'] for r in usable})
    written = []
    fig, ax = plt.subplots(figsize=(9, 4), constrained_layout=True)
    for robot in robots:
        mine = sorted((r for r in usable if r['robot'] == robot), key=lambda r: r['start'])
        ax.plot([(r['start'] - origin) / SECONDS_PER_DAY for r in mine],
                [sum(r['faults'].values()) for r in mine], 'o-', label=robot)
    ax.set(xlabel='days since the first recording', ylabel='faults (ERROR events)',
           title='Faults per recording, per robot')
    ax.legend(fontsize=8)
    fig.savefig(directory / 'faults.png', dpi=100)
    plt.close(fig)
    written.append(('Faults per robot over time', 'faults.png'))
    fig, axes = plt.subplots(len(robots), 1, figsize=(9, 3 * len(robots)), squeeze=False,
                             constrained_layout=True)
    by_key = {(t.robot, t.wheel): t for t in trends}
    for ax, robot in zip(axes[:, 0], robots):
        mine = sorted((r for r in usable if r['robot'] == robot and r.get('wheels')),
                      key=lambda r: r['start'])
        for w, wheel in enumerate(mine[0]['wheels'] if mine else []):
            days = [(r['start'] - origin) / SECONDS_PER_DAY for r in mine]
            friction = [r['friction'][w] if len(r['friction']) > w else math.nan for r in mine]
            spread = [INTERVAL_SDS * r['friction_sd'][w] if len(r.get('friction_sd', [])) > w
                      else math.nan for r in mine]
            trend = by_key.get((robot, wheel))
            label = wheel + (f' ({trend.rate:+.1%}/day{", FLAGGED" if trend.flagged else ""})'
                             if trend else '')
            ax.errorbar(days, friction, yerr=spread, fmt='o-', capsize=3, label=label,
                        lw=2.5 if trend and trend.flagged else 1)
        ax.set(xlabel='days since the first recording',
               ylabel=f'viscous friction [N·m·s/rad], ±{INTERVAL_SDS:g} sd',
               title=f'{robot}: friction per wheel')
        ax.legend(fontsize=7)
    fig.savefig(directory / 'friction.png', dpi=100)
    plt.close(fig)
    written.append(('Friction per wheel per robot over time', 'friction.png'))
    return written
