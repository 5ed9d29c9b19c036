"""``youbot-fdi incidents``: list the incident recordings of a folder, with a page for each."""
from pathlib import Path
import sys

from youbot_fdi.cli.status import ERROR

NAME = 'incidents'


def add_parser(subparsers):
    parser = subparsers.add_parser(
        NAME, help='list incident recordings (one per alarm episode) with a page for each',
        description='List the incidents the decision node kept (one recording per alarm episode: '
                    'the seconds around the alarm, its freeze-frame and parameters): time, wheel, '
                    'fault, size. Each is replayed with the parameters the robot ran with and '
                    'gets a one-page incident.html in its folder (signals, residuals against their '
                    'bounds, evidence, the alarm marked); --no-pages skips that. Replay one with '
                    '`youbot-fdi replay INCIDENT --events E.jsonl`.')
    parser.add_argument('folder', help='incident folder (default of the nodes: '
                                       '$ROS_HOME/youbot_fdi/incidents), or one incident')
    parser.add_argument('--no-pages', action='store_true', help='only the listing')
    parser.set_defaults(run=run)


def page(incident):
    """Replay ``incident`` (an IncidentSummary) with its own parameters and write its page;
    returns (page path, whether the replay gave the same alarm)."""
    from youbot_fdi.app.config import build_pipeline
    from youbot_fdi.app.incidents import incident_parameters, read_sidecar, replays_alarm
    from youbot_fdi.app.replay import replay_recording
    from youbot_fdi.app.report import write_incident_page
    params, fdi_config = incident_parameters(incident.path)
    model, pipeline = build_pipeline(params, fdi_config, keep_frames=True)
    events = replay_recording(pipeline, incident.path).events
    sidecar = read_sidecar(incident.path)
    return (write_incident_page(incident.path, model, pipeline, events, sidecar),
            replays_alarm(sidecar, events))


def run(args):
    from youbot_fdi.app.incidents import BYTES_PER_MEGABYTE, list_incidents
    from youbot_fdi.bag.reader import RecordingError
    folder = Path(args.folder)
    if not folder.exists():
        print(f'youbot-fdi incidents: error: {folder} does not exist', file=sys.stderr)
        return ERROR
    incidents = list_incidents(folder)
    if not incidents:
        print(f'{folder}: no incidents')
        return 0
    total = sum(i.size_bytes for i in incidents)
    count = f'{len(incidents)} incident' + ('s' if len(incidents) != 1 else '')
    print(f'{folder}: {count}, {total / BYTES_PER_MEGABYTE:.1f} MB')
    print(f'  {"time (UTC)":<29} {"wheel":<16} {"fault":<15} {"size":>8}  state     '
          + ('' if args.no_pages else 'replayed   page'))
    for incident in incidents:
        if incident.problem:  # a damaged sidecar: said here, the others listed as usual
            print(f'  {incident.path.name:<29} {"?":<16} {"?":<15} '
                  f'{incident.size_bytes / BYTES_PER_MEGABYTE:6.2f}MB  unreadable: {incident.problem}')
            continue
        state = 'complete' if incident.complete else 'cut'
        replayed = ''
        if not args.no_pages:
            try:
                path, same = page(incident)
                shown = path.relative_to(folder) if path.is_relative_to(folder) else path
                replayed = f'{"same alarm" if same else "DIFFERENT":<11}{shown}'
            except RecordingError as err:
                replayed = f'unreadable: {err}'
        print(f'  {incident.time:<29} {incident.wheel:<16} {incident.fault:<15} '
              f'{incident.size_bytes / BYTES_PER_MEGABYTE:6.2f}MB  {state:<9} {replayed}')
    return 0
