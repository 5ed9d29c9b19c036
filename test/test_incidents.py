"""The black box (issue 35): the incident recorder's ring, windows, budget and durability, without
ROS (the live demo's incidents are tested in test_live.py)."""
import functools
import os
from pathlib import Path
import signal
import subprocess
import sys
import textwrap

import numpy as np
import pytest
import yaml

from youbot_fdi.app.incidents import (IncidentRecorder, IncidentSettings, list_incidents,
                                      MessageRing, NANOSECONDS, read_sidecar, RunContext)
from youbot_fdi.bag.reader import RecordingReader
from youbot_fdi.errors import ConfigError
from youbot_fdi.topics import JOINT_STATES

#: `make check` runs this module's unit tests (marker fast) but for these, which simulate a drive.
FAST_EXCEPT = ('test_an_incident_replays_to_its_alarm_lists_and_joins_a_fleet',)
NAMES = ['wheel_joint_fl', 'wheel_joint_fr', 'wheel_joint_bl', 'wheel_joint_br']
RATE = 100.0  # [Hz] of the synthetic /joint_states
EVENT = {'stamp': 12.0, 'level': 'ERROR', 'wheel': 'wheel_joint_fr', 'fault': 'torque_loss',
         'residuals': ['torque_fr'], 'detail': 'test'}


@functools.cache
def typestore():
    from rosbags.typesys import get_typestore, Stores
    return get_typestore(Stores.ROS2_JAZZY)


def joint_state_bytes(stamp):
    """A /joint_states message stamped ``stamp`` [s] as CDR bytes (what a raw subscription gets)."""
    store = typestore()
    types = store.types
    sec = int(stamp)
    header = types['std_msgs/msg/Header'](
        stamp=types['builtin_interfaces/msg/Time'](sec=sec, nanosec=int(round((stamp - sec) * 1e9))),
        frame_id='')
    msg = types['sensor_msgs/msg/JointState'](header=header, name=NAMES,
                                              position=np.full(4, stamp), velocity=np.ones(4),
                                              effort=np.zeros(4))
    return bytes(store.serialize_cdr(msg, 'sensor_msgs/msg/JointState'))


def feed(recorder, start, stop, open_at=()):
    """Record samples at RATE from ``start`` to ``stop`` [s] (receive time = stamp), opening an
    incident at each time of ``open_at``."""
    pending = sorted(open_at)
    for stamp in np.arange(start, stop, 1.0 / RATE):
        recorder.record(JOINT_STATES, int(round(stamp * NANOSECONDS)), joint_state_bytes(stamp))
        while pending and stamp >= pending[0]:
            recorder.open({**EVENT, 'stamp': float(stamp)}, int(round(stamp * NANOSECONDS)),
                          {'wheels': {}})
            pending.pop(0)


def recorded_stamps(path):
    with RecordingReader(path, NAMES, keep_partial=True) as reader:
        return np.concatenate([chunk.joints.stamp for chunk in reader.chunks()])


def test_message_ring_keeps_its_span():
    ring = MessageRing(span=1.0)
    for k in range(300):  # 3 s at 100 Hz
        ring.add(('t', k * 10_000_000, b''))
    times = [item[1] for item in ring.items]
    assert times[0] == 199 * 10_000_000 and times[-1] == 299 * 10_000_000  # the last second
    assert [i[1] for i in ring.since(295 * 10_000_000)] == [k * 10_000_000 for k in range(295, 300)]


