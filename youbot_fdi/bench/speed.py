"""The project's benchmark: speed figures as ratios against baselines measured in the same run.

Each case times a piece of the product and a baseline that bounds what is achievable on this
machine, so the ratio means the same on a fast laptop and on the youBot's Atom. No test asserts a
time; this module is what ``youbot-fdi bench`` prints.
"""
from dataclasses import dataclass
import time
import uuid

import numpy as np

from youbot_fdi.faults import Level


@dataclass(frozen=True)
class BenchResult:
    """One benchmark line."""

    name: str
    value: float
    unit: str
    baseline_name: str
    baseline: float
    note: str = ''

    @property
    def ratio(self):
        """value / baseline."""
        return self.value / self.baseline if self.baseline else float('nan')


def _rate(function, min_time=0.5):
    """Calls per second of ``function`` over at least ``min_time`` seconds."""
    count, started = 0, time.perf_counter()
    while True:
        function()
        count += 1
        elapsed = time.perf_counter() - started
        if elapsed >= min_time:
            return count / elapsed


def bench_model(profile='youbot'):
    """Simulator steps per second vs the bare 8x8 matrix-vector products a step needs."""
    from youbot_fdi.model import BaseSimulator, ControlMode, load_model
    model = load_model(profile)
    simulator = BaseSimulator(model)
    setpoint = model.kinematics.inverse((0.3, 0.1, 0.2))
    a_d, b_d = simulator.plant.a_d, simulator.plant.b_d
    state, torque = np.zeros(8), np.ones(4)
    steps = _rate(lambda: simulator.step(setpoint, ControlMode.VELOCITY))
    bare = _rate(lambda: a_d @ state + b_d @ torque)
    return BenchResult('model: firmware-period steps', steps, 'steps/s', 'bare ZOH matvec', bare,
                       f'{steps / 1000:.0f}x real time at 1 kHz')


def bench_structure():
    """Structural analysis of each shipped model vs importing the toolbox that cross-checks it."""
    import subprocess
    import sys
    from youbot_fdi.structure.generate import resolve_model
    from youbot_fdi.structure.analysis import analyze
    from youbot_fdi.structure.report import placement_summary
    results = []
    probe = subprocess.run([sys.executable, '-c', 'import time; t = time.perf_counter(); '
                            'import faultdiagnosistoolbox; print(time.perf_counter() - t)'],
                           capture_output=True, text=True)
    toolbox_import = float(probe.stdout.strip()) if probe.returncode == 0 else float('nan')
    for name in ('seed', 'youbot'):
        model = resolve_model(name)
        started = time.perf_counter()
        placement_summary(analyze(model))
        elapsed = time.perf_counter() - started
        results.append(BenchResult(f'structure --model {name}', elapsed, 's',
                                   'faultdiagnosistoolbox import', toolbox_import,
                                   'target < 1 s'))
    return results


def bench_can(cycles=200):
    """Lockstep driver + virtual base cycles per second vs raw virtual-bus frame exchange.

    A cycle is 4 command frames, 12 status frames and 10 ms of simulated firmware (10 steps).
    The baseline moves the same 16 frames per cycle through python-can's virtual bus, bare.
    """
    import can
    from youbot_fdi.model import load_model
    from youbot_fdi.tmcm.lockstep import LockstepBase

    model = load_model('youbot')
    command = model.kinematics.to_driver(model.kinematics.inverse((0.3, 0.0, 0.0)))
    rig = LockstepBase(model)
    try:
        started = time.perf_counter()
        for _ in range(cycles):
            rig.step('velocity', command)
        lockstep = cycles / (time.perf_counter() - started)
        started = time.perf_counter()
        for _ in range(cycles):
            rig.base.advance(0.01)
        simulation_only = cycles / (time.perf_counter() - started)
    finally:
        rig.close()

    channel = f'bench-{uuid.uuid4()}'
    a = can.Bus(interface='virtual', channel=channel)
    b = can.Bus(interface='virtual', channel=channel)
    frame = can.Message(arbitration_id=0x211, data=bytes(8), is_extended_id=False)
    try:
        started = time.perf_counter()
        for _ in range(cycles):
            for _ in range(16):
                a.send(frame)
                b.recv(1.0)
        raw = cycles / (time.perf_counter() - started)
    finally:
        a.shutdown()
        b.shutdown()
    return [BenchResult('CAN: shim + virtual base, lockstep', lockstep, 'cycles/s',
                        'raw virtual-bus exchange of 16 frames', raw,
                        f'{lockstep * 0.01:.1f}x real time at 100 Hz cycles'),
            BenchResult('virtual base: 10 ms of firmware', simulation_only, 'cycles/s',
                        'raw virtual-bus exchange of 16 frames', raw)]


