"""Parameter changes, service requests and lifecycle transitions come back after a crash in the
order the node first applied them, wherever the checkpoint fell among them (before both
changes, between them, after both), and a change that arrives while the node recovers is
applied after everything replayed (docs/architecture.md, "Parameters", "Services",
"Lifecycle nodes").

The interleaving is forced, not timed: one real rclpy lifecycle node per process, its
runtime's entry points driven by hand in a fixed order (a checkpoint taken exactly where the
case puts it, a crash as a process that simply stops, its log replayed as the shadow topic
would carry it). The same paths run across real processes in tests/integration/
test_corpus_time.py and ``make faults`` part four.
"""

from __future__ import annotations

import atexit
import itertools
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from lifecycle_msgs.msg import Transition
from lifecycle_msgs.srv import ChangeState
from rcl_interfaces.msg import SetParametersResult
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn
from rclpy.parameter import Parameter
from runtime_fakes import FakeSubscription, deliver_live
from std_msgs.msg import Int64
from std_srvs.srv import SetBool

from rory_runtime import protocol
from rory_runtime.log import read_segment
from rory_runtime.node import lifecycle as node_lifecycle
from rory_runtime.node.runtime import NodeRuntime, RuntimeEnv
from rory_runtime.node.state import CheckpointSpec
from rory_runtime.protocol import Method, Mode
from rory_runtime.supervisor.recovery import readings_first

pytestmark = pytest.mark.ros
_names = itertools.count()


class Controller(LifecycleNode):
    """Scales each number by its gain (a parameter) and its factor (set through a service),
    and counts it only while active; ``applied`` says what each number was counted under."""

    def __init__(self, name: str, context: Context) -> None:
        super().__init__(name, context=context, start_parameter_services=False)
        self.declare_parameter('gain', 1.0)
        self.gain = 1.0
        self.factor = 1
        self.active = False
        self.applied: list[list[Any]] = []
        self.add_post_set_parameters_callback(self._after_set)
        self.fast = self.create_service(SetBool, 'fast', self._on_fast)

    def _after_set(self, params: list[Parameter]) -> None:
        for p in params:
            if p.name == 'gain':
                self.gain = p.value

    def _on_fast(self, request: Any, response: Any) -> Any:
        self.factor = 2 if request.data else 1
        response.success = True
        return response

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        self.active = True
        return TransitionCallbackReturn.SUCCESS

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        self.active = False
        return TransitionCallbackReturn.SUCCESS

    def on_number(self, msg: Int64) -> None:
        self.applied.append([self.gain, self.factor, self.active, msg.data])


class Process:
    """One incarnation: the node and its runtime, the node's inputs adopted as the decorator
    adopts them."""

    def __init__(self, tmp_path: Path, context: Context, mode: Mode, incarnation: int) -> None:
        self.node = Controller(f'controller_{next(_names)}', context)
        self.rt = NodeRuntime(
            CheckpointSpec(('applied', 'factor'), 'sha256:0'),
            RuntimeEnv(node_id='n', store=tmp_path, incarnation=incarnation,
                       method=Method.RORY, mode=mode, interval=2.0))
        self.rt.node = self.node
        self.rt.gate.watch_parameters(self.node)
        self.rt.adopt_service(node_lifecycle.change_state_service(self.node))
        self.rt.adopt_service(self.node.fast)
        self.numbers = FakeSubscription('/numbers', self.node.on_number)
        self.rt.adopt_subscription(self.numbers)  # type: ignore[arg-type]
        self.rt.checkpointer.number_from_store()  # as start-up does

    # What reaches the node from outside, through the entry points rclpy's executor uses.

    def number(self, n: int) -> None:
        deliver_live(self.numbers, n)

    def set_gain(self, gain: float) -> None:
        # rclpy's ~/set_parameters service calls the node's set_parameters_atomically.
        result: SetParametersResult = self.node.set_parameters_atomically(
            [Parameter('gain', value=gain)])
        assert result.successful, result.reason

    def set_fast(self, fast: bool) -> None:
        self.node.fast.callback(SetBool.Request(data=fast), SetBool.Response())

    def transition(self, label: str) -> None:
        service = node_lifecycle.change_state_service(self.node)
        response = service.callback(ChangeState.Request(transition=Transition(label=label)),
                                    ChangeState.Response())
        assert response.success, label

    def checkpoint(self) -> None:
        """A checkpoint taken now, between two callbacks, written before the next input."""
        persist = self.rt.checkpointer.take(self.node, self.rt.applier.windows)
        assert persist is not None
        persist()


