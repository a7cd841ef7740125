"""A ForkLauncher in a process of its own, driven over stdin/stdout (one JSON object a line).

The zygote must be forked from a process that has no DDS participant and no thread of its own
yet, as the supervisor's is (rory_runtime/supervisor/zygote.py); a pytest worker has run other
tests' participants by then. So the launcher tests run it here, fresh, and ask it what they
would ask the launcher.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path
from typing import Any


def main() -> int:
    from rory_runtime.supervisor.output import OutputPrefixer
    from rory_runtime.supervisor.standby import ForkLauncher
    from rory_runtime.supervisor.zygote import Zygote

    launcher = ForkLauncher(Zygote.start([], preload=('rclpy.node',)),
                            pool_size=int(os.environ.get('LAUNCHER_HOST_POOL', '1')))
    # Prefixed output goes to a file: this process's stdout carries the replies.
    prefixed_to = os.environ.get('LAUNCHER_HOST_PREFIXED_OUTPUT')
    if prefixed_to:
        out = open(prefixed_to + '.out', 'ab')  # noqa: SIM115 (open while the host runs)
        err = open(prefixed_to + '.err', 'ab')  # noqa: SIM115
        launcher.output = OutputPrefixer(out, err)
    children: dict[int, Any] = {}
    for line in sys.stdin:
        request = json.loads(line)
        op = request.pop('op')
        reply: dict[str, Any] = {}
        if op == 'prepare':
            started = launcher.prepare(request['argv'], request['env'], Path(request['cwd']))
            after = launcher.standby(request['argv'], Path(request['cwd']))
            # pid: the standby this command would start from next
            reply = {'started': started, 'pid': None if after is None else after.pid,
                     'pool': [s.pid for s in launcher.standbys(request['argv'],
                                                              Path(request['cwd']))],
                     'spares': [s.pid for s in launcher.spares(request['argv'],
                                                              Path(request['cwd']))]}
        elif op == 'spawn':
            child = launcher.spawn(request['argv'], request['env'], Path(request['cwd']),
                                   label=request.get('label', ''))
            children[child.pid] = child
            reply = {'pid': child.pid, 'warm': getattr(child, 'warm', None),
                     'why_cold': getattr(child, 'why_cold', '')}
        elif op == 'wait':
            try:
                reply['code'] = children[request['pid']].wait(timeout=request['timeout'])
            except subprocess.TimeoutExpired:
                reply['code'] = None
        elif op == 'standby':
            standby = launcher.standby(request['argv'], Path(request['cwd']))
            reply = {'pid': None} if standby is None else {
                'pid': standby.pid, 'ready': standby.ready_at is not None,
                'alive': standby.child.poll() is None}
        elif op == 'kill_standby':
            standby = launcher.standby(request['argv'], Path(request['cwd']))
            assert standby is not None
            standby.child.send_signal(signal.SIGKILL)
            reply['code'] = standby.child.wait(timeout=10)
        elif op == 'participant':
            # As the supervisor does after forking the zygote: a participant of its own, and
            # an executor thread spinning its node.
            import threading

            import rclpy
            from rclpy.executors import SingleThreadedExecutor
            from rclpy.node import Node

            rclpy.init()
            node = Node(request['name'])
            executor = SingleThreadedExecutor()
            executor.add_node(node)
            threading.Thread(target=executor.spin, name='rory-ros', daemon=True).start()
        elif op == 'close':
            zygote = launcher.zygote.pid if launcher.zygote is not None else None
            launcher.close()
            try:
                os.waitpid(zygote or -1, os.WNOHANG)
                reply['zygote_reaped'] = False
            except ChildProcessError:
                reply['zygote_reaped'] = True
        reply['host'] = os.getpid()
        print(json.dumps(reply), flush=True)
        if op == 'close':
            return 0
    launcher.close()
    return 0


if __name__ == '__main__':
    sys.exit(main())