def test_incident_holds_the_window_around_the_alarm(tmp_path):
    settings = IncidentSettings(incident_dir=str(tmp_path), incident_before=2.0, incident_after=1.0)
    logged = []
    recorder = IncidentRecorder(settings, RunContext(profile='youbot'), log=logged.append)
    feed(recorder, 0.0, 8.0, open_at=[5.0])
    recorder.close()
    [incident] = list_incidents(tmp_path)
    assert (incident.wheel, incident.fault, incident.complete) == ('wheel_joint_fr', 'torque_loss', True)
    stamps = recorded_stamps(incident.path)
    # From `before` ahead of the alarm to `after` past it, every sample, none outside.
    assert stamps[0] == pytest.approx(3.0, abs=1e-6) and stamps[-1] == pytest.approx(6.0, abs=0.011)
    assert len(stamps) == pytest.approx(3.0 * RATE, abs=2)
    sidecar = read_sidecar(incident.path)
    assert sidecar['ended'] == 'after' and sidecar['messages'][JOINT_STATES] == len(stamps)
    assert sidecar['software']['youbot_fdi'] and sidecar['event']['fault'] == 'torque_loss'
    assert sidecar['window']['recorded_before_s'] == pytest.approx(2.0, abs=1e-6)
    assert any('incident:' in line for line in logged)


def test_incident_cut_by_shutdown_keeps_what_came(tmp_path):
    settings = IncidentSettings(incident_dir=str(tmp_path), incident_before=1.0, incident_after=5.0)
    recorder = IncidentRecorder(settings, RunContext(), log=lambda _: None)
    feed(recorder, 0.0, 3.0, open_at=[2.0])
    recorder.close()
    [incident] = list_incidents(tmp_path)
    assert read_sidecar(incident.path)['ended'] == 'shutdown'
    assert read_sidecar(incident.path)['window']['recorded_before_s'] == pytest.approx(1.0, abs=1e-6)
    stamps = recorded_stamps(incident.path)
    assert stamps[0] == pytest.approx(1.0, abs=1e-6) and stamps[-1] == pytest.approx(2.99, abs=1e-6)


def test_parameter_file_and_settings_travel_with_the_incident(tmp_path):
    params = tmp_path / 'params.yaml'
    params.write_text('profile: {name: youbot}\n')
    settings = IncidentSettings(incident_dir=str(tmp_path / 'incidents'), incident_before=0.5,
                                incident_after=0.5)
    context = RunContext(params_file=str(params), settings={'family_thresholds': [3.0, 4.0]},
                         profile='youbot')
    recorder = IncidentRecorder(settings, context, log=lambda _: None)
    feed(recorder, 0.0, 2.0, open_at=[1.0])
    recorder.close()
    [incident] = list_incidents(tmp_path / 'incidents')
    import hashlib
    sidecar = read_sidecar(incident.path)
    assert sidecar['parameters']['params_sha256'] == hashlib.sha256(params.read_bytes()).hexdigest()
    assert (incident.path / 'params.yaml').read_text() == params.read_text()
    copied = yaml.safe_load((incident.path / 'fdi.yaml').read_text())
    assert copied['/**']['ros__parameters']['family_thresholds'] == [3.0, 4.0]


def test_budget_drops_the_oldest_first(tmp_path):
    settings = IncidentSettings(incident_dir=str(tmp_path), incident_before=0.2, incident_after=0.2,
                                incident_max_count=3)
    logged = []
    recorder = IncidentRecorder(settings, RunContext(), log=logged.append)
    feed(recorder, 0.0, 6.0, open_at=[0.5, 1.5, 2.5, 3.5, 4.5])
    recorder.close()
    kept = list_incidents(tmp_path)
    assert [i.stamp for i in kept] == pytest.approx([2.5, 3.5, 4.5], abs=0.011)
    assert recorder.dropped == 2
    assert sum('dropped the oldest' in line for line in logged) == 2

    # The size budget: room for little more than one of them; the folder stays within it.
    size = kept[-1].size_bytes
    budget = 1.5 * size
    settings = IncidentSettings(incident_dir=str(tmp_path), incident_before=0.2, incident_after=0.2,
                                incident_max_megabytes=budget / 1e6)
    recorder = IncidentRecorder(settings, RunContext(), log=logged.append)
    feed(recorder, 10.0, 12.0, open_at=[10.5])
    recorder.close()
    kept = list_incidents(tmp_path)
    assert [i.stamp for i in kept] == pytest.approx([10.5], abs=0.011)
    assert sum(i.size_bytes for i in kept) <= budget