Change = Callable[[Process], None]
# Per kind of input: the two changes (A, B) made while the node runs, and one (C) that arrives
# while it recovers.
KINDS: dict[str, tuple[Change, Change, Change]] = {
    'parameter': (lambda p: p.set_gain(2.0), lambda p: p.set_gain(3.0),
                  lambda p: p.set_gain(4.0)),
    'service': (lambda p: p.set_fast(True), lambda p: p.set_fast(False),
                lambda p: p.set_fast(True)),
    'lifecycle': (lambda p: p.transition('deactivate'), lambda p: p.transition('activate'),
                  lambda p: p.transition('deactivate')),
}
CHECKPOINT_AT = ('before both', 'between', 'after both')


def _run_until_crash(proc: Process, a: Change, b: Change, checkpoint_at: str | None) -> None:
    """The node's life until it dies: numbers 1-7, change A after 2, change B after 4, and a
    checkpoint where ``checkpoint_at`` says (None: none)."""
    proc.rt.open_gates(next_segment=1)
    proc.transition('configure')
    proc.transition('activate')
    for n in (1, 2):
        proc.number(n)
    if checkpoint_at == 'before both':
        proc.checkpoint()
    a(proc)
    for n in (3, 4):
        proc.number(n)
    if checkpoint_at == 'between':
        proc.checkpoint()
    b(proc)
    for n in (5, 6):
        proc.number(n)
    if checkpoint_at == 'after both':
        proc.checkpoint()
    proc.number(7)


def _after_recovery(proc: Process, c: Change) -> None:
    """What follows the release: the change that came while the node recovered (its service
    is out of the executor's wait set until release, so the request waits in its queue and
    is taken right after), then live numbers."""
    c(proc)
    proc.number(8)


@pytest.fixture
def no_crash(context: Context, tmp_path_factory: pytest.TempPathFactory) -> Iterator[
        dict[str, list[list[Any]]]]:
    """Per kind, what the node applied in a run without a crash."""
    made: dict[str, list[list[Any]]] = {}
    for kind, (a, b, c) in KINDS.items():
        proc = Process(tmp_path_factory.mktemp(kind), context, Mode.FRESH, 1)
        _run_until_crash(proc, a, b, None)
        _after_recovery(proc, c)
        made[kind] = proc.node.applied
        proc.rt.close()
    yield made


@pytest.mark.parametrize('checkpoint_at', CHECKPOINT_AT)
@pytest.mark.parametrize('kind', list(KINDS))
def test_changes_come_back_in_the_order_first_applied_wherever_the_checkpoint_fell(
    kind: str, checkpoint_at: str, context: Context, tmp_path: Path,
    no_crash: dict[str, list[list[Any]]],
) -> None:
    a, b, c = KINDS[kind]
    first = Process(tmp_path, context, Mode.FRESH, 1)
    _run_until_crash(first, a, b, checkpoint_at)
    # SIGKILLed here: nothing closed, no checkpoint at exit; what it logged is in its segments
    # already (write-ahead).
    atexit.unregister(first.rt.close)

    second = Process(tmp_path, context, Mode.RECOVER, 2)
    restored = second.rt.restore([])
    assert restored is not None and restored.cut is not None
    after_cut = [n for n in first.rt.checkpointer.segments.numbers() if n > restored.cut]
    segments = first.rt.checkpointer.segments
    logged = [entry for n in after_cut for entry in read_segment(segments.path(n))]
    for entry in readings_first(logged):
        second.rt.router.from_shadow(protocol.Msg(2, 0, entry.recv_ns, entry.source_ns,
                                                  entry.seq, entry.topic, entry.data))
    # The change C arrives now, while the node recovers: a request waits in its service's
    # queue (the executor does not take it before release), and a direct change is refused
    # rather than applied out of order with the replay.
    held = [second.node.fast, node_lifecycle.change_state_service(second.node)]
    executor = SingleThreadedExecutor(context=context)
    assert not any(executor.can_execute(srv) for srv in held)
    early = second.node.set_parameters_atomically([Parameter('gain', value=9.0)])
    assert not early.successful
    second.rt.open_gates(next_segment=max(first.rt.checkpointer.segments.numbers(), default=0) + 1)
    assert all(executor.can_execute(srv) for srv in held)
    executor.shutdown()
    # The handover after release (tested in test_routing.py): /numbers is read live again.
    second.rt.router.switch('/numbers')
    _after_recovery(second, c)

    assert second.node.applied == no_crash[kind]
    changes_logged = sum(e.topic in (protocol.PARAMETERS_RECORD, protocol.REQUEST_RECORD)
                         for e in logged)
    # Where the checkpoint fell decides what comes back from it and what from the log.
    assert changes_logged == {'before both': 2, 'between': 1, 'after both': 0}[checkpoint_at]
    if kind == 'parameter':
        assert restored.parameters == (() if checkpoint_at == 'before both' else ('gain',))
    second.rt.close()
