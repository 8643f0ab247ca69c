"""semfeat-play and semfeat-record over DDS: a player process, a recorder process (or the
record() API in this process), an isolated domain per test (80-89)."""
from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
import signal
import threading
import time

import numpy as np
import pytest
import rclpy
from rclpy.context import Context
from rosbags.interfaces import QosDurability
from rosbags.rosbag2 import Reader
from test_bagtools_common import (
    CHATTER,
    IMAGE,
    NS,
    ODOM,
    STORE,
    T0_NS,
    T,
    Tool,
    payloads,
    qos,
    read_bag,
    sample_messages,
    timing_deviation_ms,
    write_bag,
)
import yaml

from semfeat_ros.tools.record import record

#: Max |recorded - scheduled| inter-message timing deviation accepted (ms). Measured ~1 ms on
#: an idle machine; the margin covers 2 cores shared with other jobs.
TIMING_TOL_MS = 30.0


@pytest.fixture(autouse=True)
def _no_stray_tools() -> Iterator[None]:
    """A failed test must not leave a recorder subscribed on its domain."""
    yield
    Tool.kill_all()


@pytest.mark.parametrize('in_storage,out_format,rate,domain', [
    ('mcap', 'sqlite3', 1.0, 80),
    ('sqlite3', 'mcap', 2.0, 81),
])
def test_roundtrip_bytes_and_timing(tmp_path: Path, in_storage: str, out_format: str,
                                    rate: float, domain: int) -> None:
    """Every payload arrives byte-identical, with the bag's timing (scaled by --rate)."""
    played = write_bag(tmp_path / 'in', sample_messages(), in_storage)
    out = tmp_path / 'out'
    rec = Tool('record', [out, '--topics', IMAGE, CHATTER, ODOM, '--format', out_format],
               domain)
    # Started together: the player waits until the recorder subscribed to every topic.
    player = Tool('play', [tmp_path / 'in', '--rate', rate, '--wait-for-subscribers', 1],
                  domain)
    code, stdout, stderr = player.finish()
    assert code == 0, stderr
    assert 'done: 35 messages' in stdout and f'{CHATTER}: 5 messages' in stdout
    time.sleep(0.3)
    code, rec_out, rec_err = rec.finish(signal.SIGINT)
    assert code == 0, rec_err
    assert f'{IMAGE}: 10 messages' in rec_out

    recorded = read_bag(out)
    assert set(recorded) == set(played)
    for topic, msgs in played.items():  # the bytes published are the bag's, untouched
        assert payloads(recorded[topic]) == payloads(msgs, padded=True), topic
    dev = timing_deviation_ms(played, recorded, rate)
    assert np.abs(dev).max() < TIMING_TOL_MS, dev
    bag_span = (T0_NS + 950_000_000 - T0_NS) / NS
    rec_stamps = [t for msgs in recorded.values() for t, _ in msgs]
    assert (max(rec_stamps) - min(rec_stamps)) / NS == pytest.approx(
        bag_span / rate, abs=TIMING_TOL_MS / 1e3)

    meta = yaml.safe_load((out / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    assert meta['version'] == 9 and meta['storage_identifier'] == out_format
    assert meta['message_count'] == 35
    topics = {t['topic_metadata']['name']: t['topic_metadata']
              for t in meta['topics_with_message_count']}
    assert topics[IMAGE]['type'] == 'sensor_msgs/msg/Image'
    assert topics[IMAGE]['type_description_hash'].startswith('RIHS01_')
    assert topics[IMAGE]['offered_qos_profiles'][0]['reliability'] == 'reliable'


@pytest.mark.parametrize('domain', [82])
def test_clock_topics_remap_and_stamps(tmp_path: Path, domain: int) -> None:
    """--clock publishes a monotonic /clock (100 Hz and with every message); --topics filters;
    --remap renames; the recorder stamps by header (--stamp header) or by /clock
    (--use-sim-time)."""
    played = write_bag(tmp_path / 'in', sample_messages(), 'mcap')
    out_h, out_s = tmp_path / 'by_header', tmp_path / 'by_clock'
    rec_h = Tool('record', [out_h, '--topics', '/clock', IMAGE, '/talk', CHATTER, ODOM,
                            '--stamp', 'header', '--ros-args', '-r', '__node:=rec_h'], domain)
    rec_s = Tool('record', [out_s, '--topics', IMAGE, '/talk', '--use-sim-time',
                            '--ros-args', '-r', '__node:=rec_s'], domain)
    player = Tool('play', [tmp_path / 'in', '--clock', '--topics', IMAGE, CHATTER,
                           '--remap', f'{CHATTER}:=/talk', '--wait-for-subscribers', 2], domain)
    code, stdout, stderr = player.finish()
    assert code == 0, stderr
    time.sleep(0.3)
    results = [rec.finish(signal.SIGINT) for rec in (rec_h, rec_s)]
    for code, _, err in results:
        assert code == 0, err
    assert f'{ODOM}: no publisher appeared' in results[0][1]
    assert f'{CHATTER}: no publisher appeared' in results[0][1]

    by_header = read_bag(out_h)
    assert set(by_header) == {'/clock', IMAGE, '/talk'}  # odom filtered out, chatter renamed
    assert payloads(by_header['/talk']) == payloads(played[CHATTER], padded=True)
    assert payloads(by_header[IMAGE]) == payloads(played[IMAGE], padded=True)
    # --stamp header: images carry their header stamp = bag time exactly.
    assert [t for t, _ in by_header[IMAGE]] == [t for t, _ in played[IMAGE]]

    clock_type = 'rosgraph_msgs/msg/Clock'
    ticks = [STORE.deserialize_cdr(d, clock_type).clock for _, d in by_header['/clock']]
    ticks_ns = np.array([c.sec * NS + c.nanosec for c in ticks])
    assert np.all(np.diff(ticks_ns) > 0), 'clock must be strictly increasing'
    message_stamps = {t for topic in (IMAGE, CHATTER) for t, _ in played[topic]}
    assert min(message_stamps) <= ticks_ns[0] and ticks_ns[-1] <= max(message_stamps)
    assert len(ticks_ns) >= 50, 'about 100 Hz over 0.93 s expected'
    assert len(message_stamps & set(ticks_ns.tolist())) >= 0.8 * len(message_stamps)
    # Stamped with ROS time from /clock: close to the bag time (within a few clock periods).
    by_clock = read_bag(out_s)
    sim = np.array([t for t, _ in by_clock[IMAGE]], dtype=np.int64)
    bag = np.array([t for t, _ in played[IMAGE]], dtype=np.int64)
    assert np.abs(sim - bag).max() < 50_000_000, (sim - bag) / 1e6


@pytest.mark.ros_domain(83)
def test_latched_topic_recorded_late(tmp_path: Path, isolated_ros: int) -> None:
    """A transient_local topic in the bag is replayed latched, and the recorder (the record()
    API, in this process) subscribes transient_local, so it gets the message although it
    starts after it was published."""
    cloud = T['sensor_msgs/msg/PointCloud2'](
        T['std_msgs/msg/Header'](T['builtin_interfaces/msg/Time'](1_700_000_000, 0), 'map'),
        1, 2, [T['sensor_msgs/msg/PointField']('x', 0, 7, 1)], False, 4, 8,
        np.arange(8, dtype=np.uint8), True)
    msgs = [('/semantic_cloud', 'sensor_msgs/msg/PointCloud2', T0_NS, cloud)]
    msgs += [('/tick', 'std_msgs/msg/String', T0_NS + i * 100_000_000,
              T['std_msgs/msg/String'](str(i))) for i in range(100)]
    latched = qos(durability=QosDurability.TRANSIENT_LOCAL, depth=1)
    played = write_bag(tmp_path / 'in', msgs, 'mcap', offered={'/semantic_cloud': [latched]})
    player = Tool('play', [tmp_path / 'in'], isolated_ros)
    player.wait_for('playing')
    time.sleep(0.4)  # the cloud is out before the recorder exists

    seen: dict[str, int] = {}
    stop = threading.Event()

    def written(topic: str, size: int) -> None:
        seen[topic] = seen.get(topic, 0) + 1
        if seen.get('/semantic_cloud') and seen.get('/tick', 0) >= 3:
            stop.set()

    ctx = Context()
    rclpy.init(context=ctx)
    timeout = threading.Timer(15.0, stop.set)
    timeout.start()
    try:
        stats = record(tmp_path / 'out', {'topics': ['/semantic_cloud', '/tick'],
                                          'progress': False}, stop, context=ctx,
                       on_written=written)
    finally:
        timeout.cancel()
        rclpy.try_shutdown(context=ctx)
    code, stdout, stderr = player.finish(signal.SIGINT)
    assert code == 0, stderr
    assert '/semantic_cloud: 1 messages [sensor_msgs/msg/PointCloud2, ' \
           'reliable/transient_local/depth 1]' in stdout
    assert stats.qos['/semantic_cloud'] == 'reliable/transient_local'
    assert stats.recorded['/semantic_cloud'] == 1 and stats.recorded['/tick'] >= 3
    recorded = read_bag(tmp_path / 'out')
    assert len(played['/semantic_cloud'][0][1]) % 4 != 0  # exercises the DDS padding
    assert payloads(recorded['/semantic_cloud']) == payloads(played['/semantic_cloud'], True)
    with Reader(tmp_path / 'out') as reader:  # the latched QoS is kept for a later replay
        conn = next(c for c in reader.connections if c.topic == '/semantic_cloud')
        assert conn.ext.offered_qos_profiles[0].durability == QosDurability.TRANSIENT_LOCAL


@pytest.mark.parametrize('domain', [84])
def test_signals_stop_cleanly(tmp_path: Path, domain: int) -> None:
    """SIGINT stops a looping player, SIGTERM a recorder: both exit 0 with their report, and
    the recorder's bag is closed (metadata.yaml written, readable)."""
    write_bag(tmp_path / 'in', sample_messages(), 'sqlite3')
    rec = Tool('record', [tmp_path / 'out', '--topics', CHATTER], domain)
    player = Tool('play', [tmp_path / 'in', '--loop', '--rate', 2, '--clock', 50,
                           '--wait-for-subscribers', 1, '--wait-topics', CHATTER], domain)
    player.wait_for('playing')
    time.sleep(1.1)  # > 2 passes of 0.47 s
    code, stdout, stderr = player.finish(signal.SIGINT)
    assert code == 0, stderr
    assert 'interrupted' in stdout and 'Traceback' not in stderr
    passes = int(stdout.split(' complete pass')[0].rsplit('(', 1)[1])
    assert passes >= 2
    code, rec_out, rec_err = rec.finish(signal.SIGTERM)
    assert code == 0, rec_err
    assert 'Traceback' not in rec_err
    recorded = read_bag(tmp_path / 'out')
    assert len(recorded[CHATTER]) >= 5 * passes
