"""mapping_node's solver diagnostics and run-time parameter updates.

The solver's failures are injected as in test_mapping_mapper: a wrapper around every smoother
the mapper's backend makes raises gtsam's IndeterminantLinearSystem on chosen updates. The
first test drives a mapper on the synthetic garage and reads the levels of
:class:`SolverHealth` frame by frame (no ROS); the others run a mapping_node in-process, its
inputs handed to its callbacks (no message crosses DDS; the node itself needs a context, on a
domain of its own).
"""
from __future__ import annotations

import time
from typing import Any

from diagnostic_msgs.msg import DiagnosticStatus
import numpy as np
import pytest
import rclpy
from rclpy.parameter import Parameter
from sensor_msgs.msg import CameraInfo, PointCloud2
from std_srvs.srv import Trigger

from msg_adapters import model_to_camera_info, tracks_to_msg
from semfeat_ros.camera import Extrinsic, FisheyeCamera, load_camera_yaml
from semfeat_ros.mapping import Mapper
from semfeat_ros.mapping.session import MappingSession
from semfeat_ros.mapping.synthetic import MAPPER_SIGMA_PX, DriveConfig, garage_drive
from semfeat_ros.nodes.diagnostics import SolverHealth

CAMERA = FisheyeCamera(640, 512, 186.7, 186.7, 320.0, 256.0,
                       k=(0.02, -0.004, 0.0005, -0.0001), fov_deg=190)
OK, WARN, ERROR = DiagnosticStatus.OK, DiagnosticStatus.WARN, DiagnosticStatus.ERROR


class FailingUpdates:
    """Wraps a smoother; the updates carrying factors whose number (counted over every smoother
    of the mapper, from 1) is in ``fail`` raise like gtsam."""

    def __init__(self, smoother: Any, calls: dict[str, int], fail: set[int]) -> None:
        self.smoother, self.calls, self.fail = smoother, calls, fail

    def update(self, *args: Any) -> Any:
        if args:
            self.calls['n'] += 1
            if self.calls['n'] in self.fail:
                raise RuntimeError('\nIndeterminant linear system detected while working near '
                                   'variable 8646911284551352340 (Symbol: x20).')
        return self.smoother.update(*args)

    def __getattr__(self, name: str) -> Any:
        return getattr(self.smoother, name)


def failing(fail: set[int]) -> Any:
    """A ``wrap_smoother`` for :class:`Mapper` whose updates numbered in ``fail`` raise."""
    calls = {'n': 0}
    return lambda smoother: FailingUpdates(smoother, calls, fail)


# update 5 alone fails (recovered by a rebuild); updates 15-18 fail (the update and its three
# rebuilds: the window is reset)
FAIL = {5, 15, 16, 17, 18}


def level_of(health: SolverHealth) -> tuple[int, str]:
    found = health.level()
    return (OK, '') if found is None else found


