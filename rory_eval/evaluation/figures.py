"""Side-by-side figures like the paper's Fig. 2, 3 and 8: no crash, restart, RORY.

One PNG per target and world (the first repetition): a panel per run, each drawing the world
and what that run produced - the final map (mapping), the model's points above the floor seen
from above (3D model), or the driven path to the goal (navigation and localization) - titled
with the run's verdict.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import matplotlib

matplotlib.use('Agg')
import matplotlib.pyplot as plt  # after the backend is chosen

from rory_eval.evaluation.judge import Verdict, load_map, load_model
from rory_eval.evaluation.report import Judged
from rory_eval.runs.plan import BARE
from rory_eval.runs.runner import RunRecord
from rory_eval.targets import TARGETS, Kind
from sim.render import draw_world
from sim.worlds import get_world

PANELS = ('restart', 'rory')  # beside the no-crash run, as in the paper's figures
FLOOR = 0.05  # m: model points below this are floor, left out of the top view


def cell_figure(target: str, world: str, reference: tuple[RunRecord, Path],
                crashes: Sequence[Judged], out: Path) -> Path:
    """The PNG of one target in one world: no crash, then each crash run given."""
    kind = TARGETS[target].kind
    w = get_world(world)
    panels: list[tuple[str, RunRecord, Path, Verdict | None]] = [
        ('no crash', reference[0], reference[1], None)]
    panels += [(f'{j.record.spec.column}, crash at {j.record.spec.crash_at:g} s', j.record,
                j.folder, j.verdict) for j in crashes]
    xmin, ymin, xmax, ymax = w.bounds
    aspect = (ymax - ymin) / (xmax - xmin)
    fig, axes = plt.subplots(1, len(panels), figsize=(4.6 * len(panels), 4.6 * aspect + 1.0),
                             squeeze=False)
    try:
        for ax, (label, record, folder, verdict) in zip(axes[0], panels, strict=True):
            truth = [(r[1], r[2]) for r in record.ground_truth]
            if kind == Kind.MAP:
                draw_world(ax, w, grid=load_map(folder), show_route=False, show_goals=False,
                           obstacle_alpha=0.25,
                           paths={'robot (ground truth)': truth,
                                  'its pose': [(p[1], p[2]) for p in record.poses]})
            elif kind == Kind.MODEL:
                draw_world(ax, w, show_route=False, show_goals=False, obstacle_alpha=0.25,
                           paths={'robot (ground truth)': truth,
                                  'its pose': [(p[1], p[2]) for p in record.poses]})
                points = load_model(folder)
                if points is not None and len(points):
                    above = points[points[:, 2] > FLOOR]
                    ax.scatter(above[:, 0], above[:, 1], s=0.3, c=above[:, 2], cmap='viridis',
                               vmin=0.0, vmax=1.5, linewidths=0)
            else:
                paths = {'robot (ground truth)': truth}
                if kind == Kind.LOCALIZATION:
                    paths['its pose'] = [(p[1], p[2]) for p in record.poses]
                draw_world(ax, w, show_route=False, paths=paths)
            crash = record.killed_at
            if crash is not None and record.ground_truth:
                at = min(record.ground_truth, key=lambda r: abs(r[0] - crash))
                ax.plot(at[1], at[2], 'rx', ms=10, mew=2, label='crash')
            status = '' if verdict is None else (
                ': correct' if verdict.correct else
                (': not judged' if verdict.correct is None else ': WRONG'))
            ax.set_title(f'{label}{status}', fontsize=9)
            ax.legend(loc='lower right', fontsize=6)
        fig.suptitle(f'{target} ({TARGETS[target].paper}) in {world}', fontsize=10)
        out.parent.mkdir(parents=True, exist_ok=True)
        fig.tight_layout()
        fig.savefig(out, dpi=110)
    finally:
        plt.close(fig)
    return out


def all_figures(runs: Sequence[tuple[RunRecord, Path]], judged: Sequence[Judged],
                out: Path, methods: Sequence[str] = PANELS) -> list[Path]:
    """One figure per target and world, from its first repetition with a reference."""
    written = []
    references = {(r.spec.target, r.spec.world, r.spec.repetition): (r, f) for r, f in runs
                  if r.spec.method == BARE and not r.error}
    done: set[tuple[str, str]] = set()
    for (target, world, rep), reference in sorted(references.items()):
        if (target, world) in done:
            continue
        crashes = sorted((j for j in judged
                          if (j.record.spec.target, j.record.spec.world,
                              j.record.spec.repetition) == (target, world, rep)
                          and j.record.spec.column in methods),
                         key=lambda j: methods.index(j.record.spec.column))
        if not crashes:
            continue
        done.add((target, world))
        written.append(cell_figure(target, world, reference, crashes,
                                   out / f'{target}-{world}.png'))
    return written
