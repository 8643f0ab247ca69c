"""semfeat-play / semfeat-record building blocks, error handling and the Python APIs."""
from __future__ import annotations

from pathlib import Path
import shutil
import subprocess
import sys
import threading

from conftest import REPO, ros_env
import numpy as np
import pytest
import rclpy
from rclpy.context import Context
from rclpy.duration import Infinite
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rclpy.serialization import deserialize_message, serialize_message
from rosbags.interfaces import QosDurability, QosHistory, QosReliability
from rosbags.rosbag2.metadata import dump_qos_v9, parse_qos
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from test_bagtools_common import (
    CHATTER,
    IMAGE,
    NS,
    STORE,
    T0_NS,
    T,
    dds_padded,
    qos,
    read_bag,
    sample_messages,
    write_bag,
)

from semfeat_ros.tools import play as play_mod
from semfeat_ros.tools import record as record_mod
from semfeat_ros.tools.bagio import (
    has_header_first,
    header_stamp_ns,
    message_definition,
    open_bag,
    profile_to_bag_qos,
    replay_qos,
    resolve_bag_path,
    resolve_message_class,
    split_ros_args,
    subscription_qos,
)
from semfeat_ros.tools.errors import (
    BagConfigError,
    BagFormatError,
    BagNotFoundError,
    BagWriteError,
    UnknownMessageTypeError,
)
from semfeat_ros.tools.play import PlayConfig, plan_topics
from semfeat_ros.tools.record import RecordConfig


