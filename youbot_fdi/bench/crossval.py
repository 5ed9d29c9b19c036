"""Cross-validation on the real Robotino recordings (``youbot-fdi bench --faults --suites real``).

A user calibrates on the floor and at the speed they have, then drives elsewhere. Each **fold**
calibrates (``identify``, as a user would) on one covering at one speed, or on one covering at
all speeds, and replays every run calibration did not see: the other covering, the other speeds,
the runs that cross coverings, runs spliced from one covering onto the other half-way, and
faults injected into the recorded signals of a moving wheel (``robotino.FAULTS``: the abrupt
ones, a current ramp x1 -> x2 over 4 s, intermittent readings). Every fold is printed, the worst
first; nothing is tuned per fold or per suite.

Runs ``expNN`` of the data: speed 0.1 x (1 + NN // 72) m/s, direction 5 x (NN % 72) degrees
(``shared/real_data/robotino/README.md``); the development set keeps every third run, so each
(covering, speed) group has 24 directions, every 15 degrees.
"""
from dataclasses import dataclass
import math
from pathlib import Path

import numpy as np

from youbot_fdi.bench import robotino

COVERINGS = {'green': 'green_surface', 'gray': 'gray_surface'}  # carpet, slippery rubber
SPEEDS = (0.1, 0.2, 0.3)  # [m/s] of run expNN: SPEEDS[NN // RUNS_PER_SPEED]
RUNS_PER_SPEED = 72
#: A one-speed calibration drives every other direction of its group (12 runs, every 30 degrees);
#: an all-speed one every third direction of its covering (24 runs, every 45 degrees).
SINGLE_SPEED_STRIDE = 2
ALL_SPEEDS_STRIDE = 3
#: Injected fault cases per fault type, spread over both coverings and every speed; a fold judges
#: those whose run it did not calibrate on.
FAULT_CASES = 12
GAP = 1.0  # [s] between the runs of a calibration recording


