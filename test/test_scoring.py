"""The fault benchmark's scoring (``bench/scoring.py``): what counts as a run with a false alarm."""
import math

import pytest

from youbot_fdi.bench.scoring import Case, score, summarise
from youbot_fdi.fdi.decision import FaultEvent

pytestmark = pytest.mark.fast  # `make check`


def alarm(stamp, wheel='wheel_joint_fl', fault='friction', level='ERROR'):
    return FaultEvent(stamp, level, wheel, fault, ('torque_fl',))


def healed(stamp, wheel='wheel_joint_fl'):
    return alarm(stamp, wheel, level='OK')


def test_every_judged_run_with_an_alarm_counts_even_when_runs_share_a_name():
    """A recording judged by two folds (or two runs of one plant named alike) is two runs."""
    quiet = Case('plant000/fault_free', 'unused', 60.0)
    results = [score(quiet, [alarm(10.0)]), score(quiet, [alarm(20.0), healed(30.0), alarm(40.0)]),
               score(quiet, [])]
    table = summarise('t', results)
    assert 'false alarms        3 in 180 s fault-free' in table
    assert 'runs with one: 2 of 3 (1 recordings)' in table


def test_a_false_alarm_is_an_episode_its_refined_type_is_no_second_one():
    """An episode's type refined within it (a second ERROR of the wheel before its OK) is one
    false alarm, two ERROR events; an ERROR after the OK is another; other wheels their own."""
    quiet = Case('plant000/fault_free', 'unused', 60.0)
    events = [alarm(10.0), alarm(10.5, fault='torque_loss'), healed(12.0), alarm(20.0),
              alarm(20.2, wheel='wheel_joint_br'), alarm(25.0, wheel='wheel_joint_br', fault='stuck')]
    result = score(quiet, events)
    assert result['false_alarms'] == 3 and result['false_alarm_events'] == 5
    table = summarise('t', [result])
    assert 'false alarms        3 in 60 s fault-free' in table
    assert '(5 ERROR events with the types refined)' in table


def test_an_alarm_after_the_onset_on_the_right_wheel_is_a_detection_not_a_false_alarm():
    case = Case('stuck', 'unused', 20.0, fault='stuck', wheel='wheel_joint_fl', onset=10.0,
                expected='stuck')
    result = score(case, [alarm(10.05, fault='stuck')])
    assert result['detected'] and result['isolated'] and result['named']
    assert result['false_alarms'] == 0 and result['delay'] == pytest.approx(0.05)
    assert result['fault_free_seconds'] == 10.0 and math.isinf(result['closest_events'])


def test_an_alarm_on_another_wheel_after_the_fault_is_its_isolation_not_a_false_alarm():
    """The rate of false alarms is of fault-free driving: an alarm on another wheel after the
    fault began (a runaway wheel drags the others) is counted apart, with the runs it came in;
    one before the fault is a false alarm."""
    case = Case('runaway', 'unused', 20.0, fault='runaway', wheel='wheel_joint_fl', onset=10.0)
    result = score(case, [alarm(4.0, wheel='wheel_joint_br'), healed(6.0, wheel='wheel_joint_br'),
                          alarm(10.1, fault='runaway'), alarm(12.0, wheel='wheel_joint_bl')])
    assert result['isolated'] and result['false_alarms'] == 1 and result['other_wheels'] == 1
    table = summarise('t', [result, score(case, [alarm(10.2, fault='runaway')])])
    assert 'false alarms        1 in 20 s fault-free' in table
    assert 'after a fault began (its isolation, not fault-free driving): 1 in 1 of 2 fault runs' in table


def test_a_randomized_fault_is_visible_once_its_wheel_is_driven():
    """The randomized suite's delays count from when a fault could be seen: a fault on a wheel
    told to stand (stuck, torque loss, friction, a frozen encoder) from the first command that
    drives it; on a driven wheel at once; a lost link at once; a runaway from its command's
    change."""
    import numpy as np
    from youbot_fdi.bench.plant import Drive, _visible
    times = np.array([0.0, 1.0, 2.0, 3.0])
    commands = np.zeros((4, 4))
    commands[3, 1] = 2.0  # wheel 1 driven from 3 s; wheel 0 from the start
    commands[:, 0] = 1.0

    def drive(fault, wheel):
        return Drive(np.array([0.0]), np.zeros((1, 3)), 4.0, fault=fault, wheel=wheel, fault_time=1.5)

    assert _visible(drive('stuck', 1), times, commands, False) == 3.0
    assert _visible(drive('encoder_freeze', 1), times, commands, False) == 3.0
    assert _visible(drive('torque_loss', 0), times, commands, False) == 1.5
    assert _visible(drive('comm_loss', 1), times, commands, False) == 1.5
    assert _visible(drive('runaway', 1), times, commands, False) == 3.0
    assert math.isnan(_visible(drive('runaway', 0), times, commands, False))
    assert math.isnan(_visible(drive(None, 0), times, commands, False))  # no fault


