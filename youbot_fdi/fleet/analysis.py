"""One recording of a fleet: where it is, whose it is, and what it says (the Dask task).

**Robot and time rule.** A recording is a rosbag2 directory (one holding ``metadata.yaml`` or a
``.db3``/``.mcap`` storage file) anywhere below ROOT. Its robot is the first folder below ROOT
(``ROOT/<robot>/...``; ``unknown`` for a recording directly in ROOT); its time is the header stamp
of its first joint state (the robot's clock, as the events use it). Its name is its path below
ROOT with ``/`` written ``__``: ``OUT/events/<name>.jsonl``.
"""
from dataclasses import dataclass
import json
import math
from pathlib import Path

from youbot_fdi.bag.salvage import STORAGE_SUFFIXES
from youbot_fdi.faults import Level

UNKNOWN_ROBOT = 'unknown'
NAME_SEPARATOR = '__'


@dataclass(frozen=True)
class FleetRecording:
    """A recording found below the fleet's root."""

    path: str
    name: str  # unique, file-name safe
    robot: str


def discover(root):
    """Every rosbag2 recording below ``root``, sorted by path (a recording's own folders are not
    searched further)."""
    root = Path(root)
    found = []

    def is_recording(folder):
        return (folder / 'metadata.yaml').is_file() or any(
            p.suffix in STORAGE_SUFFIXES for p in folder.iterdir() if p.is_file())

    def walk(folder):
        if folder != root and is_recording(folder):
            relative = folder.relative_to(root).parts
            found.append(FleetRecording(str(folder), NAME_SEPARATOR.join(relative),
                                        relative[0] if len(relative) > 1 else UNKNOWN_ROBOT))
            return
        for child in sorted(p for p in folder.iterdir() if p.is_dir()):
            walk(child)

    if root.is_dir():
        if is_recording(root):
            found.append(FleetRecording(str(root), root.name, UNKNOWN_ROBOT))
        else:
            walk(root)
    return found


def warm_up():
    """Import what :func:`analyse` needs (run once on every worker when the cluster starts)."""
    import youbot_fdi.bag.reader  # noqa: F401
    import youbot_fdi.fdi.identify  # noqa: F401
    import youbot_fdi.fdi.pipeline  # noqa: F401
    return True


def analyse(recording, params_path, output, fault_free_margin):
    """Replay ``recording`` (the pipeline of ``replay``, events to ``OUT/events/<name>.jsonl``)
    and identify its friction on the stretch before its first alarm; returns the row of
    ``recordings.csv`` as a dict (``status`` ok, damaged or error, never an exception) and keeps it
    in ``OUT/rows/<name>.json`` (what a resumed run skips)."""
    import numpy as np

    from youbot_fdi.app.eventlog import EventLog
    from youbot_fdi.app.config import build_pipeline
    from youbot_fdi.app.incidents import incident_parameters, is_incident
    from youbot_fdi.app.replay import replay_recording
    output = Path(output)
    row = {'recording': recording.name, 'robot': recording.robot, 'path': recording.path,
           'start': math.nan, 'duration_s': math.nan, 'samples': 0, 'faults': {},
           'friction': [], 'friction_sd': [], 'mass': math.nan, 'mass_sd': math.nan,
           'status': 'ok', 'error': ''}
    try:
        # An incident (youbot_fdi/app/incidents.py) carries what its robot ran with; it is replayed
        # with that unless the fleet was given a parameter file.
        fdi_config = None
        if not params_path and is_incident(recording.path):
            params_path, fdi_config = incident_parameters(recording.path)
        model, pipeline = build_pipeline(params_path, fdi_config)
        row['wheels'] = list(model.wheel_names)
        with EventLog(output / 'events' / f'{recording.name}.jsonl') as log:
            result = replay_recording(pipeline, recording.path, on_event=log.write)
        row['samples'] = int(result.counters['joint_states'])
        faults = {}
        for event in result.events:
            if event.level == Level.ERROR:
                key = f'{event.fault}@{event.wheel or "base"}'
                faults[key] = faults.get(key, 0) + 1
        row['faults'] = faults
        if result.damage is not None and result.damage.lost:
            row['status'], row['error'] = 'damaged', result.damage.describe()
        first_alarm = min((e.stamp for e in result.events if e.level == Level.ERROR), default=math.inf)
        row.update(_identify_friction(recording.path, model, first_alarm - fault_free_margin,
                                      pipeline.settings))
    except Exception as err:  # noqa: BLE001 - one recording's failure is its row, never the run's
        row['status'], row['error'] = 'error', f'{type(err).__name__}: {err}'
    row['friction'] = [float(v) for v in np.asarray(row['friction'], dtype=float)]
    row['friction_sd'] = [float(v) for v in np.asarray(row['friction_sd'], dtype=float)]
    rows = output / 'rows'
    rows.mkdir(parents=True, exist_ok=True)
    temporary = rows / f'.{recording.name}.json'
    temporary.write_text(json.dumps(row))
    temporary.replace(rows / f'{recording.name}.json')  # whole or absent: resume can trust it
    return row


def _identify_friction(path, model, until, settings):
    """Start, duration and the identified viscous friction per wheel [N·m·s/rad] and mass [kg],
    each with its standard deviation (``friction_sd``, ``mass_sd``; the model as the prior,
    ``settings`` its spread), from the samples before ``until`` [s] (NaN when too few or no
    effort recorded)."""
    from youbot_fdi.app.recordings import read_arrays
    from youbot_fdi.fdi.identify import fit_dynamics, IdentificationError, MIN_SAMPLES, RecordingArrays
    arrays = read_arrays(path, model)
    found = {'start': float(arrays.time[0]), 'duration_s': float(arrays.time[-1] - arrays.time[0]),
             'friction': [math.nan] * model.dynamics.n_wheels,
             'friction_sd': [math.nan] * model.dynamics.n_wheels}
    keep = arrays.time < until
    if keep.sum() < MIN_SAMPLES:
        return found
    clean = RecordingArrays(arrays.time[keep], arrays.position[keep], arrays.velocity[keep],
                            arrays.torque[keep], [c for c in arrays.commands if c.stamp < until])
    try:
        fit = fit_dynamics(clean, model, settings)
    except IdentificationError:
        return found
    sd, n = fit.info['uncertainty'], model.dynamics.n_wheels
    found.update(friction=list(fit.parameters.viscous_friction), mass=float(fit.parameters.mass),
                 friction_sd=[sd[f'viscous_friction[{j}]'] for j in range(n)], mass_sd=sd['mass'],
                 unexcited=list(fit.info['unexcited']))
    return found


def load_rows(output):
    """The rows of every recording already analysed in ``OUT`` (by name)."""
    rows = Path(output) / 'rows'
    if not rows.is_dir():
        return {}
    return {p.stem: json.loads(p.read_text()) for p in sorted(rows.glob('*.json'))
            if not p.name.startswith('.')}