NODE_TARGET = 1.5  # each layout <= this x its relay arrangement, CPU and latency (issue 13)


def bench_nodes(seconds=5.0, progress=print):
    """Per layout of the FDI nodes: CPU share at 100 Hz and /joint_states -> decision latency,
    against as many bare relay nodes in the same arrangement (youbot_fdi.nodes.bench)."""
    try:
        from youbot_fdi.nodes.bench import bench_node_suite
    except ImportError as err:
        return [BenchResult(f'node suite (skipped: {err})', float('nan'), '', 'relay', float('nan'))]
    results = []
    for case, ((cpu, latency), (relay_cpu, relay_latency)) in bench_node_suite(seconds, progress).items():
        note = f'target <= {NODE_TARGET:g}x'
        results += [
            BenchResult(f'nodes {case}: CPU at 100 Hz', cpu * 100, '% core', 'relays', relay_cpu * 100, note),
            BenchResult(f'nodes {case}: latency p50', np.median(latency) * 1000, 'ms', 'relays p50',
                        np.median(relay_latency) * 1000, note),
            BenchResult(f'nodes {case}: latency p99', np.percentile(latency, 99) * 1000, 'ms',
                        'relays p99', np.percentile(relay_latency, 99) * 1000, note)]
    return results


INCIDENT_CPU_TARGET = 1.1  # the suite with its incident recorder <= this x without (issue 35)
INCIDENT_CALLBACK_TARGET_MS = 1.0  # the recorder's own callback, at most [ms] (issue 35)


INTERFERENCE_SECONDS = 40.0  # [s] of 100 Hz messages through the recorder in the probe below
INTERFERENCE_OPEN_EVERY = 3.0  # [s] between incidents in it


def _writer_interference(incidents):
    """The longest time [s] one step of a callback-like loop takes (hand a 100 Hz sample's three
    messages to the recorder, a little work) while the recorder's writer thread writes an
    incident every ``INTERFERENCE_OPEN_EVERY`` s (``incidents`` True) or never: the loop never
    sleeps, so it wants the interpreter lock whenever the writer holds it (the worst case for a
    callback), and the difference is the delay the writer adds. Receive times are simulated: it
    runs as fast as the machine allows."""
    import gc
    import tempfile
    from youbot_fdi.app.incidents import IncidentRecorder, IncidentSettings, RunContext
    data = bytes(300)  # about a /joint_states message
    freeze = {'wheels': {w: {'evidence': dict.fromkeys('toce', 0.1)} for w in ('fl', 'fr', 'bl', 'br')}}
    with tempfile.TemporaryDirectory() as tmp:
        recorder = IncidentRecorder(IncidentSettings(incident_dir=tmp), RunContext(),
                                    log=lambda _: None)
        gc.collect()
        gc.freeze()  # as the nodes do after start-up
        longest, period_ns = 0.0, 10_000_000
        opening = int(INTERFERENCE_OPEN_EVERY * 1e9 / period_ns)
        for k in range(int(INTERFERENCE_SECONDS * 100)):
            now = k * period_ns
            started = time.perf_counter()
            recorder.record_batch([('/joint_states', now, data), ('/wheel_commands', now, data),
                                   ('/cmd_vel', now, data)])
            if incidents and k >= 1000 and k % opening == 0:
                recorder.open({'wheel': 'wheel_joint_fl', 'fault': 'stuck', 'level': 'ERROR'}, now,
                              freeze)
            sum(range(200))  # a callback's own work
            longest = max(longest, time.perf_counter() - started)
        recorder.flush()
        recorder.close()
        gc.unfreeze()
    return longest


