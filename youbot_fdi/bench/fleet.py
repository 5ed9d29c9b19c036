"""The fleet benchmark: throughput of ``youbot-fdi fleet`` (Dask, 1 and 2 local workers) against a
serial loop doing the same per-recording work (replay + friction identification) in one process,
on the same recordings, in the same run. Cluster start-up is reported apart."""
import tempfile
import time
from pathlib import Path

FLEET_RECORDINGS = 8
FLEET_DRIVE = 30.0  # [s] per recording
SPEEDUP_TARGET = 1.6  # with 2 workers on 2 cores (issue 16)


def bench_fleet(progress=print, recordings=FLEET_RECORDINGS, seconds=FLEET_DRIVE):
    """BenchResults: 1 and 2 workers against the serial loop [recordings/s], and start-up."""
    from youbot_fdi.bench.speed import BenchResult
    try:
        import distributed  # noqa: F401 - only to say it is missing
    except ImportError:
        return [BenchResult('fleet (skipped: pip install "youbot_fdi[fleet]")', float('nan'), '',
                            'serial loop', float('nan'))]
    from youbot_fdi.bench.simulated import random_script
    from youbot_fdi.fleet.analysis import analyse, discover
    from youbot_fdi.fleet.runner import dask_client, run_fleet
    from youbot_fdi.fleet.settings import FleetSettings
    from youbot_fdi.model import load_model
    from youbot_fdi.tmcm.recordings import record_drive
    model, settings = load_model('youbot'), FleetSettings()
    results = []
    with tempfile.TemporaryDirectory(prefix='youbot_fdi_fleet_') as tmp:
        root = Path(tmp) / 'fleet'
        progress(f'  recording {recordings} drives of {seconds:g} s')
        for k in range(recordings):
            record_drive(root / f'robot_{k % 2}' / f'run{k}', model, random_script(k, seconds))
        found = discover(root)
        started = time.perf_counter()
        for recording in found:
            analyse(recording, None, str(Path(tmp) / 'serial'), settings.fault_free_margin)
        serial = len(found) / (time.perf_counter() - started)
        for workers in (1, 2):
            progress(f'  fleet with {workers} worker(s)')
            started = time.perf_counter()
            client = dask_client(workers)
            startup = time.perf_counter() - started
            try:
                result = run_fleet(root, Path(tmp) / f'fleet{workers}', None, settings, client)
            finally:
                cluster = client.cluster
                client.close()
                cluster.close()
            note = (f'{len(found)} recordings of {seconds:g} s; cluster start-up {startup:.1f} s apart'
                    + (f'; target >= {SPEEDUP_TARGET:g}x' if workers == 2 else ''))
            results.append(BenchResult(f'fleet: {workers} worker(s), throughput',
                                       len(found) / result.seconds, 'rec/s',
                                       'serial loop, same work', serial, note))
    return results
