"""A separate process on the DDS graph: publishes or receives one sensor_msgs/Image pattern.

usage: dds_peer.py pub|sub WIDTH HEIGHT TIMEOUT_S
The subscriber prints ``OK <sha256>`` of the received pixels and exits 0, or exits 1 on timeout.
"""
from __future__ import annotations

import hashlib
import sys
import time

import numpy as np
import rclpy
from rclpy.node import Node
from sensor_msgs.msg import Image


def pattern(width: int, height: int) -> np.ndarray:
    y, x = np.mgrid[0:height, 0:width]
    return np.stack([x % 256, y % 256, (x + y) % 256], axis=2).astype(np.uint8)


def main() -> int:
    role, width, height, timeout = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), float(
        sys.argv[4])
    rclpy.init()
    node = Node(f'dds_peer_{role}')
    deadline = time.monotonic() + timeout
    try:
        if role == 'pub':
            pub = node.create_publisher(Image, '/camera/front/image_raw', 10)
            img = pattern(width, height)
            msg = Image(height=height, width=width, encoding='rgb8', step=width * 3,
                        data=img.tobytes())
            msg.header.frame_id = 'camera_front_optical'
            while time.monotonic() < deadline:
                pub.publish(msg)
                rclpy.spin_once(node, timeout_sec=0.05)
            return 0
        received: list[Image] = []
        node.create_subscription(Image, '/camera/front/image_raw', received.append, 10)
        while time.monotonic() < deadline and not received:
            rclpy.spin_once(node, timeout_sec=0.1)
        if not received:
            print('TIMEOUT', flush=True)
            return 1
        m = received[0]
        data = np.frombuffer(bytes(m.data), np.uint8).reshape(m.height, m.width, 3)
        print('OK', m.encoding, m.header.frame_id, hashlib.sha256(data.tobytes()).hexdigest(),
              flush=True)
        return 0
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == '__main__':
    sys.exit(main())
