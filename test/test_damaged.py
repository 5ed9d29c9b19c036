"""Recordings cut short (power lost while recording), without metadata.yaml, or with stamps that
jump: read as far as they can be, analysed, and what was lost said in one line (issue 17)."""
import json
import shutil

import numpy as np
import pytest

from youbot_fdi.bag.reader import RecordingError, RecordingReader
from youbot_fdi.bag.salvage import storage_files
from youbot_fdi.bag.writer import RecordingWriter
from youbot_fdi.cli.main import main
from youbot_fdi.cli.status import DAMAGED, ERROR
from youbot_fdi.app.config import build_pipeline
from youbot_fdi.app.replay import replay_recording
from youbot_fdi.model import load_model
from youbot_fdi.model.scenario import load_script
from youbot_fdi.tmcm.recordings import record_drive

DRIVE = 8.0  # [s]
FAULT_AT = 1.0  # [s] into the drive
WHEEL = 'wheel_joint_bl'


@pytest.fixture(scope='module')
def model():
    return load_model('youbot')


@pytest.fixture(scope='module', params=['sqlite3', 'mcap'])
def intact(request, tmp_path_factory, model):
    """A drive with a stuck wheel from 1 s, and what replay finds in it whole."""
    path = tmp_path_factory.mktemp(request.param) / 'drive'
    record_drive(path, model, load_script(duration=DRIVE)[1], fault='stuck', wheel=WHEEL,
                 fault_time=FAULT_AT, storage=request.param)
    return path, replay_recording(build_pipeline()[1], path).events


def cut(source, target, fraction):
    """A copy of the recording whose storage file ends at ``fraction`` of its size."""
    shutil.copytree(source, target)
    storage = storage_files(target)[0]
    data = storage.read_bytes()
    storage.write_bytes(data[:int(len(data) * fraction)])
    return target


def replay_cli(path, events, capsys):
    status = main(['replay', str(path), '--events', str(events)])
    out, err = capsys.readouterr()
    lines = [json.loads(line) for line in events.read_text().splitlines()]
    return status, lines, out, err


@pytest.mark.parametrize('fraction', [0.25, 0.5, 0.8])
def test_a_cut_recording_gives_the_events_of_its_readable_part(intact, tmp_path, capsys, fraction):
    source, whole = intact
    path = cut(source, tmp_path / 'cut', fraction)
    status, lines, _, err = replay_cli(path, tmp_path / 'events.jsonl', capsys)
    assert status == DAMAGED
    damage_lines = [line for line in err.splitlines() if 'damaged recording' in line]
    assert len(damage_lines) == 1 and 'lost' in damage_lines[0] and 'readable up to' in damage_lines[0]
    with RecordingReader(path, load_model('youbot').wheel_names) as reader:
        last = max(chunk.joints.stamp.max() for chunk in reader.chunks() if len(chunk.joints))
        assert reader.damage.lost and 0 < reader.damage.messages < 2 * DRIVE * 100
    expected = [e.to_dict() for e in whole if e.stamp <= last]
    assert lines == expected  # the same events as the whole recording, up to where it ends
    assert any(e['wheel'] == WHEEL and e['level'] == 'ERROR' for e in lines)  # found after 1 s


def test_a_recording_cut_inside_its_header_is_unreadable(intact, tmp_path, capsys):
    path = cut(intact[0], tmp_path / 'stub', 0.0001)
    status, lines, _, err = replay_cli(path, tmp_path / 'events.jsonl', capsys)
    assert status == ERROR and lines == []
    assert len(err.strip().splitlines()) == 1 and 'not a readable rosbag2 recording' in err


def test_without_metadata_yaml_the_storage_file_is_enough(intact, tmp_path, capsys):
    source, whole = intact
    path = tmp_path / 'bare'
    shutil.copytree(source, path)
    (path / 'metadata.yaml').unlink()
    status, lines, _, err = replay_cli(path, tmp_path / 'events.jsonl', capsys)
    assert status == 0 and 'no metadata.yaml' in err and 'nothing lost' in err
    assert lines == [e.to_dict() for e in whole]


def test_identify_uses_the_readable_part(intact, tmp_path, capsys):
    path = cut(intact[0], tmp_path / 'cut', 0.5)
    params = tmp_path / 'params.yaml'
    assert main(['identify', str(path), '--output', str(params), '--no-gains']) == DAMAGED
    assert params.is_file() and 'damaged recording' in capsys.readouterr().err


def test_the_original_is_never_written(intact, tmp_path, capsys):
    path = cut(intact[0], tmp_path / 'cut', 0.5)
    before = {p.name: p.read_bytes() for p in path.iterdir()}
    replay_cli(path, tmp_path / 'events.jsonl', capsys)
    assert {p.name: p.read_bytes() for p in path.iterdir()} == before


def test_nothing_readable_is_one_clear_error(tmp_path):
    (tmp_path / 'empty').mkdir()
    (tmp_path / 'empty' / 'x.mcap').write_bytes(b'not an mcap file at all')
    with pytest.raises(RecordingError, match='not a readable rosbag2 recording'):
        RecordingReader(tmp_path / 'empty', ['a'])


# ---------------------------------------------------------------------- stamps that jump
@pytest.mark.parametrize('defect, counter', [('backwards', 'stamps_backwards'),
                                             ('duplicate', 'stamps_repeated'),
                                             ('gap', 'gaps')])
def test_stamps_going_backwards_repeated_or_gapped_are_counted(tmp_path, model, capsys, defect, counter):
    """Header stamps (what the FDI goes by) that jump; the recording's receive times run on."""
    rng = np.random.default_rng(3)
    stamps = list(100.0 + 0.01 * np.arange(300))
    if defect == 'backwards':
        stamps[150:] = [s - 5.0 for s in stamps[150:]]  # the sender's clock jumps back 5 s
    elif defect == 'duplicate':
        stamps.insert(150, stamps[150])
    else:
        stamps[150:] = [s + 1.0 for s in stamps[150:]]
    path = tmp_path / defect
    with RecordingWriter(path, model.wheel_names) as writer:
        for k, stamp in enumerate(stamps):
            writer.joint_state(200.0 + 0.01 * k, *rng.normal(scale=0.05, size=(3, 4)),
                               header_stamp=stamp)
    result = replay_recording(build_pipeline()[1], path)
    others = {c for c in ('stamps_backwards', 'stamps_repeated', 'gaps') if c != counter}
    assert result.counters[counter] == 1 and all(result.counters[c] == 0 for c in others)
    assert main(['replay', str(path), '--events', str(tmp_path / 'e.jsonl')]) == 0
    assert f"'{counter}': 1" in capsys.readouterr().out
