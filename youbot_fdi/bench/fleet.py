"""The fleet benchmark: throughput of ``youbot-fdi fleet`` (Dask, 1 and 2 local workers) against a
serial loop doing the same per-recording work (replay + friction identification) in one process,
on the same recordings, in the same run. Cluster start-up is reported apart."""
from pathlib import Path
import shutil
import tempfile
import time

FLEET_RECORDINGS = 8  # copies of one recording (the work per recording is what is timed)
FLEET_DRIVE = 300.0  # [s] per recording: a fleet's recordings are minutes to hours long
SPEEDUP_TARGET = 1.6  # with 2 workers on 2 cores (issue 16)


def bench_fleet(progress=print, recordings=FLEET_RECORDINGS, seconds=FLEET_DRIVE):
    """BenchResults: 1 and 2 workers against the serial loop [recordings/s]; cluster start-up
    (worker processes importing the pipeline) is reported apart."""
    from youbot_fdi.bench.speed import BenchResult
    try:
        import distributed  # noqa: F401 - only to say it is missing
    except ImportError:
        return [BenchResult('fleet (skipped: pip install "youbot_fdi[fleet]")', float('nan'), '',
                            'serial loop', float('nan'))]
    from youbot_fdi.bench.simulated import random_script
    from youbot_fdi.fleet.analysis import analyse, discover, warm_up
    from youbot_fdi.fleet.runner import close_client, dask_client, run_fleet
    from youbot_fdi.fleet.settings import FleetSettings
    from youbot_fdi.model import load_model
    from youbot_fdi.tmcm.recordings import record_drive
    model, settings = load_model('youbot'), FleetSettings()
    results = []
    with tempfile.TemporaryDirectory(prefix='youbot_fdi_fleet_') as tmp:
        root = Path(tmp) / 'fleet'
        progress(f'  recording a drive of {seconds:g} s, {recordings} copies')
        first = record_drive(Path(tmp) / 'drive', model, random_script(0, seconds)).path
        for k in range(recordings):
            shutil.copytree(first, root / f'robot_{k % 2}' / f'run{k}')
        found = discover(root)
        warm_up()  # as every worker does at cluster start
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
                close_client(client)
            note = (f'{len(found)} recordings of {seconds:g} s; cluster start-up {startup:.1f} s apart'
                    + (f'; target >= {SPEEDUP_TARGET:g}x' if workers == 2 else ''))
            results.append(BenchResult(f'fleet: {workers} worker(s), throughput',
                                       len(found) / result.seconds, 'rec/s',
                                       'serial loop, same work', serial, note))
    return results