def test_settings_are_checked():
    with pytest.raises(ConfigError, match='incident_max_count'):
        IncidentSettings(incident_max_count=0).validate('here')
    with pytest.raises(ConfigError, match='incident_before'):
        IncidentSettings(incident_before=-1.0).validate('here')
    assert IncidentSettings(incident_dir='').folder().parts[-2:] == ('youbot_fdi', 'incidents')


def test_a_damaged_sidecar_is_listed_as_such_and_hides_no_other_incident(tmp_path, capsys):
    """Bad input gets a diagnostic, not a crash: an incident whose incident.yaml was damaged is
    listed with why it cannot be read; the others are listed as usual."""
    from youbot_fdi.cli.main import main
    settings = IncidentSettings(incident_dir=str(tmp_path), incident_before=0.2, incident_after=0.2)
    recorder = IncidentRecorder(settings, RunContext(), log=lambda _: None)
    feed(recorder, 0.0, 3.0, open_at=[0.5, 1.5, 2.5])
    recorder.close()
    first, second, third = list_incidents(tmp_path)
    (second.path / 'incident.yaml').write_text('event: [unclosed\n')
    (third.path / 'incident.yaml').write_text('just: text\n')
    listed = list_incidents(tmp_path)
    assert [i.path for i in listed] == [first.path, second.path, third.path]
    assert listed[0].problem == '' and listed[0].complete
    assert 'cannot read the incident sidecar' in listed[1].problem and not listed[1].complete
    assert 'no event' in listed[2].problem
    assert main(['incidents', str(tmp_path), '--no-pages']) == 0
    out = capsys.readouterr().out
    assert '3 incidents' in out and out.count('unreadable:') == 2 and 'complete' in out


KILLED = textwrap.dedent('''
    import os, signal, sys
    sys.path.insert(0, {test_dir!r})
    from test_incidents import feed
    from youbot_fdi.app.incidents import IncidentRecorder, IncidentSettings, RunContext
    settings = IncidentSettings(incident_dir={folder!r}, incident_before=1.0, incident_after=30.0)
    recorder = IncidentRecorder(settings, RunContext(), log=lambda _: None)
    feed(recorder, 0.0, 2.0, open_at=[1.5])       # an incident opens...
    feed(recorder, 2.0, 6.0)                        # ... and is being written
    recorder.flush()
    os.kill(os.getpid(), signal.SIGKILL)
''')


def test_kill_9_cuts_only_the_incident_being_written(tmp_path):
    """An incident cut by kill -9 reads to its damage like any recording: its sidecar says it is
    not complete, and what was flushed (all but the last FLUSH_INTERVAL at most) reads back."""
    code = KILLED.format(test_dir=str(Path(__file__).parent), folder=str(tmp_path))
    result = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                            timeout=120, check=False)
    assert result.returncode == -signal.SIGKILL, result.stderr
    [incident] = list_incidents(tmp_path)
    assert not incident.complete
    with RecordingReader(incident.path, NAMES, keep_partial=True) as reader:
        stamps = np.concatenate([chunk.joints.stamp for chunk in reader.chunks()])
        assert reader.damage is not None
    assert stamps[0] == pytest.approx(0.5, abs=1e-6)
    assert stamps[-1] >= 6.0 - 1.0 - 0.02  # what was flushed: at most FLUSH_INTERVAL is cut
    assert not os.path.exists(incident.path / 'metadata.yaml')