def test_solver_health_levels_over_a_mapper_with_failing_updates() -> None:
    """WARN for warn_frames frames from the recovered failure, ERROR for error_frames frames
    from the window reset and WARN after it until warn_frames, then OK; the counters are the
    mapper's."""
    T_base_cam = Extrinsic((3.7, 0.0, 0.75), (0.0, 0.12, 0.0)).T_base_cam
    mapper = Mapper(CAMERA, T_base_cam, {'bearing_sigma_px': MAPPER_SIGMA_PX},
                    wrap_smoother=failing(FAIL))
    health = SolverHealth(error_frames=5, warn_frames=40)
    levels, results = [], []
    for frame in garage_drive(CAMERA, T_base_cam, DriveConfig(seed=6)).frames():
        results.append(mapper.update(frame.tracks, frame.odometry, frame.gnss))
        health.on_result(results[-1].state, results[-1].events)
        levels.append(level_of(health))
    assert all(r.state != 'lost' for r in results)  # every level below is the solver's
    recovered = [i for i, r in enumerate(results) if 'update_recovered' in r.events]
    reset = [i for i, r in enumerate(results) if 'window_reset' in r.events]
    assert len(recovered) == 1 and len(reset) == 1, (recovered, reset)
    i_rec, i_reset = recovered[0], reset[0]
    assert i_rec < i_reset and i_reset + 40 < len(results)
    assert all(lv == OK for lv, _ in levels[:i_rec])
    for i in range(i_rec, min(i_rec + 40, i_reset)):
        assert levels[i][0] == WARN and 'solver update failed' in levels[i][1], (i, levels[i])
    assert all(lv == OK for lv, _ in levels[i_rec + 40:i_reset])
    for i in range(i_reset, i_reset + 5):
        assert levels[i][0] == ERROR and 'could not be recovered' in levels[i][1], levels[i]
        assert 'Indeterminant linear system' in levels[i][1]
    assert all(lv == WARN for lv, _ in levels[i_reset + 5:i_reset + 40])
    assert all(lv == OK for lv, _ in levels[i_reset + 40:])
    values = health.values()
    assert values['solver_update_failures'] == str(mapper.stats['update_failures']) == '2'
    assert values['solver_recoveries'] == str(mapper.stats['recoveries']) == '1'
    assert values['solver_window_resets'] == '1'
    assert values['solver_smoother_resets'] == '0'
    assert values['solver_last_failure'].startswith('update_failed: Indeterminant')


def test_solver_health_lost_and_new_map() -> None:
    """A lost mapper is ERROR whatever happened before; a new map ends the holds, the counters
    stay."""
    health = SolverHealth(error_frames=10, warn_frames=10)
    health.on_result('tracking', ('update_failed: x', 'rebuild_failed: y', 'window_reset'))
    assert level_of(health)[0] == ERROR
    health.on_result('lost', ('tracking_lost',))
    assert level_of(health) == (ERROR, 'mapper lost: poses are predictions until it '
                                       're-initialises')
    health.new_map()
    assert level_of(health)[0] == OK
    health.on_result('initializing', ())
    assert level_of(health)[0] == OK
    assert health.values()['solver_tracking_lost'] == '1'
    assert health.values()['solver_window_resets'] == '1'


class Node:
    """A mapping_node in this process, not spun: its callbacks are called directly and its
    worker thread maps the frames."""

    def __init__(self, overrides: list[Parameter]) -> None:
        from semfeat_ros.nodes.mapping_node import MappingNode

        rclpy.init()
        self.node = MappingNode(parameter_overrides=[
            Parameter('input_timeout_s', value=0.0), Parameter('publish_tf', value=False),
            Parameter('use_gnss', value=False), Parameter('output_dir', value=''),
            *overrides])

    def start(self) -> None:
        self.node._on_camera_info(model_to_camera_info(
            CAMERA, stamp_ns=0, frame_id='camera_front_optical', msg_cls=CameraInfo))
        assert wait(lambda: self.node.feeder is not None)

    def send(self, frames: list) -> None:
        for f in frames:
            tr = f.tracks
            self.node._on_tracks(tracks_to_msg(
                tr.pixel, tr.bearing, tr.label, tr.track_id, np.full(len(tr), 2),
                np.ones(len(tr)), stamp_ns=tr.stamp_ns, frame_id='camera_front_optical',
                msg_cls=PointCloud2))

    def close(self) -> None:
        self.node.destroy_node()
        rclpy.try_shutdown()


