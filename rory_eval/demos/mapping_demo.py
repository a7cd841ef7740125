"""``make demo``: the paper's story in about two minutes, in the simulator.

grid_slam (our hector_mapping) maps office_small while the simulator drives the robot along its
route. The same run is made three times: without a crash; SIGKILLed at 9 s and brought back by
``restart`` (what ROS's respawn does); SIGKILLed at 9 s and brought back by ``rory``. It prints
how each crash run's final map compares with the no-crash map and how long recovery took, and
draws the three maps side by side (``demo-out/figures/grid_slam-office_small.png``).

It is ``rory eval`` cut down to one cell; ``make eval`` runs every target, world and method.
The integrator demo that used to be here is ``python -m rory_eval.demos.integrator_demo``.
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Sequence
from pathlib import Path

TARGET, WORLD = 'grid_slam', 'office_small'


def main(argv: Sequence[str] | None = None) -> int:
    """Run the demo; exit 0 when it ran and RORY's map was judged correct."""
    parser = argparse.ArgumentParser(prog='python -m rory_eval.demos.mapping_demo',
                                     description=__doc__.split('\n\n')[0])
    parser.add_argument('--out', type=Path, default=Path('demo-out'))
    parser.add_argument('--crash-at', type=float, default=9.0, help='sim seconds')
    parser.add_argument('--duration', type=float, default=25.0, help='sim seconds per run')
    parser.add_argument('--domain', type=int,
                        default=int(os.environ.get('ROS_DOMAIN_ID', '0') or 0) or 77)
    args = parser.parse_args(argv)

    from rory_eval.evaluation import figures, report
    from rory_eval.evaluation.cli import Progress, execute_plan
    from rory_eval.runs.plan import build_plan

    print(f'{TARGET} maps {WORLD} for {args.duration:g} s: without a crash, then SIGKILLed at '
          f'{args.crash_at:g} s and recovered by restart (ROS respawn) and by rory.\n',
          flush=True)
    plan = build_plan([TARGET], [WORLD], ['restart', 'rory'], repetitions=1,
                      crash_at=args.crash_at, duration=args.duration, overhead_worlds=())
    progress = Progress(len(plan.runs))
    runs = execute_plan(plan, args.out, jobs=1, domain=args.domain, fresh=True,
                        progress=progress)
    progress.close()
    failed = [r for r, _ in runs if r.error]
    for record in failed:
        print(f'{record.spec.name} failed: {record.error}', file=sys.stderr)
    judged = report.judge_all(runs)
    lines = ['| method | map after the crash | coverage | agreement | occupied IoU | '
             'recovery (ms) |', '|---|---|---:|---:|---:|---:|']
    for j in judged:
        m = j.verdict.measures
        verdict = {True: 'correct', False: 'WRONG', None: 'not judged'}[j.verdict.correct]
        recovered = j.record.recoveries
        took = f'{recovered[0]["total_ms"]:.0f}' if recovered else '-'
        lines.append(
            f'| {j.record.spec.method} | {verdict} | {m.get("coverage", 0):.3f} | '
            f'{m.get("agreement", 0):.3f} | {m.get("iou", 0):.3f} | {took} |')
    table = '\n'.join(lines)
    pngs = figures.all_figures(runs, judged, args.out / 'figures')
    (args.out / 'results.md').write_text(table + '\n')
    print('\n' + table + '\n')
    print('coverage: share of the no-crash map\'s observed cells this map observed; '
          'agreement: share of the cells both observed with the same free/occupied class.')
    for png in pngs:
        print(f'maps side by side: {png}')
    rory_ok = any(j.record.spec.method == 'rory' and j.verdict.correct for j in judged)
    return 0 if rory_ok and not failed else 1


if __name__ == '__main__':
    sys.exit(main())
