"""The project's benchmark: speed figures as ratios against baselines measured in the same run.

Each case times a piece of the product and a baseline that bounds what is achievable on this
machine, so the ratio means the same on a fast laptop and on the youBot's Atom. No test asserts a
time; this module is what ``youbot-fdi bench`` prints.
"""
from dataclasses import dataclass
import time
import uuid

import numpy as np


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


def bench_nodes(seconds=5.0):
    """CPU share of the FDI node suite at 100 Hz and its latency, against a bare relay node."""
    try:
        from youbot_fdi.nodes.bench import bench_node_suite
    except ImportError as err:
        return [BenchResult(f'node suite (skipped: {err})', float('nan'), '', 'relay', float('nan'))]
    suite, relay, suite_latency, relay_latency = bench_node_suite(seconds)
    return [BenchResult('nodes: bridge+observer+decision CPU at 100 Hz', suite * 100, '% core',
                        'bare JointState relay', relay * 100),
            BenchResult('nodes: /joint_states -> decision, p50', np.median(suite_latency) * 1000, 'ms',
                        'relay p50', np.median(relay_latency) * 1000),
            BenchResult('nodes: /joint_states -> decision, p99', np.percentile(suite_latency, 99) * 1000,
                        'ms', 'relay p99', np.percentile(relay_latency, 99) * 1000)]


REPLAY_DRIVE = 30.0  # [s] of the demo script recorded for the replay case
REPLAY_REPEATS = 3  # best of


def bench_replay(seconds=REPLAY_DRIVE):
    """Replay (the batched FDI) and the live path (one sample at a time) against merely decoding
    the same recording with rosbags; best of ``REPLAY_REPEATS`` each."""
    import tempfile
    from pathlib import Path
    from youbot_fdi.bag.reader import RecordingReader
    from youbot_fdi.fdi.pipeline import build_pipeline
    from youbot_fdi.model import load_model
    from youbot_fdi.model.scenario import load_script
    from youbot_fdi.tmcm.recordings import record_drive
    model = load_model('youbot')
    with tempfile.TemporaryDirectory(prefix='youbot_fdi_bench_') as tmp:
        path = record_drive(Path(tmp) / 'drive', model, load_script(duration=seconds)[1]).path

        def decode():
            with RecordingReader(path, model.wheel_names) as reader:
                reader.decode_only()

        def replay():
            build_pipeline()[1].replay(path)

        def live():
            _, pipeline = build_pipeline()
            generator, decision = pipeline.generator, pipeline.decision
            with RecordingReader(path, model.wheel_names) as reader:
                for sample in reader.samples():
                    if hasattr(sample, 'kind'):
                        generator.command(sample)
                    else:
                        frame = generator.update(sample)
                        if frame is not None:
                            decision.update(frame)

        best = {}
        for name, function in (('decode', decode), ('replay', replay), ('live', live)):
            times = []
            for _ in range(REPLAY_REPEATS):
                started = time.perf_counter()
                function()
                times.append(time.perf_counter() - started)
            best[name] = min(times)
        with RecordingReader(path, model.wheel_names) as reader:
            messages = reader.message_count
            samples = sum(c.msgcount for c in reader.connections if c.topic == reader.joint_topic)
    per_sample = 1e6 / samples  # [µs/s] per /joint_states sample (with its share of commands)
    return [BenchResult('replay: a recording, batched', best['replay'], 's',
                        'rosbags decode-only', best['decode'],
                        f'{messages} messages; target <= 1.5x'),
            BenchResult('live path: one sample at a time', best['live'] * per_sample, 'us/sample',
                        'replay per sample', best['replay'] * per_sample,
                        'generator + decision, as the nodes call them')]


def run_all(progress=print):
    """Run every case; returns the results."""
    results = []
    for label, case in (('model', bench_model), ('structure', bench_structure), ('can', bench_can),
                        ('replay', bench_replay), ('nodes', bench_nodes)):
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
