"""``youbot-fdi structure``: structural analysis of a model (report chapter 4)."""
import json
from pathlib import Path
import time

NAME = 'structure'


def add_parser(subparsers):
    parser = subparsers.add_parser(
        NAME, help='structural analysis: matching, MSO sets, detectability and isolability',
        description='Structural analysis of a model: incidence matrix, matching, parity relations, '
                    'MSO sets, fault signature matrix, detectability and isolability (report '
                    'Table 4.4 form), and which extra sensors would improve isolation. Models: '
                    '"seed" (the report\'s c1..c16), any parameter profile (e.g. "youbot": the '
                    'corrected model generated from its geometry), or a YAML path.')
    parser.add_argument('--model', default='youbot', help='model name or YAML path (default: youbot)')
    parser.add_argument('--format', choices=('text', 'json'), default='text',
                        help='output format (default: text)')
    parser.add_argument('--plot', metavar='FILE', help='write the structure graph (PNG) here')
    parser.add_argument('--write-residuals', metavar='FILE',
                        help='write the runtime residual set (YAML) the FDI core loads')
    parser.set_defaults(run=run)


def run(args):
    from youbot_fdi.structure.analysis import analyze
    from youbot_fdi.structure.generate import resolve_model
    from youbot_fdi.structure.report import (placement_summary, plot_structure_graph,
                                             residual_file_text, to_dict, to_text)
    model = resolve_model(args.model)
    started = time.perf_counter()
    analysis = analyze(model)
    placement = placement_summary(analysis)
    elapsed = time.perf_counter() - started
    if args.format == 'json':
        data = to_dict(analysis, placement)
        data['elapsed_s'] = round(elapsed, 4)
        print(json.dumps(data, indent=1))
    else:
        print(to_text(analysis, placement))
        print(f'\n(analysis took {elapsed:.3f} s)')
    if args.plot:
        plot_structure_graph(analysis, args.plot)
        if args.format == 'text':
            print(f'structure graph: {args.plot}')
    if args.write_residuals:
        Path(args.write_residuals).parent.mkdir(parents=True, exist_ok=True)
        Path(args.write_residuals).write_text(residual_file_text(analysis))
        if args.format == 'text':
            print(f'residual set: {args.write_residuals}')
    return 0
