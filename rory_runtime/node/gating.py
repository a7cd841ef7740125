"""The node's outputs and its other inputs, held until release (docs/architecture.md, "Taking
over the node's entities", "Services", "Parameters").

:class:`OutputGate` holds what the node makes besides subscriptions: its publishers, muted
until the outputs open (at release, or under a release gate when the supervisor says OPEN);
its timers, held until release, then put back on their grids (timers.py); its services
and rclpy's parameter-setting services, held until release. Their events (ticks, requests,
parameter changes from outside) run through the applier (applier.py), written ahead to the
log; in replay the gate finds the timer, service or parameter setter a logged event names and
the applier runs it again.
"""

from __future__ import annotations

import inspect
import time
from collections.abc import Callable
from typing import Any

from rcl_interfaces.msg import SetParametersResult
from rcl_interfaces.srv import SetParameters, SetParametersAtomically
from rclpy.exceptions import ParameterException
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.publisher import Publisher
from rclpy.service import Service
from rclpy.timer import Timer

from .. import protocol
from ..errors import RoryError
from . import event_clock
from . import parameters as node_parameters
from . import services as node_services
from .applier import Applier
from .event_clock import Reading
from .timers import NodeTimers


class OutputGate:
    """Publishers muted, timers and services held, until release; their events logged.

    Args:
        applier: Runs the node's events under the lock, logged ahead (and counts them).
        gated: A release gate: outputs stay muted after release until the supervisor's OPEN.
        error: Reports an error (the ERROR status).
    """

    def __init__(self, applier: Applier, *, gated: bool, error: Callable[[str], None]) -> None:
        self.applier = applier
        self.gated = gated
        self._error = error
        self.released = False
        # Outputs go out: at release, or under a release gate when the supervisor says OPEN.
        self.outputs_open = False
        self.publishers: list[Publisher] = []
        # The node's timers by creation order (a logged tick names its timer by index), held
        # until release, then put back on their grids (timers.py).
        self.timers = NodeTimers(lambda: self.released, error)
        # The user's services by creation order: a logged request names its service by index.
        self.services: list[tuple[Service, Callable[[Any, Any], Any]]] = []
        # The node's own set_parameters_atomically, behind the wrapper that logs changes
        # from outside (set by watch_parameters).
        self.set_parameters_atomically: Callable[[list[Parameter]], SetParametersResult] | None
        self.set_parameters_atomically = None

    # -- adoption -------------------------------------------------------------------------------

    def adopt_publisher(self, pub: Publisher) -> None:
        """Mute a user publisher while the node is isolated."""
        if pub in self.publishers:
            return
        self.publishers.append(pub)
        publish = pub.publish
        stats = self.applier.stats

        def gated_publish(msg: Any) -> None:
            if self.outputs_open:
                publish(msg)
            else:
                stats['muted'] += 1

        pub.publish = gated_publish  # type: ignore[method-assign]

    def adopt_timer(self, timer: Timer) -> None:
        """Hold a user timer until release, and run its callback under the runtime lock."""
        if getattr(timer, '_rory', False) or self.timers.known(timer):
            return
        callback = timer.callback
        if inspect.iscoroutinefunction(callback):
            raise RoryError('async timer callbacks are not supported yet')
        index = self.timers.adopt(timer, callback).index
        applier = self.applier
        stats = applier.stats

        def record() -> None:
            applier.write_record(protocol.TIMER_RECORD, time.time_ns(),
                                 int(event_clock.original_now(timer.clock).nanoseconds), index)
            stats['ticks'] += 1

        def locked_tick() -> Any:
            if not self.released:
                return None
            return applier.live_event(record, callback)

        timer.callback = locked_tick
        timer._rory = True  # type: ignore[attr-defined]

    def adopt_service(self, srv: Service) -> None:
        """Hold a user service until release; log each request before its handler runs."""
        if any(srv is known for known, _ in self.services):
            return
        callback = srv.callback
        if inspect.iscoroutinefunction(callback):
            raise RoryError(f'async service callbacks are not supported yet ({srv.srv_name})')
        index = len(self.services)
        self.services.append((srv, callback))
        if not self.released:  # (one made after release serves at once)
            srv.callback_group = node_services.HeldUntilRelease(srv.callback_group,
                                                                lambda: self.released)
        applier = self.applier

        def logged_request(request: Any, response: Any) -> Any:
            def record() -> None:
                applier.write_record(protocol.REQUEST_RECORD, time.time_ns(), 0, index,
                                     node_services.pack_request(request),
                                     node_services.RECORD_TYPE)
                applier.stats['requests'] += 1

            return applier.live_event(record, lambda: callback(request, response))

        srv.callback = logged_request

    def watch_parameters(self, node: Node) -> None:
        """Route parameter changes from outside through :meth:`_parameters_from_outside`.

        rclpy's parameter services call ``set_parameters_atomically`` on the node; an instance
        attribute of that name is what they find. Its two setting services are held until
        release like the node's own (``HeldUntilRelease``): a change requested while the node
        recovers waits, then is applied and logged in order.
        """
        for srv in node.services:
            if srv.srv_type in (SetParameters, SetParametersAtomically):
                srv.callback_group = node_services.HeldUntilRelease(srv.callback_group,
                                                                    lambda: self.released)
        original = node.set_parameters_atomically
        self.set_parameters_atomically = original

        def set_parameters_atomically(parameter_list: list[Parameter]) -> SetParametersResult:
            return self._parameters_from_outside(original, parameter_list)

        node.set_parameters_atomically = set_parameters_atomically  # type: ignore[method-assign]

    def _parameters_from_outside(
        self, original: Callable[[list[Parameter]], SetParametersResult],
        parameter_list: list[Parameter],
    ) -> SetParametersResult:
        """A parameter change: an input when it comes from outside an event."""
        if event_clock.in_event():
            return original(parameter_list)  # a callback's own change: replayed with it
        if not self.released:
            # Called directly (the services wait until release): not in order with the
            # replay, so refused rather than applied out of order.
            return SetParametersResult(
                successful=False, reason='[rory] the node is recovering (or not yet released); '
                'set it again once it is back')
        applier = self.applier

        def record() -> None:
            applier.write_record(protocol.PARAMETERS_RECORD, time.time_ns(), 0, 0,
                                 node_parameters.pack(parameter_list),
                                 node_parameters.RECORD_TYPE)
            applier.stats['parameter_changes'] += 1

        return applier.live_event(record, lambda: original(parameter_list))

    # -- release --------------------------------------------------------------------------------

    def open(self) -> None:
        """Released: timers and services may run; outputs go out unless a release gate holds
        them until OPEN."""
        self.released = True
        self.outputs_open = not self.gated

    def open_outputs(self) -> bool:
        """The release gate opened: what the node publishes from now on goes out. Returns
        whether it did (not before release)."""
        if self.released:  # (again if OPEN came twice: the supervisor resends until it hears)
            self.outputs_open = True
            return True
        return False

    def release_held(self, node: Node, overdue: Callable[[Callable[[], Any]], None]) -> None:
        """Services back to their own callback groups; each timer back on its grid, a tick
        that fell due while the node was down handed to ``overdue``."""
        self._unhold_services(node)
        self.timers.release(overdue)

    @staticmethod
    def _unhold_services(node: Node) -> None:
        """Give each held service its own callback group back: released, the hold would
        only add a Python call for each of them to every wait of the executor."""
        for srv in node.services:
            if isinstance(srv.callback_group, node_services.HeldUntilRelease):
                srv.callback_group = srv.callback_group.inner

    # -- replay ---------------------------------------------------------------------------------

    def replay_event(self, msg: protocol.Msg, readings: list[Reading]) -> None:
        """A logged tick, request or parameter change from the shadow topic, run again with the
        clock ``readings`` it took live."""
        if msg.topic == protocol.TIMER_RECORD:
            self._replay_tick(msg.seq, msg.recv_ns, msg.source_ns, readings)
        elif msg.topic == protocol.PARAMETERS_RECORD:
            self._replay_parameters(msg.data, msg.recv_ns, readings)
        else:
            self._replay_request(msg.seq, msg.data, msg.recv_ns, readings)

    def _replay_tick(self, index: int, event_ns: int, tick_ns: int,
                     readings: list[Reading]) -> None:
        """One logged tick of the user's timer number ``index`` (at ``tick_ns`` on its clock),
        replayed."""
        callback = self.timers.callback(index)
        if callback is None:
            self._error(f'the log has a tick of timer {index}, but the node has no timer '
                        f'{index} ({self.timers.count()} made): tick skipped')
            return
        self.timers.ticked(index, tick_ns)
        self.applier.replayed_event(event_ns, readings, callback)
        self.applier.stats['ticks_replayed'] += 1

    def _replay_request(self, index: int, data: bytes, event_ns: int,
                        readings: list[Reading]) -> None:
        """A logged request to the user's service number ``index``, handled again; the response
        goes nowhere."""
        if index >= len(self.services):
            self._error(f'the log has a request to service {index}, but the node made '
                        f'{len(self.services)} service(s): request skipped')
            return
        srv, callback = self.services[index]
        srv_type: Any = srv.srv_type  # rclpy's annotation lacks Request and Response
        try:
            request = node_services.unpack_request(data, srv_type.Request)
        except ValueError as err:
            self._error(f'a logged request to {srv.srv_name} is unreadable: {err}')
            return
        self.applier.replayed_event(event_ns, readings,
                                    lambda: callback(request, srv_type.Response()))
        self.applier.stats['requests_replayed'] += 1

    def _replay_parameters(self, data: bytes, event_ns: int, readings: list[Reading]) -> None:
        """A logged parameter change, applied again with the node's parameter callbacks."""
        original = self.set_parameters_atomically
        assert original is not None
        try:
            result = self.applier.replayed_event(
                event_ns, readings, lambda: original(node_parameters.unpack(data)))
        except (ParameterException, ValueError) as err:
            self._error(f'a logged parameter change failed again in replay: {err}')
            return
        self.applier.stats['parameter_changes_replayed'] += 1
        if not result.successful:
            self._error(f'a logged parameter change was refused in replay: {result.reason}')
