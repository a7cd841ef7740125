"""What the evaluation runs: targets, worlds, methods, repetitions, crash times.

The targets themselves (folder, command line, topics, kind) are rory_eval/targets.py's.

A *cell* is one target in one world. For each cell and repetition the evaluation makes a
``bare`` run (the original node, no RORY: the no-crash reference and Table II's baseline) and one
crash run per method. In the ``overhead_worlds`` it also makes a ``rory`` run without a crash, the
same workload under RORY, for Table II. The methods named in ``other_pace`` also crash once with
the other replay pace (paced when the evaluation's is fast), beside the evaluation's own: a
column of their own in Tables III and IV (:attr:`RunSpec.column`).

How each kind of target runs, as in the paper's section IV-B:

* mapping (grid_slam, graph_slam) and the 3D model (depth_mapper): the simulator's internal
  driver drives the world's route, the same every run for a seed; judged by the final map or
  model.
* navigation (navigator): the navigator drives to the world's default goal, which is sent
  *once* (volatile, as RViz's goal tool does), on a ground-truth-plus-noise localizer.
* localization (amcl, lama_local): the navigator (not supervised) drives to the goal on the
  target's pose, so a localizer that comes back lost sends the robot astray.
"""

from __future__ import annotations

import random
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

from rory_eval.targets import NAVIGATION_SECONDS, TARGETS, Kind, Target

METHODS = ('restart', 'checkpoint', 'replay', 'rory')
PACES = ('fast', 'paced')
PACED_METHODS = ('replay', 'rory')  # the methods that replay, so have a pace
WORLDS = ('office_small', 'workshop', 'real_room')
BARE = 'bare'  # the reference: the original node, no supervisor
CRASH_AT = 9.0  # sim s, the paper's crash time
CHECKPOINT_INTERVAL = 2.0  # s, the paper's interval
MAPPING_SECONDS = 30.0  # sim s of route for mapping and the 3D model


@dataclass(frozen=True)
class RunSpec:
    """One run: everything the runner needs, and the key of its record.

    ``method`` is ``bare`` (no RORY, no crash) or one of :data:`METHODS`; ``crash_at`` None means
    no crash.
    """

    target: str
    world: str
    method: str
    repetition: int
    crash_at: float | None
    duration: float
    seed: int = 0
    replay: str = 'fast'
    interval: float = CHECKPOINT_INTERVAL
    beside: bool = False  # a run of the other replay pace, beside the evaluation's own

    @property
    def name(self) -> str:
        """A folder name, unique in one evaluation."""
        crash = 'nocrash' if self.crash_at is None else f'crash{self.crash_at:.1f}'
        column = self.column.replace(' ', '-')
        return f'{self.target}-{self.world}-{column}-{crash}-r{self.repetition}'

    @property
    def column(self) -> str:
        """Its column in the tables: the method, with the pace when it runs beside."""
        return f'{self.method} {self.replay}' if self.beside else self.method

    @property
    def spec(self) -> Target:
        """The target."""
        return TARGETS[self.target]

    def to_json(self) -> dict[str, Any]:
        """Plain data (the runner's command line carries it)."""
        return asdict(self)

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> RunSpec:
        """Back from :meth:`to_json`."""
        return cls(**data)


def opposite_pace(pace: str) -> str:
    """The replay pace that is not ``pace``."""
    return PACES[1 - PACES.index(pace)]


def duration_for(target: str, world: str, override: float | None = None) -> float:
    """Sim seconds of a run: the route's first part for mapping, the goal's time to drive."""
    if override is not None:
        return override
    kind = TARGETS[target].kind
    if kind in (Kind.NAVIGATION, Kind.LOCALIZATION):
        return NAVIGATION_SECONDS[world]
    return MAPPING_SECONDS


@dataclass
class Plan:
    """The runs of one evaluation, in the order they run."""

    runs: list[RunSpec] = field(default_factory=list)

    def crash_runs(self) -> list[RunSpec]:
        """The runs with a crash."""
        return [r for r in self.runs if r.crash_at is not None]


def build_plan(targets: Sequence[str], worlds: Sequence[str], methods: Sequence[str], *,
               repetitions: int, crash_at: float = CRASH_AT, random_crash: bool = False,
               duration: float | None = None, seed: int = 0, replay: str = 'fast',
               overhead_worlds: Sequence[str] = ('real_room',),
               other_pace: Sequence[str] = ()) -> Plan:
    """Every run, repetition by repetition (a partial evaluation still covers every cell).

    With ``random_crash`` each repetition of a cell draws its crash time uniformly from
    [2 s, duration - 8 s] (seeded: the same command draws the same times); every method of that
    repetition crashes at the same time, so they are compared on the same crash.
    """
    unknown = [t for t in targets if t not in TARGETS]
    if unknown:
        msg = f'unknown target(s) {", ".join(unknown)}; known: {", ".join(TARGETS)}'
        raise ValueError(msg)
    bad = [m for m in methods if m not in METHODS]
    if bad:
        msg = f'unknown method(s) {", ".join(bad)}; known: {", ".join(METHODS)}'
        raise ValueError(msg)
    if replay not in PACES:
        msg = f'unknown replay pace {replay!r}; known: {", ".join(PACES)}'
        raise ValueError(msg)
    unpaced = [m for m in other_pace if m not in PACED_METHODS]
    if unpaced:
        msg = (f'{", ".join(unpaced)} cannot run at another pace: only '
               f'{" and ".join(PACED_METHODS)} replay')
        raise ValueError(msg)
    other = opposite_pace(replay)
    draw = random.Random(seed)
    plan = Plan()
    for rep in range(repetitions):
        for target in targets:
            for world in worlds:
                seconds = duration_for(target, world, duration)
                at = draw.uniform(2.0, max(2.0, seconds - 8.0)) if random_crash else crash_at
                at = round(at, 2)
                if at >= seconds - 3.0:
                    msg = f'crash at {at:g} s leaves no time to recover in a {seconds:g} s run'
                    raise ValueError(msg)
                # Each repetition is another noise realisation of the simulator (seed + rep).
                common: dict[str, Any] = {'target': target, 'world': world, 'repetition': rep,
                                          'duration': seconds, 'seed': seed + rep,
                                          'replay': replay}
                plan.runs.append(RunSpec(method=BARE, crash_at=None, **common))
                if world in overhead_worlds:
                    plan.runs.append(RunSpec(method='rory', crash_at=None, **common))
                plan.runs.extend(RunSpec(method=m, crash_at=at, **common) for m in methods)
                plan.runs.extend(RunSpec(method=m, crash_at=at, beside=True,
                                         **{**common, 'replay': other}) for m in other_pace)
    return plan
