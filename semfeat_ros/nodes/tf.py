"""TF for the nodes: 4x4 transforms as ``TransformStamped`` and a store of static transforms.

Transforms follow tf2's convention: ``T_parent_child`` maps points of the child frame into the
parent frame (the header's ``frame_id`` is the parent, ``child_frame_id`` the child). QoS as
tf2_ros uses them: /tf reliable, volatile, depth 100; /tf_static reliable, transient-local
(latched), one message carrying every static transform of its publisher.
"""
from __future__ import annotations

import threading

from geometry_msgs.msg import TransformStamped
import numpy as np
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from msg_adapters.errors import MessageError, NonFiniteError
from msg_adapters.nav import matrix_to_quaternion, quaternion_to_matrix
from msg_adapters.stamp import ns_to_stamp

TF_QOS = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE,
                    durability=DurabilityPolicy.VOLATILE, history=HistoryPolicy.KEEP_LAST)
TF_STATIC_PUB_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                               durability=DurabilityPolicy.TRANSIENT_LOCAL,
                               history=HistoryPolicy.KEEP_LAST)
TF_STATIC_SUB_QOS = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE,
                               durability=DurabilityPolicy.TRANSIENT_LOCAL,
                               history=HistoryPolicy.KEEP_LAST)
MAX_CHAIN = 32  # longest static chain followed (a URDF tree is far shallower)


def transform_msg(T: np.ndarray, parent: str, child: str, stamp_ns: int) -> TransformStamped:
    """``TransformStamped`` of the 4x4 ``T`` (child into parent) at ``stamp_ns``."""
    msg = TransformStamped()
    msg.header.stamp = ns_to_stamp(int(stamp_ns), type(msg.header.stamp))
    msg.header.frame_id = parent
    msg.child_frame_id = child
    t = msg.transform.translation
    t.x, t.y, t.z = (float(v) for v in T[:3, 3])
    q = msg.transform.rotation
    q.x, q.y, q.z, q.w = matrix_to_quaternion(T[:3, :3])
    return msg


def transform_to_matrix(msg: TransformStamped) -> np.ndarray:
    """4x4 of a ``TransformStamped``; non-finite values or a zero quaternion raise
    :class:`MessageError`."""
    t, q = msg.transform.translation, msg.transform.rotation
    T = np.eye(4)
    T[:3, :3] = quaternion_to_matrix(q.x, q.y, q.z, q.w)
    T[:3, 3] = (t.x, t.y, t.z)
    if not np.isfinite(T).all():
        raise NonFiniteError(f'transform {msg.header.frame_id} -> {msg.child_frame_id}: '
                             'non-finite translation')
    if not msg.header.frame_id or not msg.child_frame_id:
        raise MessageError('transform without frame_id or child_frame_id')
    return T


class StaticFrames:
    """Static transforms seen on /tf_static (thread-safe): each child frame with its parent."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._parent: dict[str, tuple[str, np.ndarray]] = {}

    def add(self, parent: str, child: str, T: np.ndarray) -> bool:
        """Store ``T_parent_child``; True when it is new or changed."""
        with self._lock:
            old = self._parent.get(child)
            self._parent[child] = (parent, T)
        return old is None or old[0] != parent or not np.allclose(old[1], T, atol=1e-9)

    def lookup(self, target: str, child: str) -> np.ndarray | None:
        """``T_target_child`` composed along the stored parents of ``child``, or None when
        ``target`` is not among them."""
        T = np.eye(4)
        frame = child
        with self._lock:
            for _ in range(MAX_CHAIN):
                if frame == target:
                    return T
                link = self._parent.get(frame)
                if link is None:
                    return None
                frame, T = link[0], link[1] @ T
        return None