def bench_incidents(seconds=5.0, progress=print):
    """The incident recorder's cost in the composed suite at 100 Hz, against the suite without
    it: with no alarm (its ring buffer only: what a robot pays nearly always) and with an
    incident opened every few seconds (far more often than a robot should alarm); the longest
    time the recorder's own callback takes (youbot_fdi.nodes.bench.bench_incident_recorder)."""
    try:
        from youbot_fdi.nodes.bench import bench_incident_recorder, INCIDENT_PERIOD, INCIDENT_ROUNDS
    except ImportError as err:
        return [BenchResult(f'incident recorder (skipped: {err})', float('nan'), '', 'none', float('nan'))]
    progress('  incidents: how long the writer thread can hold a callback up')
    interference = [BenchResult('incidents: longest callback step, writer busy',
                                _writer_interference(True) * 1000, 'ms', 'writer idle',
                                _writer_interference(False) * 1000,
                                f'target <= {INCIDENT_CALLBACK_TARGET_MS:g} ms; a loop that never '
                                f'sleeps, an incident every {INTERFERENCE_OPEN_EVERY:g} s')]
    runs = bench_incident_recorder(seconds, progress)
    cpu, latency = runs['without'][:2]
    results = []
    for case, label in (('no alarm', 'no alarm'),
                        ('alarms', f'an incident every {INCIDENT_PERIOD:g} s')):
        share, latency_on, taking, written, writer_cpu = runs[case]
        # The recorder's own work, timed where it runs (its take callback, its writer thread):
        # the whole process's CPU varies by +-15 % from run to run through the middleware's
        # threads, far more than the recorder adds.
        own = (taking.sum() + writer_cpu) / (seconds * INCIDENT_ROUNDS)
        note = f'{written} incidents written'
        results += [
            BenchResult(f'incidents, {label}: recorder CPU', own * 100, '% core', 'suite without',
                        cpu * 100, f'target <= {INCIDENT_CPU_TARGET - 1:.0%} of it; {note}'),
            BenchResult(f'incidents, {label}: suite CPU', share * 100, '% core', 'suite without',
                        cpu * 100, f'whole process, median of {INCIDENT_ROUNDS} rounds'),
            BenchResult(f'incidents, {label}: latency p99', np.percentile(latency_on, 99) * 1000,
                        'ms', 'suite without', np.percentile(latency, 99) * 1000, note),
            BenchResult(f'incidents, {label}: recorder callback max', taking.max() * 1000, 'ms',
                        'target', INCIDENT_CALLBACK_TARGET_MS,
                        f'p99 {np.percentile(taking, 99) * 1e6:.0f} us over {len(taking)} takes')]
    return interference + results


REPLAY_DRIVE = 120.0  # [s] of aggressive driving per replay case, 100 Hz (issue 34 times identify on 120 s)
REPLAY_REPEATS = 3  # best of
REPLAY_TARGET = 1.5  # replay <= this x decode-only (issue 14)
IDENTIFY_TARGET = 10.0  # identify <= this x the replay of its recording (issue 34)
IDENTIFY_REPEATS = 2  # best of, for identify (its first call in a process imports scipy.optimize)
START_REPEATS = 5  # best of, for the command line's start time
START_TARGET = 2.0  # `youbot-fdi --help` <= this x `python -c "import numpy"`
REPLAY_WHEELS = ('wheel_joint_fl', 'wheel_joint_br')  # the faulty wheels of the fault cases


def _best_time(function, repeats=REPLAY_REPEATS):
    times = []
    for _ in range(repeats):
        started = time.perf_counter()
        function()
        times.append(time.perf_counter() - started)
    return min(times)


def _replay_recordings(workdir, progress, seconds):
    """The replay cases' recordings of one plant unlike the default profile (the fault
    benchmark's first random variation), and its parameter file identified from the fault-free
    one: ({case: (recording, parameter file or None)}, the time ``identify`` took [s])."""
    from youbot_fdi.bench.calibration import calibrate
    from youbot_fdi.bench.simulated import _chain, make_variations, random_script, true_model
    from youbot_fdi.model import load_model
    from youbot_fdi.tmcm.recordings import record_drive
    variation = make_variations(2)[1]
    prior = load_model('youbot')
    plant, script = true_model(prior, variation), random_script(variation.index, seconds)
    first, second = REPLAY_WHEELS
    faults = {'fault-free': {}, 'fault-free, mcap': {'storage': 'mcap'},
              'a fault at 10 %': {'fault': 'torque_loss', 'wheel': first,
                                  'fault_time': 0.1 * seconds},
              'faults on two wheels': {'fault': 'friction', 'wheel': first,
                                       'fault_time': 0.1 * seconds,
                                       'more_faults': [('stuck', second, 0.5 * seconds)]}}
    paths = {}
    for name, fault in faults.items():
        progress(f'  recording {seconds:g} s: {name}')
        paths[name] = record_drive(workdir / name.replace(' ', '_').replace(',', '').replace('%', 'pc'),
                                   plant, script, **fault, **_chain(variation)).path
    progress('  identifying the plant from the fault-free recording')
    files = []
    identified = _best_time(lambda: files.append(calibrate(
        paths['fault-free'], prior, workdir / f'params{len(files)}')[0]['learned']), IDENTIFY_REPEATS)
    cases = {name: (path, files[0]) for name, path in paths.items()}
    cases['fault-free, no --params'] = (paths['fault-free'], None)
    return cases, identified


