"""The youbot-fdi command line, run as a user would."""
import subprocess
import sys

import pytest

from youbot_fdi.cli.main import main


def run_cli(*args):
    return subprocess.run([sys.executable, '-m', 'youbot_fdi.cli.main', *args],
                          capture_output=True, text=True, timeout=120)


def test_simulate_prints_a_summary_and_writes_a_figure(tmp_path):
    result = run_cli('simulate', '--duration', '3', '--output-dir', str(tmp_path))
    assert result.returncode == 0, result.stderr
    for name in ('wheel_joint_fl', 'wheel_joint_fr', 'wheel_joint_bl', 'wheel_joint_br'):
        assert name in result.stdout
    assert 'final pose odometry' in result.stdout
    figure = tmp_path / 'drive.png'
    assert figure.stat().st_size > 10_000
    assert figure.read_bytes()[:8] == b'\x89PNG\r\n\x1a\n'


def test_model_command_shows_the_seed_weak_spot(capsys):
    assert main(['model', '--profile', 'seed']) == 0
    out = capsys.readouterr().out
    assert 'UNSTABLE' in out and 'cond(M) = 985' in out
    assert main(['model', '--profile', 'youbot']) == 0
    assert '(stable)' in capsys.readouterr().out


def test_unknown_profile_is_a_one_line_error(capsys):
    assert main(['model', '--profile', 'no_such_robot']) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and 'unknown profile' in err[0]


@pytest.mark.parametrize('args', [['--help'], ['demo', '--help'], ['simulate', '--help'], ['model', '--help'], ['replay', '--help'], ['identify', '--help'], ['record', '--help'], ['structure', '--help'], ['bench', '--help'], ['echo', '--help'], ['play', '--help'], ['incidents', '--help']])
def test_help_everywhere(args):
    result = run_cli(*args)
    assert result.returncode == 0 and 'usage: youbot-fdi' in result.stdout
