"""Derive test bags from the bundled recording: cut, inject garbage frames, make time jump."""
from __future__ import annotations

from pathlib import Path

from rosbags.highlevel import AnyReader
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

TS = get_typestore(Stores.ROS2_JAZZY)
CAMERA = '/camera/front/image_raw/compressed'


def craft(src: Path, dst: Path, *, seconds: float, garbage_every: int = 0,
          jump_back_s: float = 0.0, repeat_s: float = 0.0,
          corrupt_all: bool = False) -> dict[str, int]:
    """Write ``dst`` from the first ``seconds`` of ``src``.

    ``garbage_every``: after every k-th camera frame add one whose JPEG is cut to a third.
    ``corrupt_all``: every camera frame's JPEG is cut to a third (no frame decodes).
    ``repeat_s``/``jump_back_s``: then append the first ``repeat_s`` seconds again with header
    stamps moved back by ``jump_back_s`` relative to the end (log time keeps increasing, as after
    a bag loop on the sender), so the nodes see time going backwards.
    Returns counts of what was written.
    """
    counts = {'frames': 0, 'garbage': 0, 'repeated': 0}
    with AnyReader([src], default_typestore=TS) as reader:
        conns = list(reader.connections)
        t0 = reader.start_time
        end = t0 + int(seconds * 1e9)
        rows = [(c, t, raw) for c, t, raw in reader.messages(connections=conns) if t < end]
        with Writer(dst, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
            out = {}
            for c in conns:
                out[c.topic] = writer.add_connection(c.topic, c.msgtype, typestore=TS,
                                                     serialization_format='cdr',
                                                     offered_qos_profiles=c.ext.offered_qos_profiles)

            def write(c, t: int, raw: bytes) -> None:
                writer.write(out[c.topic], t, raw)

            for c, t, raw in rows:
                if corrupt_all and c.topic == CAMERA:
                    msg = TS.deserialize_cdr(raw, c.msgtype)
                    msg.data = msg.data[: len(msg.data) // 3].copy()
                    raw = bytes(TS.serialize_cdr(msg, c.msgtype))
                write(c, t, raw)
                if c.topic == CAMERA:
                    counts['frames'] += 1
                    if garbage_every and counts['frames'] % garbage_every == 0:
                        msg = TS.deserialize_cdr(raw, c.msgtype)
                        msg.data = msg.data[: len(msg.data) // 3].copy()
                        write(c, t + 1_000_000, bytes(TS.serialize_cdr(msg, c.msgtype)))
                        counts['garbage'] += 1
            if repeat_s > 0:
                shift_log = end - t0 + int(0.1e9)
                shift_hdr = shift_log - int(jump_back_s * 1e9) - (end - t0)
                for c, t, raw in rows:
                    if t >= t0 + int(repeat_s * 1e9):
                        break
                    msg = TS.deserialize_cdr(raw, c.msgtype)
                    if hasattr(msg, 'header'):
                        ns = msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec + shift_hdr
                        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(ns, 10**9)
                    write(c, t + shift_log, bytes(TS.serialize_cdr(msg, c.msgtype)))
                    counts['repeated'] += c.topic == CAMERA
    return counts