#: ``youbot-fdi`` with the arguments after ``-c`` (its start and imports, as a user's shell runs it)
COMMAND_LINE = ('import sys; from youbot_fdi.cli.main import main; sys.argv[0] = "youbot-fdi"; '
                'sys.exit(main(sys.argv[1:]))')


def _fresh_interpreter(code, *argv, quiet=False):
    """A callable running Python ``code`` with the arguments ``argv`` in a fresh interpreter
    (its output discarded, its errors too if ``quiet``); it raises if the run fails."""
    import subprocess
    import sys
    return lambda: subprocess.run([sys.executable, '-c', code, *map(str, argv)], check=True,
                                  stdout=subprocess.DEVNULL,
                                  stderr=subprocess.DEVNULL if quiet else None)


def _command_line_times(path, params, workdir):
    """``youbot-fdi identify`` and ``youbot-fdi replay --params`` of one recording as a user runs
    them, each in a fresh interpreter (its start and imports included), best of
    ``IDENTIFY_REPEATS`` each: (identify [s], replay [s])."""
    identify = _best_time(_fresh_interpreter(COMMAND_LINE, 'identify', '--output',
                                             workdir / 'command_line', path, quiet=True),
                          IDENTIFY_REPEATS)
    replay = _best_time(_fresh_interpreter(COMMAND_LINE, 'replay', '--params', params, '--events',
                                           workdir / 'events.jsonl', path, quiet=True),
                        IDENTIFY_REPEATS)
    return identify, replay


def bench_replay(progress=print, seconds=REPLAY_DRIVE):
    """Replay (the batched FDI) against merely decoding the same recording with rosbags, for
    every case of issue 14 (identified or not, faults early and on two wheels, both storage
    formats), and the live path (one sample at a time); best of ``REPLAY_REPEATS`` each."""
    import tempfile
    from pathlib import Path
    from youbot_fdi.bag.reader import RecordingReader
    from dataclasses import replace
    from youbot_fdi.app.config import build_pipeline, residual_data_for
    from youbot_fdi.app.replay import replay_recording
    from youbot_fdi.fdi.pipeline import FdiPipeline
    results = []
    with tempfile.TemporaryDirectory(prefix='youbot_fdi_bench_') as tmp:
        cases, identified = _replay_recordings(Path(tmp), progress, seconds)
        for name, (path, params) in cases.items():
            model, _ = build_pipeline(params)

            def decode():
                with RecordingReader(path, model.wheel_names) as reader:
                    reader.decode_only()

            events = []

            def replay():
                events.clear()
                replay_recording(build_pipeline(params)[1], path, on_event=events.append)

            decoded, replayed = _best_time(decode), _best_time(replay)
            alarms = sorted({e.wheel for e in events if e.level == Level.ERROR}, key=str)
            with RecordingReader(path, model.wheel_names) as reader:
                messages = reader.message_count
            results.append(BenchResult(f'replay: {name}', replayed, 's', 'rosbags decode-only',
                                       decoded, f'{messages} messages, alarms on '
                                       f'{", ".join(map(str, alarms)) or "none"}; '
                                       f'target <= {REPLAY_TARGET:g}x'))
        path, params = cases['fault-free']
        model, _ = build_pipeline(params)
        replayed = results[0].value
        results.append(BenchResult(f'identify: the {seconds:g} s fault-free recording', identified,
                                   's', 'replay of it', replayed,
                                   f'in this process, best of {IDENTIFY_REPEATS} (the replay: of '
                                   f'{REPLAY_REPEATS}); target <= {IDENTIFY_TARGET:g}x (issue 34)'))
        progress('  identify and replay at the command line')
        identify_command, replay_command = _command_line_times(path, params, Path(tmp))
        results.append(BenchResult('identify: the same, at the command line', identify_command, 's',
                                   'youbot-fdi replay of it', replay_command,
                                   'as a user runs them: a fresh interpreter each, best of '
                                   f'{IDENTIFY_REPEATS}; target <= {IDENTIFY_TARGET:g}x (issue 34)'))

        def live(physics_only=False):
            _, pipeline = build_pipeline(params)
            if physics_only:
                settings = replace(pipeline.settings, physics_only=True)
                pipeline = FdiPipeline(model, settings, residual_data_for(model, settings))
            generator, decision = pipeline.generator, pipeline.decision
            with RecordingReader(path, model.wheel_names) as reader:
                for sample in reader.samples():
                    if hasattr(sample, 'kind'):
                        generator.command(sample)
                    else:
                        frame = generator.update(sample)
                        if frame is not None:
                            decision.update(frame)

        with RecordingReader(path, model.wheel_names) as reader:
            samples = sum(c.msgcount for c in reader.connections if c.topic == reader.joint_topic)
        per_sample = 1e6 / samples  # [µs/s] per /joint_states sample (with its share of commands)
        learned = _best_time(live) * per_sample
        results.append(BenchResult('live path: one sample at a time', learned,
                                   'us/sample', 'replay per sample', replayed * per_sample,
                                   'generator + decision, as the nodes call them'))
        results.append(BenchResult('live path: learned variant', learned, 'us/sample',
                                   'the same, physics only', _best_time(lambda: live(True)) * per_sample,
                                   'what the learned correction adds to the nodes (issue 12)'))
    return results


