"""Packaging: the core stays free of ROS, and colcon builds an ament_python install tree."""
import os
from pathlib import Path
import shutil
import signal
import subprocess
import sys

import pytest

REPO = Path(__file__).resolve().parent.parent
PACKAGE_FILES = ('package.xml', 'setup.py', 'setup.cfg', 'README.md', 'resource', 'youbot_fdi', 'launch',
                 'config')
CORE_MODULES = ('youbot_fdi.model.simulation', 'youbot_fdi.structure.analysis', 'youbot_fdi.fdi.residuals',
                'youbot_fdi.fdi.decision', 'youbot_fdi.fdi.pipeline', 'youbot_fdi.fdi.identify')

# Run in a fresh interpreter: the top-level packages named in argv[1] cannot be imported.
BLOCK_IMPORTS = """
import sys
blocked = set(sys.argv[1].split(','))
class Block:
    def find_spec(self, name, path=None, target=None):
        if name.split('.')[0] in blocked:
            raise ImportError('blocked: ' + name)
sys.meta_path.insert(0, Block())
"""
BLOCKER = BLOCK_IMPORTS + """
import importlib
for module in sys.argv[2:]:
    importlib.import_module(module)
"""
TMCM_MODULES = ('youbot_fdi.tmcm.tmcl', 'youbot_fdi.tmcm.process_data', 'youbot_fdi.tmcm.driver',
                'youbot_fdi.tmcm.virtual_base', 'youbot_fdi.bench.speed')


def import_blocked(blocked, modules):
    return subprocess.run([sys.executable, '-c', BLOCKER, ','.join(blocked), *modules],
                          capture_output=True, text=True, timeout=60)


def test_core_imports_without_rclpy_can_or_rosbags():
    result = import_blocked(('rclpy', 'can', 'rosbags'), CORE_MODULES)
    assert result.returncode == 0, result.stderr


def test_offline_command_line_imports_without_rclpy():
    result = import_blocked(('rclpy',), ('youbot_fdi.cli.main', 'youbot_fdi.bag', 'youbot_fdi.tmcm.recordings'))
    assert result.returncode == 0, result.stderr


HELP = BLOCK_IMPORTS + """
from youbot_fdi.cli.main import build_parser, main
commands = [None] + sorted(build_parser()._subparsers._group_actions[0].choices)
for command in commands:
    try:
        main([command, '--help'] if command else ['--help'])
    except SystemExit as done:
        assert done.code == 0, (command, done.code)
print(len(commands))
"""


