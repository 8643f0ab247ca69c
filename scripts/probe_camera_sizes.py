"""Probe feature_node with CameraInfo messages of many image sizes: memory, threads, output gaps.

usage: python scripts/probe_camera_sizes.py [--sizes 20] [--repeat 1|3] [--domain 61]

Starts feature_node (shipped weights, onnxruntime) as a process on an isolated localhost domain,
streams 640x512 frames at 5 Hz with their CameraInfo, and sends ``--sizes`` CameraInfo of other
image sizes, each ``--repeat`` times in a row and then the stream's own camera again
(``--repeat 1``: lone outliers; ``--repeat 3``: changes that persist, with
``min_change_interval_s`` 0 so every one is accepted). Prints the node's resident memory (MB) at
the start and end, its peak, its thread count, the longest gap between two feature outputs
(s), the frames processed and the /diagnostics counters.
"""
from __future__ import annotations

import argparse
import os
from pathlib import Path
import subprocess
import sys
import time

import numpy as np

REPO = Path(__file__).resolve().parents[1]


def proc_status(pid: int) -> dict[str, int]:
    """VmRSS and VmHWM (MB) and Threads of process ``pid``."""
    out = {}
    for line in Path(f'/proc/{pid}/status').read_text().splitlines():
        key, _, value = line.partition(':')
        if key in ('VmRSS', 'VmHWM'):
            out[key] = int(value.split()[0]) // 1024
        elif key == 'Threads':
            out[key] = int(value)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--sizes', type=int, default=20)
    ap.add_argument('--repeat', type=int, default=1, choices=(1, 3))
    ap.add_argument('--domain', type=int, default=61)
    args = ap.parse_args(argv)
    env = dict(os.environ, ROS_DOMAIN_ID=str(args.domain),
               ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST', PYTHONUNBUFFERED='1')
    os.environ.update(ROS_DOMAIN_ID=env['ROS_DOMAIN_ID'],
                      ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
    import rclpy
    from rclpy.node import Node
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import CameraInfo, Image, PointCloud2

    from msg_adapters import model_to_camera_info, numpy_to_image
    from semfeat_ros.camera import load_camera_yaml

    node_proc = subprocess.Popen(
        [sys.executable, '-m', 'semfeat_ros.nodes.feature_node', '--ros-args',
         '-p', 'input_reliability:=reliable', '-p', 'warmup_size:=[640, 512]',
         '-p', 'min_change_interval_s:=0.0'], env=env, cwd=REPO,
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    rclpy.init()
    probe = Node('probe_camera_sizes')
    outputs: list[float] = []
    diags: list = []
    probe.create_subscription(PointCloud2, '/semfeat/features',
                              lambda m: outputs.append(time.monotonic()), 10)
    from diagnostic_msgs.msg import DiagnosticArray
    probe.create_subscription(DiagnosticArray, '/diagnostics', diags.append, 10)
    pub_img = probe.create_publisher(Image, '/camera/front/image_raw', QoSProfile(
        depth=2, reliability=ReliabilityPolicy.RELIABLE))
    pub_info = probe.create_publisher(CameraInfo, '/camera/front/camera_info', 10)
    cam = load_camera_yaml()[0].scaled(640, 512)
    rng = np.random.default_rng(0)
    image = rng.integers(0, 255, (512, 640, 3), np.uint8)
    stamp = [1_700_000_000 * 10**9]

    def info(c: object) -> CameraInfo:
        return model_to_camera_info(c, stamp_ns=stamp[0], frame_id='camera_front_optical',
                                    msg_cls=CameraInfo)

    def spin_for(seconds: float, frames: bool = True) -> None:
        end = time.monotonic() + seconds
        next_frame = time.monotonic()
        while time.monotonic() < end:
            if frames and time.monotonic() >= next_frame:
                stamp[0] += 200_000_000
                pub_info.publish(info(cam))
                pub_img.publish(numpy_to_image(image, 'rgb8', stamp_ns=stamp[0],
                                               frame_id='camera_front_optical', msg_cls=Image))
                next_frame += 0.2
            rclpy.spin_once(probe, timeout_sec=0.02)

    try:
        deadline = time.monotonic() + 120
        while pub_img.get_subscription_count() == 0 and time.monotonic() < deadline:
            spin_for(0.2, frames=False)
        spin_for(5.0)  # warm: the first outputs
        before = proc_status(node_proc.pid)
        t_start = time.monotonic()
        peak_threads = before['Threads']
        for i in range(args.sizes):
            other = cam.scaled(640 + 32 * (i + 1), 512)
            for _ in range(args.repeat):
                pub_info.publish(info(other))
                spin_for(0.02, frames=False)
            for _ in range(args.repeat):
                pub_info.publish(info(cam))
                spin_for(0.02, frames=False)
            spin_for(0.5)
            peak_threads = max(peak_threads, proc_status(node_proc.pid)['Threads'])
        spin_for(10.0)
        after = proc_status(node_proc.pid)
        during = [t for t in outputs if t >= t_start]
        gaps = np.diff(during) if len(during) > 1 else np.array([np.inf])
        values = {kv.key: kv.value for kv in diags[-1].status[0].values} if diags else {}
        print(f'sizes {args.sizes} x {args.repeat}: RSS {before["VmRSS"]} -> {after["VmRSS"]} '
              f'MB (peak {after["VmHWM"]} MB), threads {before["Threads"]} -> '
              f'{after["Threads"]} (max {peak_threads}), longest output gap '
              f'{gaps.max():.2f} s, outputs {len(during)} in {time.monotonic() - t_start:.0f} s')
        print('diagnostics: ' + ', '.join(
            f'{k} {values.get(k)}' for k in ('frames_received', 'frames_processed',
                                             'frames_dropped', 'errors_rejected',
                                             'camera_changes', 'change_outliers_ignored',
                                             'processing_errors')))
        return 0
    finally:
        node_proc.terminate()
        node_proc.wait(30)
        probe.destroy_node()
        rclpy.try_shutdown()


if __name__ == '__main__':
    sys.exit(main())