def test_a_randomized_fault_that_never_showed_is_no_detection_case():
    """The randomized summary leaves out faults whose wheel was never driven after them (onset
    NaN): their runs still count as fault-free driving, their delay does not spoil the median."""
    import numpy as np
    from youbot_fdi.bench import randomized
    from youbot_fdi.bench.plant import PlantParameters
    start = randomized.START_STAMP
    runs = [randomized.Run(0, 'fault', 'stuck', 'a', 20.0, 'stuck', 'w0', start + 9.0, start, start + 9.0),
            randomized.Run(0, 'fault', 'stuck', 'b', 20.0, 'stuck', 'w0', math.nan, start, start + 9.0)]
    alarm = FaultEvent(start + 9.05, 'ERROR', 'w0', 'stuck')
    scored = []
    for run in runs:
        case = Case(run.label, run.path, run.duration, run.fault, run.wheel, run.onset, None, run.start,
                    run.injected)
        scored.append((run, {**score(case, [alarm]), 'fault': run.label}))
    fields = {name: np.zeros(1) for name in PlantParameters.__dataclass_fields__}
    text = randomized.summarise(PlantParameters(**fields), scored)
    assert '1 fault runs left out of detection' in text
    assert 'median 50 ms' in text and 'nan' not in text
    assert 'driven fault-free: 0.0 h' in text  # 2 x 9 s before the injection


def test_the_randomized_default_magnitudes_are_also_reported_per_control_mode():
    """Two stuck wheels at the default magnitude, one on a velocity-mode plant found 50 ms after
    its onset and one on a current-mode plant never found: 1/2 in all, and per mode 1/1 (median
    50 ms) and 0/1 (no delay to state, so the mode's figures are NaN, not left out)."""
    import numpy as np
    from youbot_fdi.bench import randomized
    from youbot_fdi.bench.plant import PlantParameters
    start = randomized.START_STAMP
    runs = [randomized.Run(p, 'fault', 'stuck', f'r{p}', 20.0, 'stuck', 'w0', start + 9.0, start,
                           start + 9.0) for p in (0, 1)]
    events = {0: [FaultEvent(start + 9.05, 'ERROR', 'w0', 'stuck')], 1: []}
    scored = []
    for run in runs:
        case = Case(run.label, run.path, run.duration, run.fault, run.wheel, run.onset, None, run.start,
                    run.injected)
        scored.append((run, {**score(case, events[run.plant]), 'fault': run.label}))
    fields = {name: np.zeros(2) for name in PlantParameters.__dataclass_fields__}
    fields['current_mode'] = np.array([False, True])
    text = randomized.summarise(PlantParameters(**fields), scored)
    assert 'default magnitude: 1/2 detected and isolated; median 50 ms' in text
    assert 'velocity mode 1/1 detected and isolated; median 50 ms' in text
    assert 'current mode 0/1 detected and isolated; median nan ms' in text


def test_the_plants_coulomb_friction_in_the_fdis_terms_is_its_bearings_and_rolling_resistance():
    """A 20 kg plant with 0.03 N·m of bearing Coulomb friction, a rolling resistance of 0.5 mm
    (a quarter of the weight on each wheel: 0.0005 x 9.81 x 20 / 4 = 0.024525 N·m) and a torque
    constant 10 % above the datasheet's: the FDI, reading torque by the datasheet, sees
    (0.03 + 0.024525) / 1.1 = 0.049568 N·m; the mass 20 / 1.1. The identification table compares
    it: a found value 0.05 ± 0.001 is inside ± 2 sd (0.00043 off), one of 0.06 is not."""
    from dataclasses import replace

    import numpy as np
    from youbot_fdi.bench import randomized
    params = randomized.draw_plants(1, np.random.default_rng(0))
    params = replace(params, mass=np.array([20.0]), torque_scale=np.array([1.1]),
                     rolling_resistance=np.array([0.0005]), coulomb=np.full((1, 4), 0.03))
    truth = randomized.truth_of(params, 0)
    assert truth['coulomb_friction[2]'] == pytest.approx(0.054525 / 1.1, rel=1e-12)
    assert truth['mass'] == pytest.approx(20.0 / 1.1, rel=1e-12)
    found = {name: (value, 0.1 * value) for name, value in truth.items()}
    found['coulomb_friction[0]'] = (0.05, 0.001)
    found['coulomb_friction[1]'] = (0.06, 0.001)
    table = randomized.identification_table(params, {0: {'found': found, 'unexcited': []}})
    row = next(line for line in table.splitlines() if line.strip().startswith('coulomb_friction'))
    assert row.split()[3] == '75%'  # three of the four wheels inside


