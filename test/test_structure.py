"""Structural analysis: the report's Table 4.4, the corrected youBot model, and the toolbox cross-check."""
import json
from pathlib import Path

import numpy as np
import pytest

from youbot_fdi.cli.main import main
from youbot_fdi.structure.generate import resolve_model
from youbot_fdi.config_paths import config_dir
from youbot_fdi.errors import ConfigError, ModelError
from youbot_fdi.structure import analyze, Equation, sensor_placement, StructuralModel
from youbot_fdi.structure.analysis import find_msos, overdetermined_part
from youbot_fdi.structure.report import reference_check, residual_file_text, to_dict

pytestmark = pytest.mark.fast  # `make check`: the unit tests of the core, under a minute

# The report's Table 4.4, copied from the report.
TABLE_4_4 = dict(zip([f'c{k}' for k in range(1, 17)], 'n i n i n i n i d d d d d d d d'.split()))
WHEELS = ('fl', 'fr', 'bl', 'br')


@pytest.fixture(scope='module')
def seed():
    return analyze(resolve_model('seed'))


@pytest.fixture(scope='module')
def youbot():
    return analyze(resolve_model('youbot'))


def test_seed_reproduces_table_4_4_and_its_mso_sets(seed):
    assert seed.label_map() == TABLE_4_4
    msos = [seed.equation_names(m) for m in seed.msos]
    assert msos == [['c2'], ['c4'], ['c6'], ['c8'], ['c9', 'c10'], ['c11', 'c12'],
                    ['c13', 'c14'], ['c15', 'c16']]
    assert seed.redundancy == 8


def test_seed_findings_name_the_reports_inconsistencies(seed):
    findings = {f['item']: f for f in reference_check(seed)}
    assert findings['Table 4.4 (detectability/isolability)']['ok']
    assert findings['the printed matching']['ok']
    signature = findings['the printed signature matrix']
    assert not signature['ok']
    for residual in ('r5', 'r6', 'r7'):
        assert residual in signature['detail']
    assert 'r8' not in signature['detail']  # its last row happens to be right
    assert not findings["the text's list of undetectable constraints"]['ok']


def test_corrected_youbot_model_isolates_wheels_but_not_actuator_from_friction(youbot):
    labels = youbot.label_map()
    for w in WHEELS:
        assert labels[f'actuator_{w}'] == 'd' and labels[f'friction_{w}'] == 'd'
        assert labels[f'velocity_sensor_{w}'] == 'i'
    classes = [sorted(youbot.model.fault_names[i] for i in c) for c in youbot.classes if len(c) > 1]
    assert classes == [[f'actuator_{w}', f'friction_{w}'] for w in WHEELS]
    assert youbot.redundancy == 4
    assert len(youbot.msos) == 144


def test_runtime_residuals_are_msos_with_the_expected_signatures(youbot):
    residuals = youbot.residuals
    assert residuals.declared and residuals.complete
    faults = youbot.model.fault_names
    signature = {name: {f for f, on in zip(faults, row) if on}
                 for name, row in zip(residuals.names, residuals.signatures)}
    sensors = {f'velocity_sensor_{w}' for w in WHEELS}
    for w in WHEELS:
        assert signature[f'torque_{w}'] == {f'actuator_{w}', f'friction_{w}'} | sensors
        assert signature[f'observer_{w}'] == (
            {f'{k}_{v}' for k in ('actuator', 'friction') for v in WHEELS}
            | {f'velocity_sensor_{w}'})


def test_only_wheel_torque_sensors_close_the_gap():
    model = resolve_model('youbot')
    results = {r['groups']: r['non_isolable_pairs']
               for r in sensor_placement(model, model.reference['sensor_candidates'])}
    assert results[()] == 8
    for groups, pairs in results.items():
        assert (pairs == 0) == ('wheel_torque' in groups)


def test_shipped_residual_file_is_up_to_date(youbot):
    shipped = (config_dir() / 'residuals' / 'youbot.yaml').read_text()
    assert shipped == residual_file_text(youbot), (
        'regenerate with: youbot-fdi structure --model youbot '
        '--write-residuals config/residuals/youbot.yaml')