def test_an_incident_replays_to_its_alarm_lists_and_joins_a_fleet(tmp_path):
    """An incident made as the decision node makes it (the recording's messages as they were
    received, opened at the alarm) replays with its own parameters to the same alarm, is listed
    with a page by `youbot-fdi incidents`, and `fleet`'s per-recording analysis takes it like
    any recording (issue 35)."""
    from rosbags.rosbag2 import Reader

    from youbot_fdi.app.config import build_pipeline
    from youbot_fdi.app.incidents import incident_parameters
    from youbot_fdi.app.replay import replay_recording
    from youbot_fdi.cli.main import main
    from youbot_fdi.fleet.analysis import analyse, discover
    from youbot_fdi.model import load_model
    from youbot_fdi.model.scenario import load_script
    from youbot_fdi.tmcm.recordings import record_drive
    model = load_model('youbot')
    _, script = load_script()
    record_drive(tmp_path / 'drive', model, script.scaled_to(8.0), fault='torque_loss',
                 wheel='wheel_joint_fr', fault_time=4.0)
    _, pipeline = build_pipeline()
    [alarm] = [e for e in replay_recording(pipeline, tmp_path / 'drive').events if e.level == 'ERROR'][:1]
    assert (alarm.wheel, alarm.fault) == ('wheel_joint_fr', 'torque_loss')

    folder = tmp_path / 'incidents' / 'robot_a'
    settings = IncidentSettings(incident_dir=str(folder), incident_before=3.0, incident_after=1.0)
    recorder = IncidentRecorder(settings, RunContext(settings={}, profile='youbot'),
                                log=lambda _: None)
    opened = False
    with Reader(tmp_path / 'drive') as reader:
        for connection, time_ns, data in reader.messages():
            recorder.record(connection.topic, time_ns, bytes(data))
            if not opened and time_ns >= alarm.stamp * NANOSECONDS:
                recorder.open(alarm.to_dict(), time_ns, {'wheels': {}})
                opened = True
    recorder.close()

    [incident] = list_incidents(tmp_path / 'incidents')
    _, pipeline = build_pipeline(*incident_parameters(incident.path))
    replayed = [e for e in replay_recording(pipeline, incident.path).events if e.level == 'ERROR']
    assert [(e.wheel, e.fault) for e in replayed][:1] == [('wheel_joint_fr', 'torque_loss')]
    assert replayed[0].stamp == pytest.approx(alarm.stamp, abs=0.011)

    events = tmp_path / 'replayed.jsonl'
    assert main(['replay', str(incident.path), '--events', str(events)]) == 0
    import json
    first = next(json.loads(line) for line in events.read_text().splitlines()
                 if json.loads(line)['level'] == 'ERROR')
    assert (first['wheel'], first['fault']) == ('wheel_joint_fr', 'torque_loss')

    assert main(['incidents', str(tmp_path / 'incidents')]) == 0
    page = (incident.path / 'incident.html').read_text()
    assert 'torque_loss on wheel_joint_fr' in page and 'the same alarm' in page

    [found] = discover(tmp_path / 'incidents')
    assert found.robot == 'robot_a'
    row = analyse(found, None, tmp_path / 'fleet', 0.5)
    assert row['status'] == 'ok' and 'torque_loss@wheel_joint_fr' in row['faults']


def test_an_unwritable_folder_is_logged_and_the_recorder_goes_on(tmp_path):
    """A folder that cannot be created (here a file stands in its way; a full disk alike) costs
    the incident, said in the log, never the FDI: the recorder keeps recording and closes."""
    blocked = tmp_path / 'not_a_folder'
    blocked.write_text('')
    logged = []
    settings = IncidentSettings(incident_dir=str(blocked / 'incidents'), incident_before=0.5,
                                incident_after=0.5)
    recorder = IncidentRecorder(settings, RunContext(), log=logged.append)
    feed(recorder, 0.0, 3.0, open_at=[1.0, 2.0])
    assert recorder.flush()
    recorder.close()
    assert sum('incident recorder: open failed' in line for line in logged) == 2
    assert list_incidents(tmp_path) == []
