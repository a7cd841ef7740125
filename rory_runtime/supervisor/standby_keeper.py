"""One node's side of the warm standbys (supervisor.yaml ``warm_standby``): the pool its next
process starts from is kept full while it runs, dropped when it ends, and shown in
/diagnostics. The pool itself is the launcher's (``standby.ForkLauncher``, shared by every node
with the same ``rclpy.init``); this only asks it, at the right times."""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping

from .config import NodeConfig
from .ports import SupervisorPorts
from .process import Child
from .states import LOG_PREFIX

_logger = logging.getLogger('rory.supervisor')

STANDBY_DELAY = 1.0
"""Seconds a node runs after its (re)start before its next standby is started: the standby's
imports must not compete with the node's own start or recovery for the CPU."""


class StandbyKeeper:
    """Keeps the standby pool of one node full.

    Args:
        sup: The supervisor's ports (its launcher, folder and event log).
        cfg: The node's entry.
        next_env: The environment of the node's next process (what the launcher prepares).
    """

    def __init__(self, sup: SupervisorPorts, cfg: NodeConfig,
                 next_env: Callable[[], Mapping[str, str]]) -> None:
        self._sup = sup
        self._cfg = cfg
        self._next_env = next_env
        self.standby_for: int | None = None  # the incarnation whose successor is on standby
        self.checked_at = 0.0  # when the standby pool was last topped up for it

    def due(self, now: float, incarnation: int, running_since: float | None) -> bool:
        """A node released ``STANDBY_DELAY`` ago, and not topped up for that long."""
        return (self._cfg.warm_standby and running_since is not None
                and now - running_since >= STANDBY_DELAY
                and (self.standby_for != incarnation or now - self.checked_at >= STANDBY_DELAY))

    def prepare(self, now: float, incarnation: int) -> None:
        """Have the pool of processes that will replace this one (or another node that shares
        them) at its next crash full: another node's crash may have taken one."""
        first = self.standby_for != incarnation
        self.standby_for = incarnation
        self.checked_at = now
        if not first and self._pool_full():
            return  # what prepare would find: nothing to start, nothing to say
        pids = self._sup.launcher.prepare(self._cfg.command, self._next_env(),
                                          self._sup.config.folder)
        if pids is None:
            if first:
                _logger.info('%s %s: no warm standby for this command (not python FILE or '
                             'python -m MODULE); restarts are cold', LOG_PREFIX, self._cfg.name)
            return
        for pid in pids:
            _logger.info('%s %s: standby pid %d started', LOG_PREFIX, self._cfg.name, pid)
            self._sup.events_log.write('standby', self._cfg.name, pid=pid,
                                       incarnation=incarnation)

    def _pool_full(self) -> bool:
        """The launcher's pool for this command holds all its standbys and spares, alive
        (``ForkLauncher.full``), so ``prepare`` would start nothing: a few microseconds, where
        ``prepare`` builds the environment and computes the init signature first. A launcher
        without a pool is never full."""
        full = getattr(self._sup.launcher, 'full', None)
        return bool(full(self._cfg.command, self._sup.config.folder)) if full else False

    def spawned(self, child: Child) -> bool:
        """A new process of the node started: whether from a standby (warm); a node that had
        one prepared and started cold says why."""
        warm = bool(getattr(child, 'warm', False))
        if self.standby_for is not None and not warm:
            _logger.warning('%s %s: started cold: %s', LOG_PREFIX, self._cfg.name,
                            str(getattr(child, 'why_cold', '')))
        self.standby_for = None
        return warm

    def drop(self) -> None:
        """The node ended: its command no longer wants a standby."""
        if self.standby_for is not None:
            self._sup.launcher.discard(self._cfg.command, self._sup.config.folder)
            self.standby_for = None

    def status(self) -> str:
        """For /diagnostics: 'off', 'none', 'ready' or 'starting'."""
        if not self._cfg.warm_standby:
            return 'off'
        find = getattr(self._sup.launcher, 'standby', None)
        waiting = find(self._cfg.command, self._sup.config.folder) if find else None
        return ('none' if waiting is None
                else 'ready' if waiting.ready_at is not None else 'starting')