def test_three_wheel_base_is_generated_from_its_geometry():
    analysis = analyze(resolve_model('omni3_example'))
    assert analysis.redundancy == 3
    assert analysis.residuals.complete
    assert set(analysis.label_map().values()) == {'d', 'i'}


def test_overdetermined_part_and_msos_on_a_hand_example():
    # x measured by three sensors: e1: y1 = x, e2: y2 = x, e3: y3 = x, e4: z = w (just determined).
    incidence = np.array([[1, 0], [1, 0], [1, 0], [0, 1]], dtype=bool)
    assert overdetermined_part(incidence, range(4)) == (0, 1, 2)
    assert find_msos(incidence) == [(0, 1), (0, 2), (1, 2)]
    assert overdetermined_part(incidence, [3]) == ()


def test_bad_models_are_refused():
    with pytest.raises(ConfigError, match='undeclared'):
        StructuralModel('m', (Equation('e1', ('x', 'q')),), ('x',), (), {})
    with pytest.raises(ConfigError, match='unknown equation'):
        StructuralModel('m', (Equation('e1', ('x',)),), ('x',), (), {'f': 'e9'})
    model = StructuralModel('m', (Equation('e1', ('x', 'y')), Equation('e2', ('x', 'z')),
                                  Equation('e3', ('w',))), ('x', 'w'), ('y', 'z'),
                            {'f1': 'e1'}, reference={'residuals': {'bad': ['e1', 'e3']}})
    with pytest.raises(ModelError, match='not an MSO'):
        analyze(model)
    with pytest.raises(ConfigError, match='unknown model'):
        resolve_model('no_such_model')


def test_json_output_has_the_contract_keys(capsys):
    assert main(['structure', '--model', 'seed', '--format', 'json']) == 0
    data = json.loads(capsys.readouterr().out)
    assert data['labels'] == TABLE_4_4
    assert ['c9', 'c10'] in data['mso'] and len(data['mso']) == 8
    assert main(['structure', '--model', 'youbot', '--format', 'json']) == 0
    data = json.loads(capsys.readouterr().out)
    assert set(data['labels']) == {f'{k}_{w}' for k in ('actuator', 'friction', 'velocity_sensor')
                                   for w in WHEELS}


def test_structure_graph_figure(tmp_path, capsys):
    figure = tmp_path / 'seed.png'
    assert main(['structure', '--model', 'seed', '--plot', str(figure)]) == 0
    assert figure.read_bytes()[:4] == b'\x89PNG' and figure.stat().st_size > 10_000
    out = capsys.readouterr().out
    assert 'Table 4.4' in out and 'reproduced exactly' in out


# --- cross-check against Frisk's Fault Diagnosis Toolbox (optional extra "structure") ---

def toolbox_model(model):
    fdt = pytest.importorskip('faultdiagnosistoolbox')
    fault_of = {}
    for fault, equation in model.faults.items():
        fault_of.setdefault(equation, []).append(fault)
    rels = [list(e.variables) + fault_of.get(e.name, []) for e in model.equations]
    definition = {'type': 'VarStruc', 'x': list(model.unknown), 'f': list(model.faults),
                  'z': list(model.known), 'rels': rels}
    return fdt.DiagnosisModel(definition, name=model.name)


@pytest.mark.parametrize('name', ['seed', 'youbot', 'omni3_example'])
def test_cross_check_with_faultdiagnosistoolbox(name):
    model = resolve_model(name)
    ours = analyze(model)
    reference = toolbox_model(model)
    assert sorted(tuple(sorted(int(e) for e in m)) for m in reference.MSO()) == sorted(ours.msos)
    toolbox_not_isolable = np.asarray(reference.IsolabilityAnalysis(), dtype=bool)
    np.testing.assert_array_equal(toolbox_not_isolable, ours.not_isolable)
    detectable, _ = reference.DetectabilityAnalysis()
    assert set(detectable) == {f for f, d in zip(model.fault_names, ours.detectable) if d}


def test_report_dict_is_json_serialisable(youbot):
    json.dumps(to_dict(youbot))
    assert Path(config_dir() / 'structure' / 'seed.yaml').is_file()
