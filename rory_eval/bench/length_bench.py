"""Recovery time against run length: RORY stays flat, replay alone grows with the run.

    python -m rory_eval.bench.length_bench [--crash-at 9 60 300] [--rate 10] [--out length-out]

The integrator scenario (``rory_eval/harness/scenario.py``: numbers 1..N at ``--rate`` Hz, a SIGKILL
``T`` seconds after the first one, a checkpoint every 2 s) for each crash time T, once under
``replay`` (no checkpoints: everything since the start is replayed) and once under ``rory``
(restore, then replay what came after the checkpoint), both with fast replay and each as
configured by default (rory from its warm standby, replay cold, as the paper ran it). The two
methods run one after the other at each T, so machine load affects them alike. Every run is
also checked exact (final history 1..N: nothing lost, nothing applied twice).

Writes ``<out>/length.md`` (a table of recovery time, its steps and what was replayed) and
``<out>/recovery_vs_length.png``.
"""

from __future__ import annotations

import argparse
import os
import time
from dataclasses import dataclass
from pathlib import Path

import matplotlib

matplotlib.use('Agg')
import matplotlib.pyplot as plt  # after the backend is chosen

from rory_eval.harness.scenario import Kill, run

METHODS = ('replay', 'rory')
STEPS = ('restart_ms', 'restore_ms', 'sync_ms', 'replay_ms', 's4_ms')


@dataclass(frozen=True)
class Point:
    """One run."""

    method: str
    crash_at: float
    correct: bool
    total_ms: float
    steps: dict[str, float]
    replayed: int


def measure(crash_at: float, method: str, *, rate: float, out: Path, domain: int) -> Point:
    """One scenario run with a SIGKILL ``crash_at`` s in."""
    count = int(rate * (crash_at + 4.0))
    result = run(method, (Kill(after=crash_at),), out / f'{method}-{crash_at:g}s',
                 domain_id=domain, count=count, rate=rate, pace='fast',
                 timeout=crash_at + 150.0)
    recovered = result.recoveries[0] if result.recoveries else {}
    return Point(
        method=method, crash_at=crash_at, correct=result.correct,
        total_ms=float(recovered.get('total_ms', float('nan'))),
        steps={s: float(recovered.get(s, float('nan'))) for s in STEPS},
        replayed=int(recovered.get('replayed', 0) or 0),
    )


def table(points: list[Point]) -> str:
    """Markdown, one row per run."""
    lines = [
        '| crash at (s) | method | exact | recovery (ms) | '
        + ' | '.join(s.removesuffix('_ms') for s in STEPS) + ' | messages replayed |',
        '|---:|---|---|---:|' + '---:|' * len(STEPS) + '---:|',
    ]
    for p in sorted(points, key=lambda p: (p.crash_at, p.method)):
        lines.append(
            f'| {p.crash_at:g} | {p.method} | {"yes" if p.correct else "NO"} | '
            f'{p.total_ms:.0f} | ' + ' | '.join(f'{p.steps[s]:.0f}' for s in STEPS)
            + f' | {p.replayed} |'
        )
    return '\n'.join(lines)


def plot(points: list[Point], path: Path) -> None:
    """Recovery time against crash time, one line per method."""
    fig, ax = plt.subplots(figsize=(6.0, 3.8))
    for method, marker in zip(METHODS, ('s', 'o'), strict=True):
        mine = sorted((p for p in points if p.method == method), key=lambda p: p.crash_at)
        ax.plot([p.crash_at for p in mine], [p.total_ms / 1000 for p in mine], marker=marker,
                label=f'{method} (fast replay)')
    ax.set_xlabel('crash time: seconds of running before the SIGKILL')
    ax.set_ylabel('recovery time (s), crash detected -> released')
    ax.set_title('Recovery time against run length (checkpoint every 2 s)')
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main() -> int:
    """Run every crash time under both methods; exit 1 if any run was not exact."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--crash-at', type=float, nargs='+', default=[9.0, 60.0, 300.0])
    parser.add_argument('--rate', type=float, default=10.0, help='numbers per second')
    parser.add_argument('--out', type=Path, default=Path('length-out'))
    args = parser.parse_args()
    domain = int(os.environ.get('ROS_DOMAIN_ID', '79'))
    began = time.monotonic()
    points: list[Point] = []
    for crash_at in args.crash_at:
        for method in METHODS:
            point = measure(crash_at, method, rate=args.rate, out=args.out, domain=domain)
            points.append(point)
            print(f'crash at {crash_at:g} s, {method:6}: recovered in {point.total_ms:7.0f} ms, '
                  f'replayed {point.replayed}, exact={point.correct}', flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    text = table(points)
    minutes = (time.monotonic() - began) / 60
    header = (f'Integrator at {args.rate:g} Hz, SIGKILL at each crash time, fast replay, '
              f'checkpoint every 2 s ({minutes:.1f} min)')
    (args.out / 'length.md').write_text(f'{header}\n\n{text}\n')
    plot(points, args.out / 'recovery_vs_length.png')
    print(f'\n{header}\n\n{text}\n\nfigure: {args.out / "recovery_vs_length.png"}')
    return 0 if all(p.correct for p in points) else 1


if __name__ == '__main__':
    raise SystemExit(main())