def speed_of(number):
    """The set speed [m/s] of run ``expNN``."""
    return SPEEDS[number // RUNS_PER_SPEED]


@dataclass(frozen=True)
class Fold:
    """One calibration and what it is judged on."""

    name: str  # e.g. 'green@0.1' or 'gray@all'
    covering: str
    speed: object  # [m/s], or None: every speed
    calibration: tuple  # run keys ('green/exp00', ...)


@dataclass(frozen=True)
class RealCase:
    """One judged recording: its source runs (keys), the runs themselves, the fault injected."""

    name: str
    sources: tuple  # run keys it is made of (a fold skips it if it calibrated on one of them)
    runs: tuple  # RobotinoRun(s)
    fault: object = None
    wheel: object = None  # wheel index
    onset: object = None  # row


def load_runs(root):
    """{run key: RobotinoRun} of both coverings (keys ``green/exp00``), in run-number order."""
    runs = {}
    for covering, folder in COVERINGS.items():
        paths = sorted((Path(root) / folder).glob('exp*.csv'), key=lambda p: int(p.stem[3:]))
        for path in paths:
            runs[f'{covering}/{path.stem}'] = robotino.read_run(path)
    return runs


def number(key):
    return int(key.rsplit('/exp', 1)[1])


def folds(runs):
    """Every fold: each covering at each speed, then each covering at all speeds."""
    made = []
    for covering in COVERINGS:
        keys = [k for k in runs if k.startswith(covering + '/')]
        for speed in SPEEDS:
            group = [k for k in keys if speed_of(number(k)) == speed]
            made.append(Fold(f'{covering}@{speed:g}', covering, speed,
                             tuple(group[::SINGLE_SPEED_STRIDE])))
    for covering in COVERINGS:
        keys = [k for k in runs if k.startswith(covering + '/')]
        made.append(Fold(f'{covering}@all', covering, None, tuple(keys[::ALL_SPEEDS_STRIDE])))
    return made


def fault_free_cases(runs, root):
    """Every run alone, the real runs that cross coverings, and each green run spliced onto the
    gray run of the same number half-way."""
    cases = [RealCase(key, (key,), (run,)) for key, run in runs.items()]
    crossing_dir = Path(root) / robotino.IDENTIFICATION_DIR
    cases += [RealCase(f'crossing/{name}', (), (robotino.read_run(crossing_dir / name),))
              for name in robotino.CROSSINGS if (crossing_dir / name).is_file()]
    for key, run in runs.items():
        if not key.startswith('green/'):
            continue
        other_key = 'gray/' + key.split('/', 1)[1]
        other = runs.get(other_key)
        if other is not None:
            at = min(len(run), len(other)) // 2
            cases.append(RealCase(f'spliced/{key.split("/", 1)[1]}', (key, other_key),
                                  (robotino.splice(run, other, at),)))
    return cases


def _onset(run, fault):
    """The row a fault begins: mid-run; a ramp early enough to reach x2 before the run ends."""
    onset = int(robotino.ONSET_SHARE * len(run))
    if fault == 'ramp':
        dt = float(np.median(np.diff(run.time)))
        latest = len(run) - int(math.ceil((robotino.RAMP_TIME + 1.0) / dt))
        onset = max(int(2.0 / dt), min(onset, latest))
    return onset


def fault_cases(runs, max_current):
    """``FAULT_CASES`` injected cases per fault type on runs spread over both coverings and every
    speed (ramps on runs long enough to reach x2), each on a wheel set to at least
    ``robotino.MOVING_SHARE`` of the fastest."""
    keys = list(runs)
    cases = []
    for k, fault in enumerate(robotino.FAULTS):
        pool = keys
        if fault == 'ramp':  # the ramp must reach x2 a second before the run ends
            pool = [key for key in keys if runs[key].time[-1] - runs[key].time[0]
                    >= robotino.RAMP_TIME + 3.5]
        for j in range(FAULT_CASES):
            key = pool[(k * 5 + j * 37) % len(pool)]
            run = runs[key]
            onset = _onset(run, fault)
            speed = np.abs(run.set_speed[onset])
            moving = np.flatnonzero(speed >= robotino.MOVING_SHARE * speed.max())
            wheel = int(moving[j % len(moving)])
            cases.append(RealCase(f'{fault}/{key}/wheel{wheel + 1}', (key,),
                                  (robotino.inject(run, fault, wheel, onset, max_current),),
                                  fault, wheel, onset))
    return cases


def judged(fold, cases):
    """The cases ``fold`` did not calibrate on."""
    seen = set(fold.calibration)
    return [c for c in cases if not seen & set(c.sources)]


# ---------------------------------------------------------------------- running the folds
def _convert(job):
    """Write one case as a recording (kept if the folder has it already: it depends on the data
    alone); (name, scoring.Case) (worker process)."""
    from youbot_fdi.bench.scoring import Case
    from youbot_fdi.model.profile import load_model
    case, workdir = job
    model = load_model(robotino.PROFILE)
    path = Path(workdir) / case.name.replace('/', '_')
    if (path / 'metadata.yaml').is_file():
        start = robotino.START_STAMP
    else:
        start = robotino.write_recording(case.runs, path, model)[0]
    run = case.runs[0]
    onset = math.nan if case.onset is None else start + float(run.time[case.onset] - run.time[0])
    return case.name, Case(case.name, str(path), float(run.time[-1] - run.time[0]), case.fault,
                           None if case.wheel is None else model.wheel_names[case.wheel], onset,
                           robotino.EXPECTED_KIND.get(case.fault), start)


def _calibrate(job):
    """Identify one fold on its calibration runs; (fold name, {variant: params}, result info)."""
    from youbot_fdi.bench.calibration import calibrate, residual_spread
    from youbot_fdi.model.profile import load_model
    fold, runs, workdir = job
    model = load_model(robotino.PROFILE)
    path = Path(workdir) / f'calibration_{fold.name.replace("@", "_")}'
    if not (path / 'metadata.yaml').is_file():
        robotino.write_recording([runs[k] for k in fold.calibration], path, model, gap=GAP)
    params, result = calibrate(path, model, Path(workdir) / 'params' / fold.name.replace('@', '_'))
    return fold.name, params, {'samples': result.info['samples'], 'coverage': result.coverage,
                               'spread': residual_spread(result)}


def _replay(job):
    from youbot_fdi.bench.scoring import replay_scored
    fold_name, case, params = job
    return fold_name, replay_scored(case, params)


@dataclass(frozen=True)
class FoldResult:
    """A fold's calibration and its scored replays ({variant: [result dicts]})."""

    fold: Fold
    calibration: dict  # samples, coverage, spread
    results: dict


def run_crossval(workdir, progress=print, workers=2, root=None):
    """Every fold; returns [FoldResult], or None when the data are absent."""
    from concurrent.futures import ProcessPoolExecutor
    from youbot_fdi.model.profile import load_model
    root = root or robotino.data_dir()
    if root is None:
        return None
    workdir = Path(workdir) / 'crossval'
    workdir.mkdir(parents=True, exist_ok=True)
    (workdir / 'params').mkdir(exist_ok=True)
    runs = load_runs(root)
    max_current = load_model(robotino.PROFILE).drive.max_current
    cases = fault_free_cases(runs, root) + fault_cases(runs, max_current)
    made = folds(runs)
    progress(f'real data: {len(made)} folds; {len(cases)} recordings to convert, '
             f'{len(made)} calibrations ...')
    with ProcessPoolExecutor(workers) as pool:
        converted = dict(pool.map(_convert, [(c, str(workdir)) for c in cases], chunksize=8))
        calibrated = {name: (params, info) for name, params, info in
                      pool.map(_calibrate, [(f, runs, str(workdir)) for f in made])}
        jobs = [(fold.name, converted[c.name], calibrated[fold.name][0])
                for fold in made for c in judged(fold, cases)]
        progress(f'real data: {len(jobs)} replays (every fold, both variants) ...')
        scored = list(pool.map(_replay, jobs, chunksize=8))
    out = []
    for fold in made:
        mine = [r for name, r in scored if name == fold.name]
        variants = mine[0].keys() if mine else ()
        out.append(FoldResult(fold, calibrated[fold.name][1],
                              {v: [r[v] for r in mine] for v in variants}))
    return out


# ---------------------------------------------------------------------- the printed report
def fold_figures(results):
    """A fold's figures from its result dicts: hours, false alarms, runs with one, abrupt faults
    found and isolated, their median and p90 delay, ramps found before x2, intermittent found."""
    from youbot_fdi.bench.scoring import delay_quantiles
    abrupt = [r for r in results if r['fault'] in robotino.ABRUPT]
    median, p90 = delay_quantiles(abrupt)
    ramps = [r for r in results if r['fault'] == 'ramp']
    intermittent = [r for r in results if r['fault'] == 'intermittent']
    return {
        'hours': sum(r['fault_free_seconds'] for r in results) / 3600.0,
        'runs': len(results),
        'false_alarms': sum(r['false_alarms'] for r in results),
        'runs_with_alarm': sum(1 for r in results if r['false_alarms']),
        'abrupt': len(abrupt),
        'abrupt_isolated': sum(r['detected'] and r['isolated'] for r in abrupt),
        'median': median,
        'p90': p90,
        'ramps': len(ramps),
        'ramps_in_time': sum(r['detected'] and r['isolated'] and r['delay'] < robotino.RAMP_TIME
                             for r in ramps),
        'intermittent': len(intermittent),
        'intermittent_found': sum(r['detected'] and r['isolated'] for r in intermittent),
    }


def _badness(figures):
    """Sort key: the worst fold first (most false alarms, then fewest abrupt faults isolated,
    then the slowest)."""
    missed = figures['abrupt'] - figures['abrupt_isolated']
    return (-figures['false_alarms'], -missed,
            -(figures['median'] if not math.isnan(figures['median']) else math.inf))


def summarise_folds(fold_results, variant):
    """The cross-validation table of ``variant``: every fold (worst first), then all pooled."""
    from youbot_fdi.bench.scoring import summarise
    rows = [(fr, fold_figures(fr.results[variant])) for fr in fold_results]
    rows.sort(key=lambda row: _badness(row[1]))
    lines = ['Real-data cross-validation, Festo Robotino: calibrated on one covering at one speed '
             '(or all speeds), judged on every run it did not see; worst fold first',
             f'  {"fold":<10}{"calib.":>7}{"runs":>6}{"hours":>7}{"false alarms":>14}'
             f'{"abrupt found":>14}{"median":>8}{"p90":>8}{"ramp<x2":>9}{"intermittent":>14}']
    for fold_result, f in rows:
        lines.append(
            f'  {fold_result.fold.name:<10}{len(fold_result.fold.calibration):>7}{f["runs"]:>6}'
            f'{f["hours"]:>7.2f}{f["false_alarms"]:>6} ({f["runs_with_alarm"]:>3} runs)'
            f'{f["abrupt_isolated"]:>8}/{f["abrupt"]:<5}{1000 * f["median"]:>6.0f}ms'
            f'{1000 * f["p90"]:>6.0f}ms{f["ramps_in_time"]:>5}/{f["ramps"]:<3}'
            f'{f["intermittent_found"]:>8}/{f["intermittent"]:<5}')
    pooled = [r for fr in fold_results for r in fr.results[variant]]
    lines.append('  (abrupt: isolated on the right wheel; ramp<x2: found before the current '
                 'doubled; delays of abrupt faults)')
    lines.append('')
    lines.append(summarise('All folds pooled (a run is judged once per fold that did not see it)',
                           pooled))
    return '\n'.join(lines)