@pytest.fixture(scope='module')
def bags(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """A good bag in each storage, and broken variants."""
    root = tmp_path_factory.mktemp('bags')
    out = {s: root / s for s in ('mcap', 'sqlite3')}
    for storage, path in out.items():
        write_bag(path, sample_messages(), storage)
    truncated = root / 'truncated'
    shutil.copytree(out['mcap'], truncated)
    mcap = truncated / 'mcap.mcap'
    mcap.write_bytes(mcap.read_bytes()[: mcap.stat().st_size // 2])  # a recorder killed midway
    corrupt = root / 'corrupt_db3'
    shutil.copytree(out['sqlite3'], corrupt)
    db3 = corrupt / 'sqlite3.db3'
    db3.write_bytes(np.random.default_rng(0).bytes(db3.stat().st_size))
    bad_yaml = root / 'bad_yaml'
    shutil.copytree(out['mcap'], bad_yaml)
    (bad_yaml / 'metadata.yaml').write_text('rosbag2_bagfile_information: [\n  unclosed\n')
    no_meta = root / 'no_metadata'
    shutil.copytree(out['mcap'], no_meta)
    (no_meta / 'metadata.yaml').unlink()
    empty = root / 'empty_dir'
    empty.mkdir()
    text = root / 'notes.txt'
    text.write_text('not a bag')
    out.update(truncated=truncated, corrupt=corrupt, bad_yaml=bad_yaml, no_meta=no_meta,
               empty=empty, text=text, missing=root / 'does_not_exist')
    return out


# --- CDR: rosbags and rclpy agree, DDS padding is harmless ------------------------------------

def test_rosbags_cdr_is_rclpy_cdr() -> None:
    """The premise of raw replay: rclpy reads the bytes rosbags writes, and writes the same
    layout back (same length, same content; Fast CDR may leave alignment padding bytes
    uninitialised, so the comparison goes through rosbags' canonical serialization)."""
    from nav_msgs.msg import Odometry
    from sensor_msgs.msg import Image
    from std_msgs.msg import String

    odd = T['sensor_msgs/msg/Image'](T['std_msgs/msg/Header'](
        T['builtin_interfaces/msg/Time'](3, 7), 'c'), 3, 5, 'mono8', 0, 5,
        np.arange(15, dtype=np.uint8))
    cases = [(m[1], m[3]) for m in sample_messages()] + [('sensor_msgs/msg/Image', odd)]
    classes = {'sensor_msgs/msg/Image': Image, 'nav_msgs/msg/Odometry': Odometry,
               'std_msgs/msg/String': String}
    for type_name, msg in cases:
        data = bytes(STORE.serialize_cdr(msg, type_name))
        from_rclpy = serialize_message(deserialize_message(data, classes[type_name]))
        assert len(from_rclpy) == len(data), type_name
        again = STORE.serialize_cdr(STORE.deserialize_cdr(from_rclpy, type_name), type_name)
        assert bytes(again) == data, type_name


def test_dds_padding_is_ignored_by_readers() -> None:
    from std_msgs.msg import String

    data = bytes(STORE.serialize_cdr(T['std_msgs/msg/String']('abcd'), 'std_msgs/msg/String'))
    padded = dds_padded(data)
    assert len(padded) == len(data) + 3
    assert STORE.deserialize_cdr(padded, 'std_msgs/msg/String').data == 'abcd'
    assert deserialize_message(padded, String).data == 'abcd'


def test_header_stamp_from_raw_cdr() -> None:
    from sensor_msgs.msg import Image
    from std_msgs.msg import String

    stamp = T0_NS + 123_456_789
    topic, type_name, _, msg = next(m for m in sample_messages() if m[0] == IMAGE)
    msg.header.stamp = T['builtin_interfaces/msg/Time'](*divmod(stamp, NS))
    assert header_stamp_ns(bytes(STORE.serialize_cdr(msg, type_name))) == stamp
    big_endian = bytes([0, 0, 0, 0]) + (-2).to_bytes(4, 'big', signed=True) + \
        (5).to_bytes(4, 'big') + b'\0' * 8
    assert header_stamp_ns(big_endian) == -2 * NS + 5
    with pytest.raises(BagFormatError, match='too short'):
        header_stamp_ns(b'\0\1\0\0\0\0')
    with pytest.raises(BagFormatError, match='encapsulation'):
        header_stamp_ns(b'\0\x07' + b'\0' * 12)
    assert has_header_first(Image) and not has_header_first(String)


# --- QoS -----------------------------------------------------------------------------------------

def test_replay_qos_follows_the_recorded_offers() -> None:
    latched = replay_qos([qos(durability=QosDurability.TRANSIENT_LOCAL, depth=0)],
                         ReliabilityPolicy.BEST_EFFORT)
    assert latched.reliability == ReliabilityPolicy.RELIABLE
    assert latched.durability == DurabilityPolicy.TRANSIENT_LOCAL and latched.depth == 1
    mixed = replay_qos([qos(), qos(QosReliability.BEST_EFFORT, depth=5)],
                       ReliabilityPolicy.RELIABLE)
    assert mixed.reliability == ReliabilityPolicy.BEST_EFFORT and mixed.depth == 10
    assert mixed.durability == DurabilityPolicy.VOLATILE
    none = replay_qos([], ReliabilityPolicy.BEST_EFFORT)
    assert none.reliability == ReliabilityPolicy.BEST_EFFORT and none.depth == 10
    forced = replay_qos([qos(durability=QosDurability.TRANSIENT_LOCAL)],
                        ReliabilityPolicy.BEST_EFFORT, override=True)
    assert forced.reliability == ReliabilityPolicy.BEST_EFFORT
    assert forced.durability == DurabilityPolicy.VOLATILE
    unknown = replay_qos([qos(QosReliability.UNKNOWN)], ReliabilityPolicy.BEST_EFFORT)
    assert unknown.reliability == ReliabilityPolicy.BEST_EFFORT


def test_subscription_qos_matches_publishers() -> None:
    rel_latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
    best_effort = QoSProfile(depth=5, reliability=ReliabilityPolicy.BEST_EFFORT)
    sub = subscription_qos([rel_latched], None, 50)
    assert sub.reliability == ReliabilityPolicy.RELIABLE
    assert sub.durability == DurabilityPolicy.TRANSIENT_LOCAL and sub.depth == 50
    sub = subscription_qos([rel_latched, best_effort], None, 50)
    assert sub.reliability == ReliabilityPolicy.BEST_EFFORT
    assert sub.durability == DurabilityPolicy.VOLATILE
    sub = subscription_qos([best_effort], ReliabilityPolicy.RELIABLE, 7)
    assert sub.reliability == ReliabilityPolicy.RELIABLE and sub.depth == 7


def test_offered_qos_survives_the_metadata_round_trip() -> None:
    profile = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL, deadline=Infinite)
    bag_qos = profile_to_bag_qos(profile)
    assert bag_qos.deadline == (9223372036, 854775807)  # what rosbag2 on Jazzy writes
    assert bag_qos.durability == QosDurability.TRANSIENT_LOCAL
    assert bag_qos.history == QosHistory.KEEP_LAST and bag_qos.depth == 1
    assert parse_qos(dump_qos_v9([bag_qos])) == [bag_qos]


# --- types -----------------------------------------------------------------------------------

def test_resolve_message_class() -> None:
    from sensor_msgs.msg import Image
    from std_msgs.msg import String

    assert resolve_message_class('sensor_msgs/msg/Image') is Image
    assert resolve_message_class('std_msgs/String') is String
    with pytest.raises(UnknownMessageTypeError, match='not installed'):
        resolve_message_class('semfeat_nonexistent_msgs/msg/Thing')
    with pytest.raises(UnknownMessageTypeError, match='has no class'):
        resolve_message_class('std_msgs/msg/NoSuchType')
    with pytest.raises(UnknownMessageTypeError, match='malformed'):
        resolve_message_class('Image')


def test_resolve_message_class_imports_only_message_packages(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # a bag names its message types: a type whose package is an ordinary Python module must
    # not be imported (importing runs its code)
    marker = tmp_path / 'imported'
    pkg = tmp_path / 'semfeat_probe_pkg'
    (pkg / 'msg').mkdir(parents=True)
    (pkg / '__init__.py').write_text(f'open({str(marker)!r}, "w").close()\n')
    (pkg / 'msg' / '__init__.py').write_text('class Thing:\n    pass\n')
    (tmp_path / 'semfeat_probe_mod.py').write_text(f'open({str(marker)!r}, "w").close()\n')
    monkeypatch.syspath_prepend(str(tmp_path))
    for name in ('semfeat_probe_pkg/msg/Thing', 'semfeat_probe_mod/msg/Thing',
                 'os.path/msg/Thing', 'sensor_msgs/msg/__class__', '../x/msg/Thing'):
        with pytest.raises(UnknownMessageTypeError):
            resolve_message_class(name)
    assert not marker.exists()
    assert 'semfeat_probe_pkg' not in sys.modules


def test_message_definition_from_installed_msg_files() -> None:
    """With a typestore that lacks the type, the share/<pkg>/msg files give the same definition
    and RIHS01 hash as rosbags' Jazzy store (nested types resolved recursively)."""
    jazzy = get_typestore(Stores.ROS2_JAZZY)
    for type_name in ('nav_msgs/msg/Odometry', 'sensor_msgs/msg/PointCloud2'):
        empty = get_typestore(Stores.EMPTY)
        assert type_name not in empty.fielddefs
        msgdef, digest = message_definition(type_name, empty)
        assert digest == jazzy.hash_rihs01(type_name)
        assert msgdef == jazzy.generate_msgdef(type_name, ros_version=2)[0]
    assert message_definition('nope_msgs/msg/X', None, 'RIHS01_ab') == ('', 'RIHS01_ab')
    with pytest.raises(UnknownMessageTypeError, match='no message definition'):
        message_definition('nope_msgs/msg/X')


def test_split_ros_args() -> None:
    argv = ['bag', '--remap', '/a:=/b', '--ros-args', '-r', '__node:=p', '--', '--loop']
    assert split_ros_args(argv) == (['bag', '--remap', '/a:=/b', '--loop'],
                                    ['--ros-args', '-r', '__node:=p', '--'])
    assert split_ros_args(['x']) == (['x'], [])


# --- bag paths and broken bags --------------------------------------------------------------

def test_bag_paths(bags: dict[str, Path]) -> None:
    assert resolve_bag_path(bags['mcap']) == bags['mcap']
    assert resolve_bag_path(bags['mcap'] / 'metadata.yaml') == bags['mcap']
    assert resolve_bag_path(bags['mcap'] / 'mcap.mcap') == bags['mcap'] / 'mcap.mcap'
    with open_bag(bags['sqlite3'] / 'sqlite3.db3') as reader:
        assert reader.message_count == 35
    with pytest.raises(BagNotFoundError, match='does not exist'):
        resolve_bag_path(bags['missing'])
    with pytest.raises(BagNotFoundError, match="no metadata.yaml in it \\(it holds 'mcap.mcap'"):
        resolve_bag_path(bags['no_meta'])
    with pytest.raises(BagNotFoundError, match='not a rosbag2 directory'):
        resolve_bag_path(bags['empty'])
    with pytest.raises(BagFormatError, match='not a bag'):
        resolve_bag_path(bags['text'])


@pytest.mark.parametrize('name', ['truncated', 'corrupt', 'bad_yaml'])
def test_broken_bags_raise_one_line(bags: dict[str, Path], name: str) -> None:
    with pytest.raises(BagFormatError, match='broken or truncated') as info:
        with open_bag(bags[name]) as reader:
            list(reader.messages())
    assert '\n' not in str(info.value)


# --- configs and topic planning --------------------------------------------------------------

def test_configs_validate() -> None:
    with pytest.raises(BagConfigError, match='rate'):
        PlayConfig.coerce({'rate': 0})
    with pytest.raises(BagConfigError, match="unknown keys \\['speed'\\]"):
        PlayConfig.coerce({'speed': 2})
    with pytest.raises(BagConfigError, match='qos'):
        PlayConfig.coerce({'qos': 'fast'})
    with pytest.raises(BagConfigError, match='remap'):
        PlayConfig.coerce({'remap': {'/a': ''}})
    with pytest.raises(BagConfigError, match='topics'):
        RecordConfig.coerce({})
    with pytest.raises(BagConfigError, match='storage'):
        RecordConfig.coerce({'topics': ['/a'], 'storage': 'rosbag1'})
    with pytest.raises(BagConfigError, match='bag_version'):
        RecordConfig.coerce({'topics': ['/a'], 'bag_version': 5})
    assert RecordConfig.coerce({'topics': ['/a']}).topics == ('/a',)


def test_plan_topics(bags: dict[str, Path]) -> None:
    with open_bag(bags['mcap']) as reader:
        plans, skipped = plan_topics(reader, PlayConfig(topics=(IMAGE,),
                                                        remap={IMAGE: '/cam'}))
        assert [(p.bag_topic, p.out_topic, p.type_name) for p in plans] == [
            (IMAGE, '/cam', 'sensor_msgs/msg/Image')] and not skipped
        with pytest.raises(BagConfigError, match="\\['/nope'\\] not in the bag"):
            plan_topics(reader, PlayConfig(topics=('/nope',)))
        with pytest.raises(BagConfigError, match='remap'):
            plan_topics(reader, PlayConfig(remap={'/nope': '/x'}))
        with pytest.raises(BagConfigError, match='several bag topics'):
            plan_topics(reader, PlayConfig(remap={IMAGE: CHATTER}))


# --- command lines: one line on stderr, non-zero exit -----------------------------------------

@pytest.mark.parametrize('name,expected', [
    ('missing', 'does not exist'),
    ('empty', 'not a rosbag2 directory'),
    ('no_meta', 'no metadata.yaml'),
    ('truncated', 'broken or truncated'),
    ('corrupt', 'broken or truncated'),
    ('bad_yaml', 'broken or truncated'),
    ('text', 'not a bag'),
])
def test_play_cli_bad_bag(bags: dict[str, Path], capsys: pytest.CaptureFixture[str],
                          name: str, expected: str) -> None:
    assert play_mod.cli([str(bags[name]), '--no-progress']) == 1
    out, err = capsys.readouterr()
    assert out == '' and err.count('\n') == 1
    assert err.startswith('semfeat-play: error: ') and expected in err


@pytest.mark.parametrize('argv,expected', [
    (['--topics', '/nope'], 'not in the bag'),
    (['--rate', '0'], 'rate'),
    (['--remap', '/nope:=/x'], 'remap'),
])
def test_play_cli_bad_options(bags: dict[str, Path], capsys: pytest.CaptureFixture[str],
                              argv: list[str], expected: str) -> None:
    assert play_mod.cli([str(bags['mcap']), *argv]) == 1
    err = capsys.readouterr().err
    assert err.count('\n') == 1 and expected in err


def test_record_cli_errors(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert record_mod.cli([str(tmp_path), '--topics', '/a']) == 1  # exists: never overwritten
    err = capsys.readouterr().err
    assert err.count('\n') == 1 and 'exists already' in err
    assert record_mod.cli([str(tmp_path / 'new'), '--topics', '/a', '--duration', '-1']) == 1
    err = capsys.readouterr().err
    assert err.count('\n') == 1 and 'duration' in err
    assert record_mod.cli([str(tmp_path / 'new'), '--topics', '/a', '--ros-args',
                           '--no-such-ros-flag']) == 1
    err = capsys.readouterr().err
    assert err.count('\n') == 1 and 'invalid ROS arguments' in err
    assert not (tmp_path / 'new').exists()
    with pytest.raises(BagWriteError, match='exists already'):
        record_mod.record(tmp_path, {'topics': ['/a']})


@pytest.mark.parametrize('tool', ['play', 'record'])
def test_console_module_wrong_path(tmp_path: Path, tool: str) -> None:
    """``python -m semfeat_ros.tools.<tool>`` (the console scripts' code path)."""
    target = tmp_path / 'no' / 'such' / 'bag' if tool == 'play' else tmp_path
    proc = subprocess.run([sys.executable, '-m', f'semfeat_ros.tools.{tool}', str(target),
                           '--topics', '/a'], env=ros_env(89), cwd=REPO,
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 1 and proc.stdout == ''
    assert proc.stderr.count('\n') == 1 and proc.stderr.startswith(f'semfeat-{tool}: error:')


# --- Python APIs (in this process, own rclpy context) ----------------------------------------

@pytest.mark.ros_domain(86)
def test_play_api_skips_unknown_types_and_stops_on_event(tmp_path: Path,
                                                         isolated_ros: int) -> None:
    store = get_typestore(Stores.ROS2_JAZZY)
    store.register(get_types_from_msg('uint8[] blob', 'semfeat_test_msgs/msg/Blob'))
    blob = store.types['semfeat_test_msgs/msg/Blob'](np.arange(3, dtype=np.uint8))
    msgs = [m for m in sample_messages() if m[0] == CHATTER]
    msgs.append(('/blob', 'semfeat_test_msgs/msg/Blob', T0_NS, blob))
    write_bag(tmp_path / 'bag', sorted(msgs, key=lambda m: m[2]), store=store)
    ctx = Context()
    rclpy.init(context=ctx)
    try:
        stats = play_mod.play(tmp_path / 'bag', {'rate': 10.0, 'progress': False},
                              context=ctx)
        assert stats.published == {CHATTER: 5} and stats.passes == 1
        assert 'not installed' in stats.skipped['/blob'] and not stats.interrupted
        assert stats.bag_span_s == pytest.approx(0.9)
        assert 0.07 < stats.wall_s < 0.5  # 0.9 s of bag at rate 10
        stop = threading.Event()
        threading.Timer(0.5, stop.set).start()
        looped = play_mod.play(tmp_path / 'bag', {'rate': 10.0, 'loop': True,
                                                  'progress': False}, stop, context=ctx)
        assert looped.interrupted and looped.passes >= 2
        assert looped.published[CHATTER] >= 5 * looped.passes
    finally:
        rclpy.try_shutdown(context=ctx)
    only_blob = tmp_path / 'only_blob'
    write_bag(only_blob, [msgs[-1]], store=store)
    with pytest.raises(BagConfigError, match='nothing to play'):
        play_mod.play(only_blob, {'progress': False})


@pytest.mark.ros_domain(87)
def test_record_api_duration_and_empty_bag(tmp_path: Path, isolated_ros: int) -> None:
    """Nobody publishes: the recorder stops after --duration and still writes a valid bag."""
    ctx = Context()
    rclpy.init(context=ctx)
    try:
        stats = record_mod.record(tmp_path / 'out', {'topics': ['nothing_here'],
                                                     'duration': 0.3, 'progress': False},
                                  context=ctx)
    finally:
        rclpy.try_shutdown(context=ctx)
    assert stats.never_seen == ['/nothing_here'] and not stats.interrupted
    assert 0.3 <= stats.wall_s < 2.0
    assert read_bag(tmp_path / 'out') == {}
    assert (tmp_path / 'out' / 'out.mcap').is_file()
