"""Run an unchanged robot program with injectable one-shot faults in its callbacks.

    python -m rory_eval.faults.flaky.inject PROGRAM.py [ARGS...]

The program knows nothing of this (nor of RORY). Before it runs, rclpy's
``Node.create_subscription`` is wrapped so that every subscription callback the program
registers first looks for a flag file in the working directory, as the flaky integrator does:
``fault-raise`` makes the callback raise (an uncaught exception), ``fault-hang`` makes it block
forever (found by the supervisor's heartbeat). The flag is removed first, so the fault strikes
once, like a glitch: the same message replayed later goes through. Signals come from outside.
"""

from __future__ import annotations

import functools
import os
import runpy
import sys
import time
from collections.abc import Callable
from typing import Any

from rclpy.node import Node

RAISE_FLAG = 'fault-raise'
HANG_FLAG = 'fault-hang'


def _take(flag: str) -> bool:
    try:
        os.remove(flag)
    except FileNotFoundError:
        return False
    return True


def faulty(callback: Callable[..., Any]) -> Callable[..., Any]:
    """The callback, behind the two flags (its signature kept: rclpy reads it)."""

    @functools.wraps(callback)
    def wrapper(*args: Any) -> Any:
        if _take(RAISE_FLAG):
            msg = 'injected fault (rory_eval.faults.flaky.inject) while applying a message'
            raise RuntimeError(msg)
        if _take(HANG_FLAG):
            while True:  # a driver call that never returns
                time.sleep(1.0)
        return callback(*args)

    return wrapper


def install() -> None:
    """Wrap every subscription callback created from now on."""
    original = Node.create_subscription
    if getattr(original, '_rory_faulty', False):
        return

    @functools.wraps(original)
    def create_subscription(self: Node, msg_type: Any, topic: str,
                            callback: Callable[..., Any], *args: Any, **kwargs: Any) -> Any:
        return original(self, msg_type, topic, faulty(callback), *args, **kwargs)

    create_subscription._rory_faulty = True  # type: ignore[attr-defined]
    Node.create_subscription = create_subscription  # type: ignore[method-assign]


def main() -> None:
    """Run PROGRAM as ``python PROGRAM ARGS`` would, with the faults installed."""
    if len(sys.argv) < 2:
        sys.exit('usage: python -m rory_eval.faults.flaky.inject PROGRAM.py [ARGS...]')
    install()
    program = sys.argv[1]
    sys.argv = sys.argv[1:]
    sys.path.insert(0, os.path.dirname(os.path.abspath(program)))
    runpy.run_path(program, run_name='__main__')


if __name__ == '__main__':
    main()
