"""Managed (lifecycle) variants of feature_node, matcher_node and mapping_node.

``ros2 run semfeat_ros feature_node_managed`` (and ``matcher_node_managed``,
``mapping_node_managed``) starts the node unconfigured, under the same name and with the same
parameters as the plain node, which stays the default. The transitions (``ros2 lifecycle set``,
a lifecycle manager, or the ``lifecycle_msgs`` services ``~/change_state``, ``~/get_state``):

* configure: reads the parameters and builds what the plain node builds at start-up, but the
  subscriptions: the network with its weights (feature_node), the matcher, the mapping worker,
  publishers (lifecycle publishers: they send only while active; ``/diagnostics`` reports
  in every configured state), services and timers. A parameter or weights problem fails the
  transition with the reason logged; the node stays unconfigured.
* activate: creates the subscriptions and enables the publishers.
* deactivate: destroys the subscriptions and disables the publishers (the silent-input watch
  stops with them).
* cleanup: stops the worker threads, frees the network / matcher / map and destroys what
  configure created.
* shutdown (from any state): as cleanup; mapping_node first saves the map when
  ``save_on_shutdown`` is set.

Parameters that may change at run time on the plain node may change here in any state; the
others are read-only, as on the plain node (set them in the parameter file or on the command
line). Each node keeps its wiring in ``declare()``, ``setup()``, ``subscribe_inputs()`` and
``release()``, which the plain node runs at start-up and this module runs per transition.
"""
from __future__ import annotations

import sys
from typing import Any

from rclpy.executors import SingleThreadedExecutor
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.lifecycle import LifecycleNode, LifecyclePublisher, LifecycleState
from rclpy.lifecycle import TransitionCallbackReturn as Result

from semfeat_ros.nodes.diagnostics import spin_node
from semfeat_ros.nodes.feature_node import FeatureNode
from semfeat_ros.nodes.mapping_node import MappingNode
from semfeat_ros.nodes.matcher_node import MatcherNode
from semfeat_ros.nodes.params import read_config


class Managed:
    """The lifecycle transitions over a plain node's ``declare / setup / subscribe_inputs /
    release``; first base of a class whose next bases are the plain node and
    :class:`~rclpy.lifecycle.LifecycleNode`."""

    node_name = ''

    def __init__(self, **kwargs: Any) -> None:
        LifecycleNode.__init__(self, self.node_name, **kwargs)
        self._is_configured = False
        self._created: dict[str, list[Any]] = {}  # what configure created, by kind
        self._inputs: list[Any] = []  # subscriptions activate created
        self._guard_change_state()
        self.declare()
        self.get_logger().info(f'{self.node_name} unconfigured: configure loads its parameters '
                               'and model, activate subscribes')

    def _guard_change_state(self) -> None:
        """Answer a transition the current state does not have (e.g. activate while
        unconfigured) with success=False: rclpy's ~/change_state raises on it, which would end
        the node's executor."""
        service = self._service_change_state
        handle = service.callback

        def guarded(request: Any, response: Any) -> Any:
            try:
                return handle(request, response)
            except _rclpy.RCLError as exc:
                self.get_logger().warning(
                    f'transition {request.transition.id} refused in state '
                    f'{self._state_machine.current_state[1]}: {exc}')
                response.success = False
                return response

        service.callback = guarded

    def _entities(self) -> dict[str, set[Any]]:
        return {'publisher': set(self.publishers), 'service': set(self.services),
                'timer': set(self.timers), 'client': set(self.clients)}

    def on_configure(self, state: LifecycleState) -> Result:
        before = self._entities()
        try:
            self.conf = read_config(self, type(self.conf))
            self.setup()
        except (OSError, ValueError) as exc:  # missing weights, bad parameters or config files
            self.get_logger().error(f'configure failed: {exc}')
            failed = exc
        else:
            failed = None
        self._is_configured = True
        self._created = {kind: [e for e in now if e not in before[kind]]
                         for kind, now in self._entities().items()}
        if failed is not None:
            self._teardown()
            return Result.FAILURE
        return super().on_configure(state)

    def on_activate(self, state: LifecycleState) -> Result:
        before = set(self.subscriptions)
        self.subscribe_inputs()
        self._inputs = [s for s in self.subscriptions if s not in before]
        self.get_logger().info(f'active: {len(self._inputs)} subscriptions')
        return super().on_activate(state)

    def on_deactivate(self, state: LifecycleState) -> Result:
        self._unsubscribe()
        self.get_logger().info('inactive: subscriptions destroyed')
        return super().on_deactivate(state)

    def on_cleanup(self, state: LifecycleState) -> Result:
        self._teardown()
        self.get_logger().info('unconfigured: model and outputs freed')
        return super().on_cleanup(state)

    def on_shutdown(self, state: LifecycleState) -> Result:
        if self._is_configured:
            self.on_exit()
        self._teardown()
        return super().on_shutdown(state)

    def on_error(self, state: LifecycleState) -> Result:
        self._teardown()  # back to unconfigured
        return super().on_error(state)

    def on_exit(self) -> None:
        """What the plain node does when it goes away, before the shutdown's cleanup."""

    def _unsubscribe(self) -> None:
        for sub in self._inputs:
            self.destroy_subscription(sub)
        self._inputs = []
        health = getattr(self, 'health', None)
        if health is not None:
            health.io.forget_inputs()

    def _teardown(self) -> None:
        """Undo activate and configure (whatever of them happened)."""
        self._unsubscribe()
        if not self._is_configured:
            return
        try:
            self.release()
        except AttributeError:  # a configure that failed before creating the workers
            pass
        for pub in self._created.get('publisher', []):
            if isinstance(pub, LifecyclePublisher):
                self.destroy_lifecycle_publisher(pub)
            else:
                self.destroy_publisher(pub)
        for srv in self._created.get('service', []):
            self.destroy_service(srv)
        for timer in self._created.get('timer', []):
            self.destroy_timer(timer)
        for client in self._created.get('client', []):
            self.destroy_client(client)
        self._created, self._is_configured = {}, False

    def destroy_node(self) -> None:
        """The node goes away (Ctrl-C included): as a shutdown transition."""
        if self._is_configured:
            self.on_exit()
        self._teardown()
        LifecycleNode.destroy_node(self)


class ManagedFeatureNode(Managed, FeatureNode, LifecycleNode):
    node_name = 'feature_node'


class ManagedMatcherNode(Managed, MatcherNode, LifecycleNode):
    node_name = 'matcher_node'


class ManagedMappingNode(Managed, MappingNode, LifecycleNode):
    node_name = 'mapping_node'

    def on_exit(self) -> None:
        self.save_on_exit()


def feature_main(args: list[str] | None = None) -> None:
    spin_node('feature_node', ManagedFeatureNode, SingleThreadedExecutor, args)


def matcher_main(args: list[str] | None = None) -> None:
    spin_node('matcher_node', ManagedMatcherNode, SingleThreadedExecutor, args)


def mapping_main(args: list[str] | None = None) -> None:
    spin_node('mapping_node', ManagedMappingNode, SingleThreadedExecutor, args)


MAINS = {'feature_node': feature_main, 'matcher_node': matcher_main,
         'mapping_node': mapping_main}

if __name__ == '__main__':
    # python -m semfeat_ros.nodes.managed <node> [--ros-args ...]
    if len(sys.argv) < 2 or sys.argv[1] not in MAINS:
        sys.exit(f'usage: python -m semfeat_ros.nodes.managed {{{",".join(MAINS)}}} '
                 '[--ros-args ...]')
    MAINS[sys.argv[1]]([sys.argv[0], *sys.argv[2:]])