def wait(cond: Any, timeout: float = 120.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and not cond():
        time.sleep(0.01)
    return cond()


def garage_frames() -> list:
    _, ext = load_camera_yaml()
    return list(garage_drive(CAMERA, ext.T_base_cam, DriveConfig(seed=3)).frames())


@pytest.mark.ros_domain(172)
def test_mapping_node_reports_solver_failures(isolated_ros,
                                              monkeypatch: pytest.MonkeyPatch) -> None:
    """The node's /diagnostics status over a mapper whose updates fail: ERROR after the window
    reset with the counters; solver_error_frames lowered at run time turns it into WARN;
    ~/reset (a new map) into OK."""
    import semfeat_ros.nodes.mapping_node as mapping_node

    class FaultySession(MappingSession):
        def __init__(self, camera: Any, T_base_cam: np.ndarray, conf: Any = None,
                     session: Any = None) -> None:
            super().__init__(camera, T_base_cam, conf, session)
            self.mapper = Mapper(camera, T_base_cam, conf, wrap_smoother=failing(FAIL))

    monkeypatch.setattr(mapping_node, 'MappingSession', FaultySession)
    h = Node([Parameter('solver_error_frames', value=100000),
              Parameter('solver_warn_frames', value=100000)])
    node = h.node
    try:
        h.start()
        frames = garage_frames()
        h.send(frames)
        assert wait(lambda: node.health.counters.processed == len(frames))
        stats = node.session.mapper.stats
        assert stats['update_failures'] == 2 and stats['recoveries'] == 1
        status = node.health.status()
        assert status.level == ERROR and 'could not be recovered' in status.message, \
            status.message
        assert status.hardware_id == '/mapping_node'
        values = {kv.key: kv.value for kv in status.values}
        assert values['solver_update_failures'] == '2'
        assert values['solver_recoveries'] == '1'
        assert values['solver_window_resets'] == '1'
        assert node.set_parameters([Parameter('solver_error_frames', value=1)])[0].successful
        status = node.health.status()
        assert status.level == WARN and 'solver update failed' in status.message, \
            status.message
        node._on_reset(Trigger.Request(), Trigger.Response())
        status = node.health.status()
        assert status.level == OK, status.message
        assert {kv.key: kv.value for kv in status.values}['solver_window_resets'] == '1'
    finally:
        h.close()


@pytest.mark.ros_domain(173)
def test_mapping_node_runtime_parameters(isolated_ros) -> None:
    """A keyframe threshold set at run time reaches the mapper's conf (and a map started
    later), the backlog bound and the cloud period take effect; a read-only parameter and a
    value out of range are refused with their reasons, and nothing changes."""
    h = Node([Parameter('min_change_interval_s', value=0.0)])
    node = h.node
    try:
        h.start()
        mapper = node.session.mapper
        assert mapper.conf['kf_parallax_deg'] == 4.0
        results = node.set_parameters([Parameter('kf_parallax_deg', value=7.5),
                                       Parameter('max_backlog', value=3),
                                       Parameter('cloud_period_s', value=0.25)])
        assert [r.successful for r in results] == [True] * 3, [r.reason for r in results]
        assert mapper.conf['kf_parallax_deg'] == 7.5
        assert node.conf.max_backlog == 3
        assert node._cloud_timer.timer_period_ns == 250_000_000
        node._on_reset(Trigger.Request(), Trigger.Response())
        assert node.session.mapper.conf['kf_parallax_deg'] == 7.5  # the new map keeps it
        # a camera change starts a map built from the node's parameters
        other = FisheyeCamera(800, 600, 200.0, 200.0, 400.0, 300.0,
                              k=(0.02, -0.004, 0.0005, -0.0001), fov_deg=190)
        for _ in range(node.conf.change_confirm_messages):
            node._on_camera_info(model_to_camera_info(
                other, stamp_ns=0, frame_id='camera_front_optical', msg_cls=CameraInfo))
        assert wait(lambda: node.session.mapper is not mapper
                    and node.session.mapper.camera.width == 800)
        assert node.session.mapper.conf['kf_parallax_deg'] == 7.5

        (refused,) = node.set_parameters([Parameter('window_keyframes', value=30)])
        assert not refused.successful
        assert refused.reason == 'Trying to set a read-only parameter: window_keyframes.'
        assert node.session.mapper.conf['window_keyframes'] == 15
        assert node.get_parameter('window_keyframes').value == 15
        (refused,) = node.set_parameters([Parameter('kf_max_distance_m', value=0.01)])
        assert not refused.successful and 'kf_max_distance_m' in refused.reason
        assert node.session.mapper.conf['kf_max_distance_m'] == 1.0
        assert node.conf.kf_max_distance_m == 1.0
    finally:
        h.close()
