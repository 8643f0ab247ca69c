"""Synthetic fisheye parking garage: procedural world, exact ray-cast renderer, sensors, bags.

Modules (import what you need; nothing heavy happens at package import):

* :mod:`~semfeat_ros.sim.groundtruth`: ``warp_pixels`` / ``warp_dense`` /
  ``sample_correspondences`` (depth + poses -> occlusion-checked correspondences).
* :mod:`~semfeat_ros.sim.dataset`: training shards (``load_shard``, ``render_shard``,
  ``write_dataset``).
* :mod:`~semfeat_ros.sim.scenario`: ``Scenario.create(seed, size)`` = world + drive + camera +
  renderer + sensor model; ``camera_pose(t)``, ``base_pose(t)``; ``benchmark`` (render speed).
* :mod:`~semfeat_ros.sim.world` / :mod:`~semfeat_ros.sim.layout` /
  :mod:`~semfeat_ros.sim.config`: the garage (``build_world(seed, GarageConfig)``).
* :mod:`~semfeat_ros.sim.render`: ``Renderer.render(T_map_cam, t) -> Frame`` (radiance, label,
  depth, instance), ``SensorModel.expose``.
* :mod:`~semfeat_ros.sim.trajectory`: the ego drive; :mod:`~semfeat_ros.sim.sensors`: GNSS
  and wheel odometry; :mod:`~semfeat_ros.sim.bag`: rosbag2 writer;
  :mod:`~semfeat_ros.sim.preview`: contact sheet.
* :mod:`~semfeat_ros.sim.geometry`: transforms and the camera pose convention
  ``T_map_cam = T_map_base @ T_base_cam``.

Command line: ``semfeat-sim`` (:mod:`semfeat_ros.tools.sim`).
"""
from __future__ import annotations
