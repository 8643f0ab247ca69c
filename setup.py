"""ament_python build of semfeat_ros (colcon build / ros2 run), also pip-installable for tools."""
from __future__ import annotations

from glob import glob

from setuptools import find_packages, setup

PACKAGE = 'semfeat_ros'

# Console scripts: the three nodes (``ros2 run semfeat_ros <node>``), their managed variants and
# the offline tools.
# ament_python installs all of them into lib/semfeat_ros (see setup.cfg), where ros2 run looks.
CONSOLE_SCRIPTS = [
    'feature_node = semfeat_ros.nodes.feature_node:main',
    'matcher_node = semfeat_ros.nodes.matcher_node:main',
    'mapping_node = semfeat_ros.nodes.mapping_node:main',
    # managed (lifecycle) variants: configure / activate / deactivate / cleanup
    'feature_node_managed = semfeat_ros.nodes.managed:feature_main',
    'matcher_node_managed = semfeat_ros.nodes.managed:matcher_main',
    'mapping_node_managed = semfeat_ros.nodes.managed:mapping_main',
    'semfeat-eval = semfeat_ros.tools.eval:cli',
    'semfeat-sim = semfeat_ros.tools.sim:cli',
    'semfeat-play = semfeat_ros.tools.play:cli',
    'semfeat-record = semfeat_ros.tools.record:cli',
    'semfeat-train = semfeat_ros.tools.train:cli',
    'semfeat-train-glue = semfeat_ros.tools.train_glue:cli',
    'semfeat-calibrate-seg = semfeat_ros.tools.calibrate_seg:cli',
    'semfeat-features = semfeat_ros.tools.features:cli',
    'semfeat-map = semfeat_ros.tools.map:cli',
    'semfeat-colmap-peer = semfeat_ros.tools.colmap_peer:cli',
    'semfeat-bench = semfeat_ros.tools.bench:cli',
    'semfeat-photos = semfeat_ros.tools.photos:cli',
    'semfeat-batch = semfeat_ros.tools.batch:cli',
    'semfeat-report = semfeat_ros.tools.report:cli',
]

setup(
    name=PACKAGE,
    version='0.1.0',
    packages=find_packages(exclude=['test', 'test.*']),
    package_data={PACKAGE: ['weights/*.safetensors', 'weights/*.json', 'weights/*.md',
                           'weights/*.png', 'weights/*.LICENSE']},
    data_files=[
        ('share/ament_index/resource_index/packages', [f'resource/{PACKAGE}']),
        (f'share/{PACKAGE}', ['package.xml']),
        (f'share/{PACKAGE}/config', glob('config/*.yaml')),
        (f'share/{PACKAGE}/launch', glob('launch/*.launch.py')),
        (f'share/{PACKAGE}/rviz', glob('rviz/*.rviz')),
    ],
    install_requires=['setuptools'],
    zip_safe=False,
    maintainer='semfeat_ros developers',
    maintainer_email='semfeat-ros@example.com',
    description='Semantic-aware fisheye features, sequential matching and multi-floor mapping.',
    license='BSD-3-Clause',
    entry_points={'console_scripts': CONSOLE_SCRIPTS},
)
