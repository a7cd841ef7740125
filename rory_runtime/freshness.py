"""Freshness rules: whether a key variable's checkpointed value is still worth restoring.

A rule comes from keyvars.yaml (``{name: pose, max_age: 5.0, on_stale: reset}``, docs/keyvars.md)
through the decorator ``rory-instrument`` writes. At a recovery the checkpoint's age is taken
on the clock the node uses: its ROS clock, which is the system clock unless the node runs
under ``use_sim_time``, then simulation time. A variable whose checkpoint is older than its
``max_age`` is *stale* and is

* ``reset``: not restored; it keeps the value the node's own ``__init__`` gave it (and what
  replay then applies on top);
* ``keep``: restored anyway, and reported stale;
* ``refuse``: nothing is restored and the node is not started; the supervisor says why and
  gives up, holding the safe state.

An age that cannot be known counts as older than any ``max_age``: a checkpoint taken under
another time base (simulation time then, the system clock now, or the reverse), a clock that
went back (a simulation restarted from zero), a simulation clock that has not ticked yet.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

ON_STALE = ('reset', 'keep', 'refuse')


@dataclass(frozen=True)
class Rule:
    """The rule of one key variable (by its checkpoint key: ``pose``, ``global:goal``)."""

    key: str
    max_age: float
    on_stale: str = 'reset'

    def __post_init__(self) -> None:
        if not self.max_age > 0 or self.on_stale not in ON_STALE:
            raise ValueError(f'bad freshness rule for {self.key!r}: max_age {self.max_age!r}, '
                             f'on_stale {self.on_stale!r}')


def rules_from(entries: Iterable[Sequence[Any]]) -> tuple[Rule, ...]:
    """The decorator's ``freshness=(("pose", 5.0, "reset"), ...)`` as rules."""
    return tuple(Rule(str(key), float(max_age), str(on_stale))
                 for key, max_age, on_stale in entries)


@dataclass(frozen=True)
class ClockReading:
    """A reading of the node's ROS clock, and whether it was simulation time."""

    ns: int
    sim: bool


@dataclass
class Verdict:
    """What a recovery does with each key variable of one checkpoint."""

    age_s: float | None  # None: unknown (module docstring)
    clock: str  # 'sim' or 'system': the time base the age is counted on
    restored: list[str] = field(default_factory=list)
    reset: list[str] = field(default_factory=list)
    kept_stale: list[str] = field(default_factory=list)
    refused: list[str] = field(default_factory=list)  # stale under refuse: nothing restored
    max_age: dict[str, float] = field(default_factory=dict)  # of the variables with a rule

    def to_json(self) -> dict[str, Any]:
        """As the node's HELLO carries it, and the ``recovered`` event."""
        return {'age_s': None if self.age_s is None else round(self.age_s, 3),
                'clock': self.clock, 'restored': self.restored, 'reset': self.reset,
                'kept_stale': self.kept_stale, 'refused': self.refused,
                'max_age': self.max_age}


def checkpoint_age(taken: ClockReading | None, now: ClockReading) -> float | None:
    """Seconds from ``taken`` to ``now``, or None when they cannot be compared."""
    if taken is None or taken.sim != now.sim or now.ns <= 0 or taken.ns <= 0:
        return None
    age_ns = now.ns - taken.ns
    return age_ns / 1e9 if age_ns >= 0 else None


def judge(keys: Sequence[str], rules: Iterable[Rule], taken: ClockReading | None,
          now: ClockReading) -> Verdict:
    """Decide, per key variable, whether the checkpoint's value is restored."""
    by_key = {rule.key: rule for rule in rules}
    age = checkpoint_age(taken, now)
    verdict = Verdict(age, 'sim' if now.sim else 'system')
    for key in keys:
        rule = by_key.get(key)
        if rule is not None:
            verdict.max_age[key] = rule.max_age
        if rule is None or (age is not None and age <= rule.max_age):
            verdict.restored.append(key)
        elif rule.on_stale == 'keep':
            verdict.kept_stale.append(key)
        elif rule.on_stale == 'refuse':
            verdict.refused.append(key)
        else:
            verdict.reset.append(key)
    return verdict


def describe(verdict: Verdict) -> str:
    """One phrase for the supervisor's log: what was restored, what was not, and why."""
    age = 'age unknown' if verdict.age_s is None else f'age {verdict.age_s:.1f} s'

    def listed(keys: list[str]) -> str:
        return ', '.join(f'{k} (max_age {float(verdict.max_age[k]):g} s)'
                         if k in verdict.max_age else k for k in keys)

    parts = [f'restored: {", ".join(verdict.restored) or "none"}']
    for keys, label in ((verdict.refused, 'stale, refused'), (verdict.reset, 'stale, reset'),
                        (verdict.kept_stale, 'stale, kept')):
        if keys:
            parts.append(f'{label}: {listed(keys)}')
    return f'{"; ".join(parts)} (checkpoint {age}, {verdict.clock} clock)'