def test_every_help_starts_without_numpy_scipy_rosbags_or_rclpy():
    """``youbot-fdi [COMMAND] --help`` parses and prints without the heavy libraries (issue 14: the
    command line starts at once); each sub-command imports what it needs when it runs."""
    result = subprocess.run([sys.executable, '-c', HELP, 'numpy,scipy,rosbags,rclpy,can,matplotlib'],
                            capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    assert int(result.stdout.split()[-1]) >= 10  # the umbrella and every sub-command


def test_can_layer_imports_without_rclpy_or_rosbags():
    result = import_blocked(('rclpy', 'rosbags'), TMCM_MODULES)
    assert result.returncode == 0, result.stderr


def test_only_nodes_import_rclpy():
    offenders = []
    for path in (REPO / 'youbot_fdi').rglob('*.py'):
        if 'nodes' in path.relative_to(REPO / 'youbot_fdi').parts:
            continue
        text = path.read_text()
        if 'import rclpy' in text or 'from rclpy' in text:
            offenders.append(str(path.relative_to(REPO)))
    assert offenders == []


def test_colcon_build_installs_executables_and_ament_marker(tmp_path):
    colcon = shutil.which('colcon') or str(Path(sys.executable).parent / 'colcon')
    if not Path(colcon).exists():
        pytest.skip('colcon is not installed (make venv installs it)')
    source = tmp_path / 'ws' / 'src' / 'youbot_fdi'
    source.mkdir(parents=True)
    for name in PACKAGE_FILES:
        src = REPO / name
        if src.is_dir():
            shutil.copytree(src, source / name, ignore=shutil.ignore_patterns('__pycache__'))
        else:
            shutil.copy2(src, source / name)
    env = dict(os.environ, COLCON_HOME=str(tmp_path / 'colcon_home'))
    result = subprocess.run([colcon, 'build', '--base-paths', 'src'], cwd=tmp_path / 'ws',
                            capture_output=True, text=True, timeout=300, env=env)
    assert result.returncode == 0, result.stdout + result.stderr
    install = tmp_path / 'ws' / 'install' / 'youbot_fdi'
    executable = install / 'lib' / 'youbot_fdi' / 'youbot-fdi'
    assert executable.is_file() and os.access(executable, os.X_OK)
    assert (install / 'share' / 'ament_index' / 'resource_index' / 'packages' / 'youbot_fdi').is_file()
    assert (install / 'share' / 'youbot_fdi' / 'package.xml').is_file()
    assert (install / 'share' / 'youbot_fdi' / 'config' / 'profiles' / 'youbot.yaml').is_file()
    assert (install / 'share' / 'youbot_fdi' / 'launch' / 'youbot_fdi.launch.py').is_file()
    assert (install / 'share' / 'youbot_fdi' / 'config' / 'diagnostic_aggregator.yaml').is_file()
    # The installed script runs from the install tree and finds its shared config there.
    site = next(install.glob('lib/python3*/site-packages'))
    run_env = dict(os.environ, PYTHONPATH=str(site), AMENT_PREFIX_PATH=str(install))
    result = subprocess.run([str(executable), 'model', '--profile', 'youbot'], capture_output=True,
                            text=True, timeout=60, env=run_env, cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    assert str(install / 'share' / 'youbot_fdi' / 'config') in result.stdout


def test_every_node_parameter_file_loads_into_its_settings():
    from youbot_fdi.fdi.settings import FdiSettings
    from youbot_fdi.settings import load_settings, node_parameters
    from youbot_fdi.tmcm.driver import DriverSettings
    from youbot_fdi.tmcm.virtual_base import VirtualBaseSettings
    import yaml
    assert load_settings(DriverSettings, 'driver_shim').cycle_rate == 100.0
    assert load_settings(VirtualBaseSettings, 'virtual_youbot').module_ids == (17, 18, 19, 20)
    for node in ('observer', 'decision'):  # config/fdi.yaml applies to every node (/**)
        assert load_settings(FdiSettings, node, REPO / 'config' / 'fdi.yaml').family_thresholds == (5.0, 5.0, 5.0, 3.0)
    bridge = node_parameters(yaml.safe_load((REPO / 'config' / 'kinematics_bridge.yaml').read_text()),
                             'kinematics_bridge')
    assert set(bridge) == {'profile', 'max_wheel_speed', 'odom_frame', 'base_frame'}
    from youbot_fdi.app.incidents import IncidentSettings  # the decision node's black box
    assert load_settings(IncidentSettings, 'decision', REPO / 'config' / 'incidents.yaml') == IncidentSettings()


def test_imports_run_downward():
    """Every import runs downward: cli and bench -> nodes, fleet -> app (the only layer below them
    that opens recordings, configuration and output files) -> fdi, tmcm, structure, bag -> model
    and the top-level helpers (samples, topics, settings, naming, faults, errors), at module level
    or inside a function. The FDI core takes arrays: fdi never imports bag."""
    import ast
    adapters = ('cli', 'bench', 'nodes', 'fleet')
    above = {  # a layer may not import these
        'model': adapters + ('app', 'fdi', 'tmcm', 'structure', 'bag'),
        'bag': adapters + ('app', 'fdi', 'tmcm', 'structure'),
        'fdi': adapters + ('app', 'bag'), 'tmcm': adapters + ('app',),
        'structure': adapters + ('app',), 'app': adapters,
        'nodes': ('cli', 'bench', 'fleet'), 'fleet': ('cli', 'bench', 'nodes'),
    }
    offenders = []
    for path in sorted((REPO / 'youbot_fdi').rglob('*.py')):
        relative = path.relative_to(REPO / 'youbot_fdi').parts
        layer = relative[0] if len(relative) > 1 else 'helpers'
        forbidden = tuple(f'youbot_fdi.{name}' for name in above.get(
            layer, adapters + ('app', 'fdi', 'tmcm', 'structure', 'bag', 'model')))
        if layer in ('cli', 'bench'):
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            names = ([node.module or ''] if isinstance(node, ast.ImportFrom)
                     else [a.name for a in node.names] if isinstance(node, ast.Import) else [])
            offenders += [f'{"/".join(relative)}: {n}' for n in names if n.startswith(forbidden)]
    assert offenders == []


def node_entry_points():
    """The installed console scripts that start nodes (every one but the ``youbot-fdi`` CLI)."""
    from importlib.metadata import entry_points
    return sorted((point for point in entry_points(group='console_scripts')
                   if point.value.startswith('youbot_fdi.nodes.')), key=lambda point: point.name)


def test_every_node_executable_answers_help_without_starting_ros(capsys):
    """``ros2 run youbot_fdi <node> --help`` prints what the node does and how it is configured,
    and exits 0 without initialising ROS (before this, it started the node)."""
    import importlib
    import rclpy
    points = node_entry_points()
    assert {'driver_shim', 'decision', 'youbot_fdi_suite'} <= {point.name for point in points}
    for point in points:
        module = importlib.import_module(point.value.split(':')[0])
        assert point.load()([point.name, '--help']) == 0, point.name
        out = capsys.readouterr().out
        assert f'ros2 run youbot_fdi {point.name} [--ros-args' in out, point.name
        described = point.load() if module.__name__.endswith('composed') else module
        assert described.__doc__.strip().splitlines()[0] in out, point.name
        assert not rclpy.ok()
    # A composed executable describes each node it runs.
    suite = next(point for point in points if point.name == 'youbot_fdi_suite')
    suite.load()(['youbot_fdi_suite', '-h'])
    out = capsys.readouterr().out
    for name in ('``kinematics_bridge`` node', '``observer`` node', '``decision`` node'):
        assert name in out


def test_help_flag_after_ros_args_is_left_to_rclpy():
    from youbot_fdi.nodes.common import asks_for_help
    assert asks_for_help(['decision', '--help', '--ros-args', '-p', 'x:=1'])
    assert not asks_for_help(['decision', '--ros-args', '--help'])
    assert not asks_for_help(['decision'])


def test_installed_node_script_prints_help():
    script = Path(sys.executable).parent / 'decision'
    if not script.exists():
        pytest.skip('the package is not installed into this interpreter (make venv installs it)')
    result = subprocess.run([str(script), '--help'], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    assert '/youbot_fdi/faults' in result.stdout


@pytest.mark.parametrize('stop', [signal.SIGINT, signal.SIGTERM])
def test_a_node_stops_on_sigint_or_sigterm_with_exit_0(stop, tmp_path):
    """Our mains stop on SIGINT (Ctrl-C, the demo's stop) and SIGTERM (a supervisor's) by a flag
    the spin loop reads, not by rclpy's handlers, which shut the context down from another
    thread while a take may run (a RuntimeError traceback under load): exit 0, no traceback."""
    command = [sys.executable, '-m', 'youbot_fdi.nodes.decision']
    process = subprocess.Popen(command, stderr=subprocess.PIPE, stdout=subprocess.DEVNULL,
                               text=True, env={**os.environ, 'ROS_HOME': str(tmp_path)})
    try:
        log = []
        for line in process.stderr:  # the node logs where its incidents go once it is built
            log.append(line)
            if 'incidents:' in line:
                break
        process.send_signal(stop)
        log += process.stderr.readlines()
        assert process.wait(timeout=30) == 0, ''.join(log)
    finally:
        process.kill()
    assert 'Traceback' not in ''.join(log)
