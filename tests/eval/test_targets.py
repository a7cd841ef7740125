"""The one target registry (rory_eval/targets.py): each target's facts hold for its folder."""

from __future__ import annotations

import importlib.util
import sys

import pytest
import yaml

from rory_eval.targets import EXACT_TARGETS, TARGETS, Kind


@pytest.mark.parametrize('name', sorted(TARGETS))
def test_folder_node_keyvars_and_quality_run_exist(name: str) -> None:
    target = TARGETS[name]
    assert target.folder.name == name and target.node.is_file()
    nodes = yaml.safe_load(target.keyvars.read_text())['nodes']
    assert target.node_file in {node['file'] for node in nodes}
    assert importlib.util.find_spec(target.quality_module) is not None


@pytest.mark.parametrize('name', sorted(TARGETS))
def test_the_command_line_starts_the_original_node_in_sim_time(name: str) -> None:
    argv = TARGETS[name].argv('office_small', '-r', 'a:=b')
    assert argv[:4] == [sys.executable, str(TARGETS[name].node), '--ros-args', '-p']
    assert argv[4] == 'use_sim_time:=true'
    assert argv[-2:] == ['-r', 'a:=b']  # extra arguments come last


def test_mapping_targets_start_at_the_worlds_start_and_localizers_on_the_true_map() -> None:
    from sim.worlds import get_world

    start = get_world('workshop').start
    assert f'map_start_x:={float(start.x)!r}' in TARGETS['grid_slam'].argv('workshop')
    amcl = TARGETS['amcl'].argv('workshop')
    assert f'initial_pose_yaw:={start.yaw}' in amcl and '/map:=/ground_truth/map' in amcl
    assert 'goal_transient_local:=false' in TARGETS['navigator'].argv('workshop')


def test_what_each_kind_produces_and_which_runs_compare_byte_for_byte() -> None:
    assert {n: t.result_topic for n, t in TARGETS.items() if t.result_topic} == {
        'grid_slam': '/map', 'graph_slam': '/map', 'depth_mapper': '/depth_mapper/cloud'}
    assert all(t.result_topic for t in TARGETS.values() if t.kind in (Kind.MAP, Kind.MODEL))
    # The navigator drives the robot: its inputs follow from its outputs.
    assert list(EXACT_TARGETS) == ['grid_slam', 'graph_slam', 'depth_mapper', 'amcl',
                                   'lama_local']
    assert [t.depth for t in TARGETS.values()].count(True) == 1
    assert TARGETS['depth_mapper'].inputs == ('/camera/depth/points', '/odom')
