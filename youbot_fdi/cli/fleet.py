"""``youbot-fdi fleet``: every recording of a fleet on a Dask cluster; events, a CSV, an HTML
report with the friction trend per wheel."""
from pathlib import Path

from youbot_fdi.cli.status import ERROR

NAME = 'fleet'
DEFAULT_WORKERS = 2


def add_parser(subparsers):
    parser = subparsers.add_parser(
        NAME, help='analyse a fleet\'s recordings on Dask: events, CSV, HTML report, friction trends',
        description='Replay every rosbag2 recording below ROOT (sqlite3 and mcap) with the pipeline '
                    'of `replay`, one Dask task each (a local cluster of --workers processes, or '
                    '--scheduler ADDRESS), identify each recording\'s friction on its fault-free '
                    'stretch, and write OUT/events/<recording>.jsonl (as `replay` writes them), '
                    'OUT/recordings.csv and OUT/report.html (faults per robot over time, friction per '
                    'wheel per robot with a trend test, config/fleet.yaml). The robot is the first '
                    'folder below ROOT (ROOT/<robot>/...), the time the first joint state\'s stamp. '
                    'A recording that cannot be read is a row with its error; run again with the same '
                    'OUT to resume (recordings done are skipped). Needs the extra: '
                    'pip install "youbot_fdi[fleet]".')
    parser.add_argument('root', help='folder with the recordings (ROOT/<robot>/...)')
    parser.add_argument('--output', required=True, metavar='OUT', help='output folder')
    source = parser.add_mutually_exclusive_group()
    source.add_argument('--params', help='parameter file from `youbot-fdi identify` for every recording')
    source.add_argument('--identify-from', metavar='NOMINAL_BAG',
                        help='identify on this nominal recording first (writes OUT/params.yaml)')
    parser.add_argument('--profile', default='youbot', help='prior profile for --identify-from (default: youbot)')
    parser.add_argument('--workers', type=int, default=DEFAULT_WORKERS,
                        help=f'worker processes of the local cluster (default: {DEFAULT_WORKERS})')
    parser.add_argument('--scheduler', metavar='ADDRESS',
                        help='an existing Dask scheduler (tcp://host:8786) instead of a local cluster; '
                             'its workers must see ROOT and OUT at the same paths')
    parser.add_argument('--config', help='fleet settings YAML (default: config/fleet.yaml)')
    parser.set_defaults(run=run)


def run(args):
    import sys

    from youbot_fdi.fleet.runner import close_client, dask_client, progress_bar, run_fleet
    from youbot_fdi.fleet.settings import FleetSettings
    from youbot_fdi.settings import load_settings
    if args.workers < 1:
        print('youbot-fdi fleet: error: --workers must be at least 1', file=sys.stderr)
        return ERROR
    settings = load_settings(FleetSettings, 'fleet', args.config)
    output = Path(args.output)
    params = args.params
    if args.identify_from:
        params = str(_identify(args.identify_from, args.profile, output))
        print(f'identified on {args.identify_from}: {params}')
    client = dask_client(args.workers, args.scheduler)
    try:
        result = run_fleet(args.root, output, params, settings, client,
                           progress_bar if sys.stderr.isatty() else None)
    finally:
        close_client(client)
    errors = [r for r in result.rows if r['status'] == 'error']
    print(f'{len(result.rows)} recordings: {result.analysed} analysed in {result.seconds:.1f} s, '
          f'{result.skipped} done before (resumed), {len(errors)} unreadable')
    for row in errors:
        print(f'  {row["recording"]}: {row["error"]}')
    for trend in (t for t in result.trends if t.flagged):
        print(f'  friction rising: {trend.robot} {trend.wheel} {trend.rate:+.1%} per day '
              f'(p = {trend.p_value:.2g}, {trend.recordings} recordings)')
    print(f'table: {result.csv}\nreport: {result.html}\nevents: {output / "events"}')
    return 0


def _identify(bag, profile, output):
    from youbot_fdi.app.recordings import identify_recording
    from youbot_fdi.fdi.settings import FdiSettings
    from youbot_fdi.model.profile import load_model, save_profile
    from youbot_fdi.settings import load_settings
    result = identify_recording(bag, load_model(profile), load_settings(FdiSettings, 'fdi'))
    return save_profile(result.profile, output / 'params.yaml')
