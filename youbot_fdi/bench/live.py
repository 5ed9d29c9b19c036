"""The live soak (``youbot-fdi bench --live``): the main job as a user runs it, long and loaded.

Every run is ``youbot-fdi demo`` in a process of its own, as on a robot PC (the separate FDI
node processes, the virtual base and the driver shim), its figures read from ``--summary``:

1. the fault-free demo drive for ``soak_minutes`` (the script repeated), alone and beside a
   busy process on one core (started and stopped here): alarms, and the shim's cycles, late
   cycles (past the modules' controller timeout) and missing module answers;
2. every demo fault on every wheel (the default drive, the fault at 5 s), alone and beside the
   busy core: whether the first alarm names the injected wheel, any alarm before the injection
   (a false alarm), and the detection delay;
3. the incident budget (issue 35): every run keeps its incidents in one folder with a budget of
   ``INCIDENT_BUDGET`` incidents, so the fault runs, one after another, overflow it; at the end
   the folder must hold no more than the budget, each kept incident readable.
"""
from dataclasses import dataclass
import json
import math
from pathlib import Path
import subprocess
import sys
import tempfile

from youbot_fdi.faults import Level

#: A soak's default length [min] (issue 33: ten minutes of the fault-free demo drive).
SOAK_MINUTES = 10.0
#: Wall time allowed per run beyond its drive [s]: the node processes start, the drive settles.
RUN_OVERHEAD = 120.0
#: One core kept busy by a process of its own (a busy robot PC: mapping, planning, a browser).
BUSY_LOOP = 'while True: pass'
CONDITIONS = (('alone', False), ('busy core', True))
#: Incidents the soak's folder may keep (the fault runs alarm about 50 times).
INCIDENT_BUDGET = 10


class BusyCore:
    """A process spinning one core while the ``with`` block runs."""

    def __enter__(self):
        self.process = subprocess.Popen([sys.executable, '-c', BUSY_LOOP])
        return self

    def __exit__(self, *exc):
        self.process.kill()
        self.process.wait()


@dataclass(frozen=True)
class LiveRun:
    """One demo run of the soak: what was driven, under which condition, and its summary."""

    condition: str
    fault: str  # 'none' for the soak
    wheel: str
    summary: dict  # the demo's --summary JSON

    @property
    def alarms(self):
        """Every ERROR event of the run, the start-up's included."""
        return ([a for a in self.summary['alarms']]
                + [e for e in self.summary['before_drive'] if e.get('level') == Level.ERROR])

    @property
    def first_alarm(self):
        alarms = sorted(self.alarms, key=lambda e: e['stamp'])
        return alarms[0] if alarms else None

    @property
    def right_wheel_first(self):
        first = self.first_alarm
        injected = self.summary['injected_at']
        return (first is not None and injected is not None and first['wheel'] == self.wheel
                and first['stamp'] >= injected)

    @property
    def false_alarms(self):
        """Alarms before the injection (all of them in a fault-free run)."""
        injected = self.summary['injected_at']
        return [a for a in self.alarms if injected is None or a['stamp'] < injected]

    @property
    def delay(self):
        """From the injection to the first alarm on the right wheel [s] (NaN if none)."""
        injected = self.summary['injected_at']
        hits = [a['stamp'] for a in self.alarms if a['wheel'] == self.wheel
                and injected is not None and a['stamp'] >= injected]
        return min(hits) - injected if hits else math.nan


def demo_run(workdir, condition, fault, wheel, drive, repeat=1):
    """``youbot-fdi demo`` (its script ``repeat`` times, ``drive`` [s] in all) in its own
    process, its incidents in ``workdir/incidents`` (budget ``INCIDENT_BUDGET``); returns its
    :class:`LiveRun`."""
    summary = Path(tempfile.mkstemp(suffix='.json', dir=workdir)[1])
    command = [sys.executable, '-m', 'youbot_fdi.cli.main', 'demo', '--quiet', '--fault', fault,
               '--wheel', wheel, '--summary', str(summary), '--repeat', str(repeat),
               '--incidents', str(Path(workdir) / 'incidents'),
               '--incident-max-count', str(INCIDENT_BUDGET)]
    result = subprocess.run(command, capture_output=True, text=True, timeout=drive + RUN_OVERHEAD,
                            check=False)
    if result.returncode != 0:
        msg = f'demo {fault} on {wheel} ({condition}) failed: {result.stderr.strip()[-400:]}'
        raise RuntimeError(msg)
    return LiveRun(condition, fault, wheel, json.loads(summary.read_text()))


