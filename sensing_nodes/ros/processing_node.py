"""The five processing nodes' base: a node that its configure() builds, plain (the default:
configured and activated at construction, processing at once) or managed (a ROS 2 lifecycle
node, brought up through lifecycle_msgs services as nav2's lifecycle manager and `ros2 lifecycle
set` do).

The read-only `lifecycle` parameter (default false), read before anything else, selects managed.
A managed node starts unconfigured, with no publisher, subscription, timer or service of its own
but its lifecycle services (`~/change_state`, `~/get_state`, ...):

- configure: configure() declares and checks the parameters and makes the processor, its
  diagnostics, publishers, subscriptions, services and timers. A value the node cannot run with
  fails the transition with the message a plain node exits with; the node stays unconfigured.
  While unconfigured the parameters are writable (`ros2 param set`: rclpy stores the value,
  configure checks its type and range), while configured they are refused.
- activate: publishers send (/diagnostics too), inputs are processed, timers run.
- deactivate: publishers send nothing, timers stop; inputs that arrive are dropped unprocessed
  and counted (`dropped_inactive` on /diagnostics once active again).
- cleanup: everything configure made is destroyed; the parameters stay, writable again.
- shutdown (from any state): as cleanup, then finalized.
"""

from __future__ import annotations

import traceback
from typing import Any, Callable

from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult
from rclpy.impl.implementation_singleton import rclpy_implementation
from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn
from rclpy.lifecycle.node import LifecycleNodeMixin
from rclpy.lifecycle.publisher import LifecyclePublisher
from rclpy.node import Node

from sensing_nodes.ros.run import _PARAMETER_ERRORS

LIFECYCLE_PARAMETER = 'lifecycle'
SUCCESS, FAILURE = TransitionCallbackReturn.SUCCESS, TransitionCallbackReturn.FAILURE
# Changes to it are the clock's business, not the configuration's (rclpy takes them any time).
_ALWAYS_SETTABLE = frozenset({'use_sim_time'})


def _ignore(*args: Any) -> None:
    """What a destroyed subscription or timer does with an event queued before it was."""


