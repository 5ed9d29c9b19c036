"""Run a fleet's recordings on Dask (dask.distributed): a local cluster of worker processes on
loopback by default, any running scheduler by address. One task per recording
(:func:`~youbot_fdi.fleet.analysis.analyse`); a recording already analysed in ``OUT`` is skipped
(resume); a recording that fails is a row with its error, never the end of the run."""
from dataclasses import dataclass
from pathlib import Path
import sys
import time

from youbot_fdi.errors import FdiError
from youbot_fdi.fleet.analysis import analyse, discover, load_rows, warm_up

LOOPBACK = '127.0.0.1'
INSTALL_HINT = 'pip install "youbot_fdi[fleet]" (or: pip install "dask[distributed]")'
PROGRESS_WIDTH = 30
SCHEDULER_TIMEOUT = '5s'  # to connect to a given scheduler


class FleetError(FdiError):
    """The fleet cannot run (no Dask, no recordings, a scheduler that does not answer)."""


@dataclass(frozen=True)
class FleetResult:
    """What a run did."""

    rows: list  # every recording's row (analysed now or before)
    analysed: int  # recordings analysed in this run
    skipped: int  # recordings already analysed (resume)
    trends: list  # youbot_fdi.fleet.trend.Trend
    csv: Path
    html: Path
    seconds: float  # wall time of the analysis (cluster start-up excluded)


def dask_client(workers, scheduler=None):
    """A ``dask.distributed.Client``: to ``scheduler`` (an address) or to a new local cluster of
    ``workers`` single-threaded processes on loopback; every worker has imported the pipeline."""
    try:
        from dask.distributed import Client, LocalCluster
    except ImportError as err:
        msg = f'youbot-fdi fleet needs Dask: {INSTALL_HINT}'
        raise FleetError(msg) from err
    if scheduler:
        try:
            return Client(scheduler, timeout=SCHEDULER_TIMEOUT)
        except (OSError, TimeoutError) as err:
            msg = f'no Dask scheduler answers at {scheduler}: {err}'
            raise FleetError(msg) from err
    cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, host=LOOPBACK,
                           dashboard_address=None)
    client = Client(cluster)
    client.run(warm_up)
    return client


def close_client(client):
    """Close ``client`` and the local cluster it started, if it started one."""
    cluster = client.cluster
    client.close()
    if cluster is not None:
        cluster.close()


def run_fleet(root, output, params_path, settings, client, progress=None):
    """Analyse every recording below ``root`` not yet in ``output``; write the CSV and the HTML
    report of all of them. ``progress(done, total)`` after each recording."""
    from youbot_fdi.fleet.report import CSV_NAME, write_csv, write_html
    from youbot_fdi.fleet.trend import friction_trends
    output = Path(output)
    output.mkdir(parents=True, exist_ok=True)
    recordings = discover(root)
    if not recordings:
        msg = f'{root}: no rosbag2 recording below it'
        raise FleetError(msg)
    done = load_rows(output)
    todo = [r for r in recordings if r.name not in done]
    started = time.perf_counter()
    if todo:
        from dask.distributed import as_completed
        futures = [client.submit(analyse, r, params_path, str(output), settings.fault_free_margin,
                                 key=f'youbot-fdi-{r.name}-{time.time_ns()}', pure=False)
                   for r in todo]
        for count, future in enumerate(as_completed(futures), 1):
            row = future.result()
            done[row['recording']] = row
            if progress is not None:
                progress(count, len(todo))
    seconds = time.perf_counter() - started
    rows = [done[r.name] for r in recordings if r.name in done]
    trends = friction_trends(rows, settings)
    csv_path = write_csv(rows, output / CSV_NAME)
    html_path = write_html(rows, trends, output, settings)
    return FleetResult(rows, len(todo), len(recordings) - len(todo), trends, csv_path, html_path,
                       seconds)


def progress_bar(done, total, stream=sys.stderr):
    """A one-line progress bar (redrawn in place)."""
    filled = int(PROGRESS_WIDTH * done / max(total, 1))
    print(f'\r[{"#" * filled:<{PROGRESS_WIDTH}}] {done}/{total} recordings', end='',
          file=stream, flush=True)
    if done == total:
        print(file=stream)