def bench_start():
    """``youbot-fdi --help`` (a fresh interpreter) against ``python -c "import numpy"``."""
    command = _best_time(_fresh_interpreter(COMMAND_LINE, '--help'), START_REPEATS)
    numpy = _best_time(_fresh_interpreter('import numpy'), START_REPEATS)
    return BenchResult('command line: youbot-fdi --help', command, 's', 'python -c "import numpy"',
                       numpy, f'a fresh interpreter each; target <= {START_TARGET:g}x')


LEARNED_TARGET_US = 20.0  # [µs] the learned correction per sample, all wheels (issue 12)


def bench_learned():
    """The learned torque correction evaluated for one sample of four wheels (what the live
    observer adds per sample: the inertial feature's current gate, both parts within the
    calibrated range, the wheels outside it), against one numpy tanh of four values."""
    from youbot_fdi.fdi.learned import FEATURES, inertial_feature, TorqueCorrection
    rng = np.random.default_rng(0)
    ranges = np.tile([-1.0, 1.0], (4, 1))
    correction = TorqueCorrection(rng.normal(size=(4, FEATURES)), np.full(4, 0.1), 0.05, np.full(4, 0.1),
                                  ranges, 10.0 * ranges, 0.1)
    speed, acceleration, torque, before = rng.normal(size=(4, 1, 4))  # a batch of one sample
    value = 1e6 / _rate(lambda: correction.applied(
        speed, inertial_feature(acceleration, torque, before, 1.0)))
    baseline = 1e6 / _rate(lambda: np.tanh(speed))
    return BenchResult('learned correction: one sample, 4 wheels', value, 'us', 'np.tanh of 4 values',
                       baseline, f'target <= {LEARNED_TARGET_US:g} us')


FUZZ_FRAMES = 100_000  # generated CAN frames per benchmark run (issue 17)


def bench_fuzz(progress=print, frames=FUZZ_FRAMES):
    """The CAN fuzz (every decoding entry point, see :mod:`youbot_fdi.bench.fuzz`): frames per
    second through all of them, against decoding one well-formed TMCL request."""
    from youbot_fdi.bench.fuzz import fuzz_frames
    from youbot_fdi.tmcm.tmcl import decode_request_can, TmclRequest
    can_id, payload = TmclRequest(0x11, 1, 0, 0, 5).to_can()
    baseline = _rate(lambda: decode_request_can(can_id, payload))
    started = time.perf_counter()
    report = fuzz_frames(frames, progress=progress)
    rate = report.frames / (time.perf_counter() - started)
    for violation in report.violations[:5]:
        progress(f'  fuzz violation: {violation}')
    return BenchResult('CAN fuzz: frames through every decoder', rate, 'frames/s',
                       'one TMCL request decoded', baseline, report.describe())


def run_all(progress=print):
    """Run every case; returns the results."""
    from youbot_fdi.bench.fleet import bench_fleet
    results = []
    for label, case in (('model', bench_model), ('structure', bench_structure), ('can', bench_can),
                        ('learned', bench_learned),
                        ('start', bench_start), ('fuzz', lambda: bench_fuzz(progress)),
                        ('replay', lambda: bench_replay(progress)),
                        ('fleet', lambda: bench_fleet(progress)),
                        ('nodes', lambda: bench_nodes(progress=progress)),
                        ('incidents', lambda: bench_incidents(progress=progress))):
        progress(f'running {label} ...')
        outcome = case()
        results.extend(outcome if isinstance(outcome, list) else [outcome])
    return results


def format_results(results):
    """A text table."""
    lines = [f'{"case":<40}{"value":>14} {"unit":<9}{"baseline (same run)":>42}{"ratio":>9}  note']
    for r in results:
        lines.append(f'{r.name:<40}{r.value:>14.4g} {r.unit:<9}'
                     f'{r.baseline_name + " " + format(r.baseline, ".4g"):>42}{r.ratio:>9.3g}  {r.note}')
    return '\n'.join(lines)