def test_the_identification_table_compares_the_fitted_pi_gains_and_states_no_interval_for_them():
    """The firmware's gains act on the current the FDI reads: the truth is the plant's own. A
    velocity-mode plant with k_p 1.5 and k_i 3 found at 3 and 3.3: |errors| 100 % and 10 %;
    ``identify`` states no deviation for them, so their interval column reads "-"."""
    import numpy as np
    from dataclasses import replace
    from youbot_fdi.bench import randomized
    params = randomized.draw_plants(1, np.random.default_rng(0))
    params = replace(params, kp=np.array([1.5]), ki=np.array([3.0]))
    truth = randomized.truth_of(params, 0)
    assert (truth['velocity_kp'], truth['velocity_ki']) == (1.5, 3.0)
    found = {'mass': (truth['mass'], 0.1), 'velocity_kp': (3.0, float('nan')),
             'velocity_ki': (3.3, float('nan'))}
    table = randomized.identification_table(params, {0: {'found': found, 'unexcited': []}})
    rows = {line.split()[0]: line.split() for line in table.splitlines()[2:]}
    assert rows['velocity_kp'][1:4] == ['100.0%', '100.0%', '-']
    assert rows['velocity_ki'][1:4] == ['10.0%', '10.0%', '-']
    assert rows['mass'][3] == '100%'


@pytest.mark.parametrize('alarms', [0, 1, 3, 41])
def test_the_false_alarm_rate_bound_is_the_poisson_rate_that_makes_the_count_unlikely(alarms):
    """The printed upper bound u of a rate after k alarms in T hours is the rate at which k or
    fewer come with probability 1 - 95 %: sum_{i<=k} e^-uT (uT)^i / i! = 0.05 (hand-derived:
    for k = 0, u = -ln(0.05) / T = 2.996 / T, so 0 alarms in 20 h bound the rate by 0.15/h)."""
    from youbot_fdi.bench.scoring import RATE_CONFIDENCE, rate_upper_bound
    hours = 20.0
    bound = rate_upper_bound(alarms, hours)
    mean = bound * hours
    at_most = sum(math.exp(-mean) * mean ** i / math.factorial(i) for i in range(alarms + 1))
    assert at_most == pytest.approx(1.0 - RATE_CONFIDENCE, rel=1e-9)
    assert bound > alarms / hours
    if alarms == 0:
        assert bound == pytest.approx(-math.log(0.05) / hours) and bound == pytest.approx(0.1498, abs=1e-4)
    assert math.isinf(rate_upper_bound(alarms, 0.0))
    with pytest.raises(ValueError, match='alarms >= 0'):
        rate_upper_bound(-1, hours)


def test_the_suite_table_prints_the_rate_with_its_upper_bound():
    """0 alarms in 180 s say the rate is under 60 per hour, not that it is 0."""
    quiet = Case('plant000/fault_free', 'unused', 60.0)
    table = summarise('t', [score(quiet, []) for _ in range(3)])
    assert 'false alarms        0 in 180 s fault-free = 0 per hour (at most 60 per hour, 95% one-sided)' in table


def test_the_simulated_suite_summary_counts_and_bounds_what_it_was_given():
    """The virtual base's summary (bench/simulated.py) from plain result dicts: detection and
    isolation counts over the observable faults, the median delay of the isolated ones, and the
    false-alarm rate with its bound."""
    from youbot_fdi.bench.simulated import summarise as simulated_summary

    def result(fault, delay, isolated=True, alarms=0):
        return dict(fault=fault, mode='velocity', observable=True, detected=True, isolated=isolated,
                    named=isolated, named_as=fault, delay=delay, fault_free_seconds=360.0,
                    false_alarms=alarms, replay_time=1.0, decode_time=0.8)

    results = [result('stuck', 0.1), result('stuck', 0.3), result('friction', 0.2, isolated=False),
               result(None, math.nan, alarms=1)]
    text = simulated_summary([], results)
    assert 'detection rate      3/3' in text and 'isolation accuracy  2/3 (wheel)' in text
    assert 'detection delay     median 200 ms' in text  # of the two isolated: 0.1 and 0.3 s
    assert 'false alarms        1 in 1440 s fault-free = 2.5 per hour (at most 12 per hour' in text
    assert 'replay speed        4.00 s replay vs 3.20 s decode-only = 1.25x decode' in text
