"""QoS of the nodes' subscriptions and publishers, and the watch on their inputs.

:class:`Endpoints` creates every subscription and publisher of a node with

* QoS overrides: the parameters ``qos_overrides.<topic>.<publisher|subscription>.<policy>``
  (history, depth, reliability) may replace a profile at start-up, as on any ROS 2 node;
* incompatible-QoS events logged (throttled) and counted (``qos_incompatible``), so a
  publisher that is never matched is reported instead of silently sending nothing;
* for the inputs a node cannot work without, the time since their last message: an input
  silent for ``input_timeout_s`` is logged and reported as an ERROR by ``/diagnostics``.

On a managed (lifecycle) node the publishers are lifecycle publishers, which send only while
the node is active (``/diagnostics`` excepted: it reports an inactive node too).

Sensor inputs default to best effort (:func:`input_qos`): a best-effort subscription matches
reliable and best-effort publishers alike, so any camera, odometry or GNSS driver connects.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
import time
from typing import Any

from rclpy.event_handler import PublisherEventCallbacks, SubscriptionEventCallbacks
from rclpy.lifecycle import LifecycleNodeMixin
from rclpy.node import Node
from rclpy.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    QoSPolicyKind,
    QoSProfile,
    ReliabilityPolicy,
)
from rclpy.qos_overriding_options import QoSOverridingOptions

RELIABILITY = {'best_effort': ReliabilityPolicy.BEST_EFFORT,
               'reliable': ReliabilityPolicy.RELIABLE}


def input_qos(reliability: str = 'best_effort', depth: int = 10) -> QoSProfile:
    """Subscription profile of a sensor input: keep-last ``depth``, volatile."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth,
                      reliability=RELIABILITY[reliability],
                      durability=DurabilityPolicy.VOLATILE)


@dataclass
class WatchedInput:
    """An input that must not fall silent: its topic and when it last delivered."""

    name: str
    topic: str
    last: float  # time.monotonic() of the last message (start-up before the first)
    received: bool = False
    last_warning: float = float('-inf')


class Endpoints:
    """The subscriptions and publishers of one node (see the module docstring)."""

    def __init__(self, node: Node, input_timeout_s: float = 0.0):
        self._node = node
        self.input_timeout_s = input_timeout_s
        self.incompatible = 0
        self.inputs: dict[str, WatchedInput] = {}

    def subscribe(self, msg_type: Any, topic: str, callback: Callable[[Any], None],
                  qos: QoSProfile | int, *, watch: str | None = None) -> Any:
        """A subscription; ``watch`` names an input reported when silent."""
        events = SubscriptionEventCallbacks(
            incompatible_qos=lambda info: self._on_incompatible(topic, 'subscription', info))
        if watch is not None:
            entry = WatchedInput(watch, topic, time.monotonic())

            def cb(msg: Any) -> None:
                entry.last, entry.received = time.monotonic(), True
                callback(msg)
        else:
            entry, cb = None, callback
        sub = self._node.create_subscription(
            msg_type, topic, cb, qos, event_callbacks=events,
            qos_overriding_options=QoSOverridingOptions.with_default_policies())
        if entry is not None:
            entry.topic = sub.topic_name
            self.inputs[watch] = entry
        return sub

    def publish(self, msg_type: Any, topic: str, qos: QoSProfile | int, *,
                managed: bool = True) -> Any:
        """A publisher; on a lifecycle node a lifecycle publisher (sends only while active)
        unless ``managed`` is False."""
        events = PublisherEventCallbacks(
            incompatible_qos=lambda info: self._on_incompatible(topic, 'publisher', info))
        create = self._node.create_publisher
        if managed and isinstance(self._node, LifecycleNodeMixin):
            create = self._node.create_lifecycle_publisher
        return create(
            msg_type, topic, qos, event_callbacks=events,
            qos_overriding_options=QoSOverridingOptions.with_default_policies())

    def forget_inputs(self) -> None:
        """Stop watching the inputs (their subscriptions are gone: a managed node's
        deactivate)."""
        self.inputs.clear()

    def _on_incompatible(self, topic: str, side: str, info: Any) -> None:
        self.incompatible += max(1, int(info.total_count_change))
        try:
            policy = QoSPolicyKind(info.last_policy_kind).name.lower()
        except ValueError:
            policy = str(info.last_policy_kind)
        other = 'publisher' if side == 'subscription' else 'subscription'
        self._node.get_logger().warning(
            f'incompatible QoS on {topic}: a {other} is not matched ({policy}); '
            f'{self.incompatible} so far', throttle_duration_sec=5.0)

    def silent(self) -> list[str]:
        """One line per watched input silent for ``input_timeout_s`` (none when 0); each is
        also logged, at most once per max(timeout, 10 s) per input."""
        if self.input_timeout_s <= 0:
            return []
        now = time.monotonic()
        out = []
        for w in self.inputs.values():
            age = now - w.last
            if age < self.input_timeout_s:
                continue
            n = self._node.count_publishers(w.topic)
            hint = ('no publisher' if n == 0 else
                    f'{n} publisher{"s" if n > 1 else ""}: is it publishing? QoS?')
            line = (f'no {w.name} for {age:.0f} s on {w.topic}'
                    f'{"" if w.received else " since start-up"} ({hint})')
            out.append(line)
            if now - w.last_warning >= max(self.input_timeout_s, 10.0):
                w.last_warning = now
                self._node.get_logger().warning(line)
        return out