def run_live(progress, soak_minutes=SOAK_MINUTES, faults=None, wheels=None):
    """The soaks and the fault runs; returns the printed report (text)."""
    from youbot_fdi.faults import INJECTABLE
    from youbot_fdi.model.scenario import load_script
    from youbot_fdi.model import load_model
    _, script = load_script()
    repeat = max(1, round(soak_minutes * 60.0 / script.duration))
    faults = faults or [k.value for k in INJECTABLE]
    wheels = wheels or list(load_model('youbot').wheel_names)
    soaks, fault_runs = [], []
    with tempfile.TemporaryDirectory(prefix='youbot_fdi_live_') as workdir:
        for condition, busy in CONDITIONS:
            progress(f'live soak ({condition}): {repeat * script.duration / 60:.1f} min fault-free demo drive')
            with BusyCore() if busy else _Nothing():
                soaks.append(demo_run(workdir, condition, 'none', wheels[0],
                                      repeat * script.duration, repeat))
                for fault in faults:
                    for wheel in wheels:
                        progress(f'live ({condition}): {fault} on {wheel}')
                        fault_runs.append(demo_run(workdir, condition, fault, wheel, script.duration))
        incidents = incident_figures(Path(workdir) / 'incidents')
    return format_live(soaks, fault_runs, repeat * script.duration) + '\n\n' + incidents


def incident_figures(folder):
    """What the soak's incident folder holds at the end, against its budget (text)."""
    from youbot_fdi.app.incidents import BYTES_PER_MEGABYTE, list_incidents
    from youbot_fdi.bag.reader import RecordingError, RecordingReader
    from youbot_fdi.model import load_model
    names = load_model('youbot').wheel_names
    kept = list_incidents(folder) if folder.exists() else []
    readable = 0
    for incident in kept:
        try:
            with RecordingReader(incident.path, names, keep_partial=True) as reader:
                readable += sum(len(chunk.joints) for chunk in reader.chunks()) > 0
        except RecordingError:
            pass
    size = sum(i.size_bytes for i in kept) / BYTES_PER_MEGABYTE
    verdict = 'holds' if len(kept) <= INCIDENT_BUDGET else 'EXCEEDED'
    return (f'Incidents of every run in one folder (budget {INCIDENT_BUDGET}): {len(kept)} kept '
            f'({size:.1f} MB), {sum(i.complete for i in kept)} complete, {readable} readable; '
            f'the budget {verdict}')


def startup_late(run):
    """The shim's late cycles before the drive (while the FDI nodes connected)."""
    return (run.summary.get('shim_startup') or {}).get('late_cycles', 0)


class _Nothing:
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return None


def format_live(soaks, fault_runs, driven):
    """The report: one line per soak, per condition and fault the first-alarm figures."""
    import numpy as np
    lines = [f'Live soak: youbot-fdi demo, separate FDI node processes, fault-free demo drive '
             f'({driven / 60:.1f} min each)',
             f'  {"condition":<10} {"alarms":>6} {"shim cycles":>11} {"late":>5} {"missing":>8} '
             f'{"lateness p99 / max":>19} {"late at start-up":>16}']
    for run in soaks:
        shim = run.summary['shim']
        lines.append(f'  {run.condition:<10} {len(run.alarms):>6} {shim["cycles"]:>11} '
                     f'{shim["late_cycles"]:>5} {shim["incomplete_cycles"]:>8} '
                     f'{shim["lateness_p99"]:>8.1f} / {shim["lateness_max"]:.1f} ms '
                     f'{startup_late(run):>10}')
    lines.append('  late: cycles past the modules\' controller timeout; missing: module answers '
                 'not in their cycle; late at start-up: before the drive (the FDI nodes '
                 'connecting), in all fault runs too')
    startup = [startup_late(run) for run in fault_runs]
    lines.append(f'  late cycles at start-up over the {len(fault_runs)} fault runs: '
                 f'{sum(startup)}')
    lines += ['', 'Every demo fault on every wheel (demo drive, fault at 5 s):',
              f'  {"condition":<10} {"fault":<15} {"runs":>4} {"right wheel first":>17} '
              f'{"false alarms":>12} {"median delay":>12} {"max delay":>10}']
    for condition, _ in CONDITIONS:
        runs = [r for r in fault_runs if r.condition == condition]
        for fault in sorted({r.fault for r in runs}) + ['all']:
            chosen = [r for r in runs if fault in ('all', r.fault)]
            if not chosen:
                continue
            delays = np.array([r.delay for r in chosen])
            found = delays[np.isfinite(delays)]
            median = f'{1000 * np.median(found):.0f} ms' if len(found) else '-'
            worst = f'{1000 * np.max(found):.0f} ms' if len(found) else '-'
            lines.append(f'  {condition:<10} {fault:<15} {len(chosen):>4} '
                         f'{sum(r.right_wheel_first for r in chosen):>12}/{len(chosen):<4} '
                         f'{sum(len(r.false_alarms) for r in chosen):>12} {median:>12} {worst:>10}')
    wrong = [r for r in fault_runs if not r.right_wheel_first]
    if wrong:
        lines.append('  first alarm not on the injected wheel:')
    for run in wrong:
        first, injected = run.first_alarm, run.summary['injected_at']
        said = ('none' if first is None else
                f'{first["wheel"]}: {first["fault"]} {first["stamp"] - injected:+.2f} s from the injection'
                if injected is not None else f'{first["wheel"]}: {first["fault"]}')
        lines.append(f'    {run.condition}, {run.fault} on {run.wheel}: {said}')
    return '\n'.join(lines)
