"""The six target programs (``targets/``) as rory_eval runs them: the one place for their facts.

The evaluation (evaluation/), the quality runs (quality/), the benches, the fault campaigns and
the harness all start, feed and judge the same programs. What each needs to know of one - its
folder, node program and key-variable file, its command line in a world, the topics it reads
and writes, what it produces and so how it is judged, which quality run measures it, and
whether a crash run can be compared with a run without one byte for byte - is written here
once, in :data:`TARGETS`, and read from here.
"""

from __future__ import annotations

import enum
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

TARGETS_DIR = Path(__file__).resolve().parents[1] / 'targets'


class Kind(enum.StrEnum):
    """What a target produces, and so how it is judged."""

    MAP = 'map'  # nav_msgs/OccupancyGrid on /map
    MODEL = 'model'  # sensor_msgs/PointCloud2 3D model
    NAVIGATION = 'navigation'  # drives the robot to a goal
    LOCALIZATION = 'localization'  # a pose the navigator drives on


def _map_start(world: str) -> list[str]:
    """Sim time, the map anchored at the world's start pose (the mapping targets)."""
    from sim.worlds import get_world

    start = get_world(world).start
    return ['--ros-args', '-p', 'use_sim_time:=true',
            '-p', f'map_start_x:={float(start.x)!r}', '-p', f'map_start_y:={float(start.y)!r}',
            '-p', f'map_start_yaw:={float(start.yaw)!r}']


def _initial_pose(world: str) -> list[str]:
    """Sim time, the world's start pose as the first estimate, the ground-truth map (the
    localizers)."""
    from sim.worlds import get_world

    start = get_world(world).start
    return ['--ros-args', '-p', 'use_sim_time:=true',
            '-p', f'initial_pose_x:={start.x}', '-p', f'initial_pose_y:={start.y}',
            '-p', f'initial_pose_yaw:={start.yaw}', '-r', '/map:=/ground_truth/map']


def _navigation(world: str) -> list[str]:
    """Sim time, the ground-truth map; the goal arrives once and volatile
    (goal_transient_local off), as from RViz's goal tool."""
    return ['--ros-args', '-p', 'use_sim_time:=true', '-r', '/map:=/ground_truth/map',
            '-p', 'goal_transient_local:=false']


@dataclass(frozen=True)
class Target:
    """One target program: where it is, how it starts, what it reads and writes.

    Attributes:
        name: its folder under ``targets/``, and its node's name under ``rory supervise``.
        kind: what it produces: how the evaluation runs it and judges it.
        node_file: its main script, inside the folder.
        arguments: world -> what follows the script on its command line (sim time, the
            world's start pose, remaps), the same wherever it runs.
        pose_topic: its pose output (the navigator's is its plan's status instead).
        pose_type: the message type on ``pose_topic``.
        paper: the program of the paper it stands in for.
        result_topic: what it builds, judged at the end of a run (the map, the 3D model);
            empty when it is judged on its poses or its driving.
        depth: needs the depth camera.
        inputs: the sensor topics it reads, whose readers the simulator's clock waits for.
        exact_outputs: under the simulator's internal driver its outputs are a function of its
            inputs alone, so a crash run is compared with a run without one byte for byte
            (faults/target_crash.py, faults/target_faults.py). Not the navigator: it drives
            the robot, its inputs follow from its own outputs.
    """

    name: str
    kind: Kind
    node_file: str
    arguments: Callable[[str], list[str]]
    pose_topic: str
    pose_type: str
    paper: str
    result_topic: str = ''
    depth: bool = False
    inputs: tuple[str, ...] = ('/scan',)
    exact_outputs: bool = True

    @property
    def folder(self) -> Path:
        """``targets/<name>``: the script folder rory-instrument copies."""
        return TARGETS_DIR / self.name

    @property
    def node(self) -> Path:
        """The original node program."""
        return self.folder / self.node_file

    @property
    def keyvars(self) -> Path:
        """Its key-variable file (docs/keyvars.md)."""
        return self.folder / 'keyvars.yaml'

    @property
    def quality_module(self) -> str:
        """Its quality run in normal operation: ``python -m`` this (targets/README.md)."""
        return f'rory_eval.quality.{self.name}'

    def argv(self, world: str, *extra: str) -> list[str]:
        """The original node's command line in a world, ``extra`` arguments last."""
        return [sys.executable, str(self.node), *self.arguments(world), *extra]


# Navigation: time to the world's default goal at ~0.4 m/s, start-up and a margin to settle
# (rory_eval/quality/navigator.py measured these).
NAVIGATION_SECONDS = {'office_small': 55.0, 'workshop': 50.0, 'real_room': 30.0}
"""Sim seconds a navigation run lasts per world (the navigator and the localizers it drives)."""

POSE_STAMPED = 'geometry_msgs/msg/PoseStamped'
POSE_WITH_COVARIANCE_STAMPED = 'geometry_msgs/msg/PoseWithCovarianceStamped'

TARGETS: dict[str, Target] = {
    t.name: t for t in (
        Target('grid_slam', Kind.MAP, 'grid_slam_node.py', _map_start, '/grid_slam/pose',
               POSE_STAMPED, 'hector_mapping', result_topic='/map'),
        Target('graph_slam', Kind.MAP, 'graph_slam_node.py', _map_start, '/graph_slam/pose',
               POSE_STAMPED, 'RTAB-Map', result_topic='/map', inputs=('/scan', '/odom')),
        Target('depth_mapper', Kind.MODEL, 'depth_mapper_node.py', _map_start,
               '/depth_mapper/pose', POSE_STAMPED, 'ORB_SLAM2',
               result_topic='/depth_mapper/cloud', depth=True,
               inputs=('/camera/depth/points', '/odom')),
        Target('navigator', Kind.NAVIGATION, 'navigator_node.py', _navigation,
               '/navigator/status', 'std_msgs/msg/String', 'move_base',
               inputs=('/scan', '/odom'), exact_outputs=False),
        Target('amcl', Kind.LOCALIZATION, 'amcl_node.py', _initial_pose, '/amcl_pose',
               POSE_WITH_COVARIANCE_STAMPED, 'AMCL', inputs=('/scan', '/odom')),
        Target('lama_local', Kind.LOCALIZATION, 'lama_local_node.py', _initial_pose,
               '/lama_local/pose', POSE_WITH_COVARIANCE_STAMPED, 'LaMa_local',
               inputs=('/scan', '/odom')),
    )
}
# The targets whose crash runs are compared byte for byte with a run without a crash.
EXACT_TARGETS: dict[str, Target] = {n: t for n, t in TARGETS.items() if t.exact_outputs}