class ProcessingNode(LifecycleNode):
    """A processing node built by configure() (a subclass's): plain, or managed with
    `lifecycle` true (or `lifecycle=True` given). configure() sets self.processor and
    self.diagnostics (ros/diagnostics.py) and gives its subscriptions' callbacks through
    when_active (ros/processor.wire does); managed, its publishers are lifecycle publishers."""

    managed = False   # until __init__ has read `lifecycle`: Node.__init__'s publishers are plain

    def __init__(self, node_name: str, *, lifecycle: bool | None = None,
                 **node_options: Any) -> None:
        # LifecycleNode.__init__'s two steps apart: whether the lifecycle services exist is a
        # parameter, readable only once the node exists.
        Node.__init__(self, node_name, **node_options)
        if lifecycle is None:
            lifecycle = self.declare_parameter(LIFECYCLE_PARAMETER, False, ParameterDescriptor(
                description='managed (lifecycle) node: starts unconfigured and is brought up '
                            'through its lifecycle services; false: processes from start-up',
                read_only=True)).value
        LifecycleNodeMixin.__init__(self, enable_communication_interface=lifecycle)
        self.managed = lifecycle
        self.active = False
        self._before: tuple[dict[str, list], set[str]] | None = None   # None: unconfigured
        self._failure: BaseException | None = None
        if self.managed:
            self._refuse_unavailable_transitions()
            self.add_on_set_parameters_callback(self._settable)
            self.get_logger().info(
                'managed (lifecycle): unconfigured until configured and activated through '
                f'{self.get_fully_qualified_name()}/change_state')
            return
        for transition in (self.trigger_configure, self.trigger_activate):
            if transition() != SUCCESS:
                raise self._failure   # a bad parameter: run_node reports it and exits with 2

    def configure(self) -> None:
        """Declare and check the parameters, make the processor, diagnostics, publishers,
        subscriptions, services and timers (ParameterError for a value it cannot run with)."""
        raise NotImplementedError

    def when_active(self, callback: Callable[..., Any]) -> Callable[..., Any]:
        """An input's callback: itself in a plain node; in a managed one, what arrives while
        inactive is dropped, counted as dropped_inactive."""
        if not self.managed:
            return callback

        def gated(*args: Any) -> Any:
            if self.active:
                return callback(*args)
            self.diagnostics.count('dropped_inactive')
            return None
        return gated

    def create_publisher(self, *args: Any, **kwargs: Any):
        """A lifecycle publisher in a managed node (sends only while active), else rclpy's."""
        if self.managed:
            return self.create_lifecycle_publisher(*args, **kwargs)
        return super().create_publisher(*args, **kwargs)

    # -- transitions (called by rclpy's state machine) -------------------------------------
    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        before = (self._entities(), set(vars(self)))
        try:
            self.configure()
        except Exception as error:   # noqa: BLE001 - the transition fails, the node lives on
            self._undo(before)
            self._failure = error
            if self.managed:
                if isinstance(error, _PARAMETER_ERRORS):
                    self.get_logger().error(
                        f'invalid parameter: {error}; configure failed, still unconfigured: '
                        'set the parameter (ros2 param set) and configure again')
                else:
                    self.get_logger().error('configure failed, still unconfigured:\n'
                                            + traceback.format_exc())
            return FAILURE
        self._before = before
        if self.managed:
            for timer in self._made('timers'):
                timer.cancel()
            self.get_logger().info('configured (inactive): publishing nothing until activated')
        return SUCCESS

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        super().on_activate(state)   # the lifecycle publishers send from now on
        if self.managed:
            for timer in self._made('timers'):
                timer.reset()
            dropped = self.diagnostics.counts['dropped_inactive']
            self.get_logger().info('active' + (f' ({dropped} inputs dropped while inactive, '
                                               'counted as dropped_inactive)' if dropped else ''))
        self.active = True
        return SUCCESS

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        self.active = False
        for timer in self._made('timers'):
            timer.cancel()
        super().on_deactivate(state)
        self.get_logger().info('inactive: publishing nothing; inputs are dropped and counted '
                               '(dropped_inactive)')
        return SUCCESS

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._undo(self._before)
        self.get_logger().info('cleaned up (unconfigured): parameters may be set again')
        return SUCCESS

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._release()
        self.get_logger().info('shut down (finalized)')
        return SUCCESS

    def on_error(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._release()
        return SUCCESS   # back to unconfigured

    def _release(self) -> None:
        """Inactive, and what configure made destroyed (from any state)."""
        self.active = False
        if self._before is not None:
            self._undo(self._before)

    def _refuse_unavailable_transitions(self) -> None:
        """A transition the current state has not (configure while active) answered with
        success false, as rclcpp's lifecycle nodes do: rclpy 7.1's change_state service raises,
        which ends the process."""
        service = self._service_change_state
        answer = service.callback

        def change_state(request, response):
            try:
                return answer(request, response)
            except rclpy_implementation.RCLError:
                machine = self._state_machine
                self.get_logger().warn(
                    f'transition {request.transition.id} refused: state '
                    f'{machine.current_state[1]} has '
                    + ', '.join(f'{t[1]} ({t[0]})' for t in machine.available_transitions))
                response.success = False
                return response
        service.callback = change_state

    # -- what configure made -----------------------------------------------------------------
    def _entities(self) -> dict[str, list]:
        return {'publishers': list(self.publishers), 'subscriptions': list(self.subscriptions),
                'services': list(self.services), 'clients': list(self.clients),
                'timers': list(self.timers)}

    def _made(self, kind: str, before: tuple[dict[str, list], set[str]] | None = None) -> list:
        """The entities of a kind made since `before` (default: since configure began; none
        while unconfigured)."""
        before = before or self._before
        if before is None:
            return []
        return [e for e in self._entities()[kind] if e not in before[0][kind]]

    def _undo(self, before: tuple[dict[str, list], set[str]]) -> None:
        """Destroy the entities made since `before` and forget the attributes set since: the
        node as it was unconfigured."""
        self.active = False
        destroy = {'publishers': self._destroy_publisher,
                   'subscriptions': self.destroy_subscription, 'services': self.destroy_service,
                   'clients': self.destroy_client, 'timers': self.destroy_timer}
        for kind, made in [(kind, self._made(kind, before)) for kind in destroy]:
            for entity in made:
                if kind in ('subscriptions', 'timers'):
                    # rclpy's EventsExecutor still runs events queued before the entity was
                    # destroyed, with the callback it has then: one of a node cleaned up
                    entity.callback = _ignore
                destroy[kind](entity)
        for name in set(vars(self)) - before[1]:
            delattr(self, name)
        self._before = None

    def _destroy_publisher(self, publisher) -> None:
        if isinstance(publisher, LifecyclePublisher):
            self.destroy_lifecycle_publisher(publisher)
        else:
            self.destroy_publisher(publisher)

    def _settable(self, parameters: list) -> SetParametersResult:
        """Parameters are read at configure: set only while unconfigured."""
        refused = [p.name for p in parameters if p.name not in _ALWAYS_SETTABLE]
        if self._before is None or not refused:
            return SetParametersResult(successful=True)
        return SetParametersResult(successful=False, reason=(
            f'{", ".join(refused)}: parameters are read at configure; clean the node up '
            '(unconfigured) to set them'))
