"""targets/depth_mapper offline: decoding, normals, the voxel model, ICP, the pose graph, and
whole routes in the simulator against ground truth.

No ROS: ``sim.simulation.Simulation`` is stepped synchronously along a world's route (the
driver's control law, as ``--driver internal`` does), and its odometry and depth clouds are fed
to ``DepthMapper`` in the order the simulator publishes them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from depth_mapper_backend import Backend, BackendSettings, Keyframe, LoopClosure
from depth_mapper_calibration import HeadingCalibration
from depth_mapper_cloud import CloudError, FieldSpec, decode_xyz, organised_normals, valid_mask
from depth_mapper_geometry import (
    between,
    camera_quaternion,
    compose,
    optical_directions_to_base,
    optical_to_base,
    wrap,
)
from depth_mapper_graph import Edge, batch_errors, edge_error, optimize
from depth_mapper_icp import IcpSettings, align, well_constrained
from depth_mapper_model import VoxelModel
from depth_mapper_tracker import DepthMapper, MapperSettings
from rory_eval.metrics import distance_to_geometry
from rory_runtime import codec
from sim.driver import CONTROL_RATE, RouteFollower
from sim.simulation import TICK, Simulation
from sim.worlds import get_world

KEYVARS = Path(__file__).resolve().parents[2] / 'targets' / 'depth_mapper' / 'keyvars.yaml'
MOUNT = (0.12, 0.0, 0.25)


@dataclass
class Recording:
    """What a route produced: the messages in publishing order and ground truth per stamp."""

    world: str
    messages: list[tuple[str, int, Any]] = field(default_factory=list)
    truth: dict[int, tuple[float, float, float]] = field(default_factory=dict)
    odometry_errors: list[float] = field(default_factory=list)  # at each cloud


def record(world_name: str, until: float | None = None, seed: int = 0) -> Recording:
    """Drive the world's route and keep odometry (50 Hz) and clouds (5 Hz) as published."""
    world = get_world(world_name)
    sim = Simulation(world, seed, lidar=False, depth=True)
    follower = RouteFollower(world.route)
    every = round(1.0 / (CONTROL_RATE * TICK))
    out = Recording(world_name)
    s = world.start
    while not follower.done and (until is None or sim.time < until):
        if sim.ticks % every == 0:
            p = sim.pose()
            sim.command(*follower.command(p.x, p.y, p.yaw))
        frame = sim.step()
        if frame.odom_due:
            o = sim.odometry
            out.messages.append(('odom', frame.stamp_ns, (o.x, o.y, o.yaw)))
            p = sim.pose()
            out.truth[frame.stamp_ns] = (p.x, p.y, p.yaw)
        if frame.cloud is not None:
            out.messages.append(('cloud', frame.stamp_ns, frame.cloud))
            o, p = sim.odometry, sim.pose()
            c, sn = math.cos(s.yaw), math.sin(s.yaw)
            out.odometry_errors.append(math.hypot(s.x + c * o.x - sn * o.y - p.x,
                                                  s.y + sn * o.x + c * o.y - p.y))
    return out


def new_mapper(world_name: str, settings: MapperSettings | None = None) -> DepthMapper:
    s = get_world(world_name).start
    return DepthMapper(settings or MapperSettings(), np.array([s.x, s.y, s.yaw]))


def feed(mapper: DepthMapper, messages: list[tuple[str, int, Any]]) -> list[Any]:
    results = []
    for kind, stamp, payload in messages:
        if kind == 'odom':
            results += mapper.add_odometry(stamp, *payload)
        else:
            results += mapper.add_frame(stamp, payload)
    return results


@pytest.fixture(scope='module')
def real_room() -> Recording:
    return record('real_room')


CUT = 2751  # 50 s: the checkpoint, after a loop closure, with more of them to come


@dataclass
class RouteRun:
    """The mapper after the whole route, its results, and its key state checkpointed at CUT."""

    mapper: DepthMapper
    results: list[Any]
    checkpoint: bytes


@pytest.fixture(scope='module')
def real_room_run(real_room: Recording) -> RouteRun:
    mapper = new_mapper('real_room')
    results = feed(mapper, real_room.messages[:CUT])
    checkpoint = codec.encode_vars(_key_state(mapper))
    results += feed(mapper, real_room.messages[CUT:])
    return RouteRun(mapper, results, checkpoint)


def pose_errors(results: list[Any], truth: dict[int, tuple[float, float, float]]
                ) -> tuple[np.ndarray, np.ndarray]:
    position = np.array([math.hypot(r.pose[0] - truth[r.stamp_ns][0],
                                    r.pose[1] - truth[r.stamp_ns][1]) for r in results])
    heading = np.array([abs(wrap(float(r.pose[2]) - truth[r.stamp_ns][2])) for r in results])
    return position, heading


# -- pieces ---------------------------------------------------------------------------------------


def test_decode_reads_xyz_by_field_offset_and_refuses_malformed_clouds() -> None:
    rng = np.random.default_rng(0)
    xyz = rng.normal(size=(6, 8, 3)).astype(np.float32)
    padded = np.zeros((6, 8, 4), np.float32)
    padded[..., 1:] = xyz  # x y z after a leading pad: offsets 4, 8, 12, point_step 16
    fields = [FieldSpec('x', 4, 7), FieldSpec('y', 8, 7), FieldSpec('z', 12, 7)]
    assert np.array_equal(decode_xyz(padded.tobytes(), 6, 8, 16, fields), xyz)
    big = padded.astype('>f4').tobytes()
    assert np.array_equal(decode_xyz(big, 6, 8, 16, fields, is_bigendian=True), xyz)
    with pytest.raises(CloudError, match="'z' missing"):
        decode_xyz(padded.tobytes(), 6, 8, 16, fields[:2])
    with pytest.raises(CloudError, match='bytes of data'):
        decode_xyz(padded.tobytes()[:-4], 6, 8, 16, fields)
    with pytest.raises(CloudError, match='organised'):
        decode_xyz(padded.tobytes(), 1, 48, 16, fields)
    with pytest.raises(CloudError, match='FLOAT32'):
        decode_xyz(padded.tobytes(), 6, 8, 16, [*fields[:2], FieldSpec('z', 12, 8)])


def test_normals_of_a_tilted_wall_face_the_camera_and_skip_edges() -> None:
    # A plane z = 2 + 0.5 x seen by a pinhole camera, with a NaN hole.
    u, v = np.meshgrid(np.arange(40) - 19.5, np.arange(30) - 14.5)
    rx, ry = u / 35.0, v / 35.0
    z = 2.0 / (1.0 - 0.5 * rx)
    points = np.stack([rx * z, ry * z, z], axis=-1).astype(np.float32)
    points[10, 10] = np.nan
    valid = valid_mask(points, 0.3, 5.0)
    normals, has = organised_normals(points, valid)
    expected = np.array([0.5, 0.0, -1.0]) / math.sqrt(1.25)  # towards the camera
    assert has.sum() > 0.8 * has.size * (36 * 26) / (40 * 30)
    assert np.allclose(normals[has], expected, atol=1e-3)
    assert not has[10, 8] and not has[12, 10]  # neighbours of the hole have none
    base = optical_directions_to_base(normals[has])
    assert np.allclose(base[0], [-1.0 / math.sqrt(1.25), -0.5 / math.sqrt(1.25), 0.0],
                       atol=1e-3)


def test_geometry_frames() -> None:
    a, b = np.array([1.0, 2.0, 0.3]), np.array([-0.5, 0.7, 2.9])
    assert np.allclose(compose(a, between(a, b)), [*b[:2], wrap(b[2])])
    # The optical axis (z) points along the robot's heading, x to its right, y down.
    x, y, z, w = camera_quaternion(0.7)
    rot = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                    [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                    [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
    assert np.allclose(rot[:, 2], [math.cos(0.7), math.sin(0.7), 0.0])
    assert np.allclose(rot[:, 0], [math.sin(0.7), -math.cos(0.7), 0.0])
    assert np.allclose(rot[:, 1], [0.0, 0.0, -1.0])
    assert np.allclose(optical_to_base(np.array([[0.5, -0.2, 2.0]], np.float32), MOUNT),
                       [[2.12, -0.5, 0.45]])


def test_voxel_model_averages_points_by_weight_and_counts_keyframes() -> None:
    model = VoxelModel(0.05)
    pts = np.array([[0.01, 0.01, 0.01], [0.03, 0.01, 0.01], [1.01, 0.0, 0.0]])
    normals = np.array([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    weights = np.array([1.0, 3.0, 1.0])
    # Normals go in multiplied by their weights (normal sums).
    assert model.integrate(pts, normals * weights[:, None], weights) == 2
    assert model.integrate(pts[:1] + 0.001, normals[:1], np.array([1.0])) == 0
    assert np.all(np.diff(model.keys) > 0)
    index, dist = model.nearest(np.array([[0.06, 0.02, 0.02], [3.0, 0.0, 0.0]]))
    assert index[1] == -1 and dist[1] == np.inf
    mean = model.means(index[:1])[0]
    assert mean == pytest.approx([(0.01 + 0.09 + 0.011) / 5, 0.0102, 0.0102], abs=1e-9)
    assert sorted(model.hits.tolist()) == [1, 2]
    unit, consistency = model.normals(index[:1])
    assert np.allclose(unit[0], [1.0, 0.0, 0.0]) and consistency[0] == pytest.approx(1.0)
    assert len(model.points(min_hits=2)) == 1
    # Rebuilding from the same keyframe clouds gives the same voxels.
    again = VoxelModel(0.05)
    again.rebuild([pts, pts[:1] + 0.001], [normals * weights[:, None], normals[:1]],
                  [weights, np.array([1.0])])
    assert np.array_equal(again.keys, model.keys) and np.array_equal(again.hits, model.hits)
    assert np.allclose(again.point_sums, model.point_sums)


def test_pose_graph_jacobians_match_finite_differences() -> None:
    rng = np.random.default_rng(1)
    for _ in range(5):
        pi, pj, z = rng.normal(size=3), rng.normal(size=3), rng.normal(size=3) * 0.3
        e, jac = batch_errors(pi[None], pj[None], z[None])
        assert np.allclose(e[0], edge_error(pi, pj, z))
        d = np.eye(3) * 1e-6
        num_i = np.stack([edge_error(pi + d[k], pj, z) - edge_error(pi - d[k], pj, z)
                          for k in range(3)], axis=1) / 2e-6
        num_j = np.stack([edge_error(pi, pj + d[k], z) - edge_error(pi, pj - d[k], z)
                          for k in range(3)], axis=1) / 2e-6
        assert np.allclose(jac['i'][0], num_i, atol=1e-6)
        assert np.allclose(jac['j'][0], num_j, atol=1e-6)


def test_pose_graph_spreads_a_loop_error_over_the_weak_edges() -> None:
    true = np.array([[0, 0, 0], [2, 0, math.pi / 2], [2, 2, math.pi], [0, 2, -math.pi / 2],
                     [0, 0, 0]], dtype=float)
    strong, weak = np.diag([1e4, 1e4, 1e5]), np.diag([1e2, 1e2, 1e2])
    edges = [Edge(i, i + 1, between(true[i], true[i + 1]), strong if i != 1 else weak)
             for i in range(4)]
    edges[1].measurement = edges[1].measurement + np.array([0.3, 0.0, 0.1])  # a bad edge
    edges.append(Edge(0, 4, between(true[0], true[4]), strong, loop=True))
    start = np.array(true)
    for i in range(1, 5):
        start[i] = compose(start[i - 1], edges[i - 1].measurement)
    solved = optimize(start, edges)
    assert np.abs(start[4] - true[4]).max() > 0.15
    assert np.abs(solved[:, :2] - true[:, :2]).max() < 0.02
    assert solved[0] == pytest.approx(true[0])


def test_calibration_learns_the_odometry_heading_error() -> None:
    cal = HeadingCalibration()
    rng = np.random.default_rng(1)
    for _ in range(300):
        turn, ds = rng.choice([0.0, 0.2, -0.2]), rng.uniform(0.0, 0.06)
        true_turn = turn + rng.normal(0, 0.0005)
        cal.observe(turn * 1.02 - 0.01 * ds, ds, true_turn)  # over-counts turns, drifts right
    a, b = cal.coefficients()
    assert a == pytest.approx(1 / 1.02 - 1, abs=0.003)
    assert b == pytest.approx(0.01 / 1.02, abs=0.004)
    assert cal.corrected_yaw(0.204, 0.0) == pytest.approx(0.2, abs=0.001)



def test_a_loop_closure_that_moves_the_keyframes_does_not_teach_the_calibration(
        real_room: Recording, monkeypatch: pytest.MonkeyPatch) -> None:
    # The frame of such a closure is moved by the graph solve: its turn since the frame
    # before holds the loop's correction, which is not an error of the odometry.
    mapper = new_mapper('real_room')
    taught: list[int] = []
    observe = mapper.calibration.observe

    def spy(odom_yaw: float, odom_distance: float, true_yaw: float) -> None:
        taught.append(mapper.counters['frames'])
        observe(odom_yaw, odom_distance, true_yaw)

    monkeypatch.setattr(mapper.calibration, 'observe', spy)
    results = feed(mapper, real_room.messages)
    moved = [n for n, r in enumerate(results, start=1) if r.loop is LoopClosure.MOVED]
    assert moved and taught
    assert not set(moved) & set(taught)


def test_icp_recovers_an_offset_and_leaves_what_a_wall_cannot_tell_to_the_prior(
        real_room: Recording) -> None:
    # A real frame, its model built at the true pose; then aligned from a wrong start.
    stamp, cloud = next((s, c) for k, s, c in real_room.messages if k == 'cloud' and s > 3e9)
    truth = np.array(real_room.truth[stamp])
    valid = valid_mask(cloud, 0.3, 5.0)
    normals_o, has = organised_normals(cloud, valid)
    base = optical_to_base(cloud, MOUNT)[valid & has]
    normals = optical_directions_to_base(normals_o)[valid & has]
    c, s = math.cos(truth[2]), math.sin(truth[2])
    rot = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    model = VoxelModel(0.05)
    model.integrate(base @ rot.T + [truth[0], truth[1], 0.0], normals @ rot.T,
                    np.ones(len(base)))
    start = truth + np.array([0.06, -0.05, math.radians(2.0)])
    weak = np.eye(3) * 1e-3
    result = align(model, base, normals, np.full(len(base), 0.01), start, weak,
                   IcpSettings(iterations=20))
    assert result.tracked
    assert np.abs(result.pose[:2] - truth[:2]).max() < 0.01
    assert abs(wrap(float(result.pose[2] - truth[2]))) < math.radians(0.2)


def test_icp_leaves_what_a_wall_cannot_tell_to_the_prior() -> None:
    # A wall 3 m ahead (x = 3 in map) whose model normals lean 2 degrees: it says nothing
    # about sliding along it.
    y, z = np.meshgrid(np.linspace(-1.5, 1.5, 30), np.linspace(0.1, 2.0, 20))
    wall = np.stack([np.full(y.size, 3.0), y.ravel(), z.ravel()], axis=1)
    lean = math.radians(2.0)
    model = VoxelModel(0.05)
    model.integrate(wall, np.tile([-math.cos(lean), math.sin(lean), 0.0], (len(wall), 1)),
                    np.ones(len(wall)))
    truth = np.array([0.0, 0.0, 0.0])
    frame_normals = np.tile([-1.0, 0.0, 0.0], (len(wall), 1))
    start = truth + np.array([0.03, 0.05, 0.0])  # 3 cm short of the wall, 5 cm to the side
    prior_information = np.diag([1e4, 1e4, 1e6])  # the odometry: 1 cm, 1 mrad
    sigmas = np.full(len(wall), 0.01)
    settings = IcpSettings(iterations=20, max_distance=0.2)
    result = align(model, wall, frame_normals, sigmas, start, prior_information, settings)
    assert result.tracked
    assert result.pose[0] == pytest.approx(0.0, abs=0.004)  # the wall gives the distance
    assert result.pose[1] == pytest.approx(0.05, abs=0.002)  # sideways: the prior's
    # What the geometry claims to know (the edge information): distance to the wall, and
    # nothing along it.
    along = np.array([math.sin(lean), math.cos(lean), 0.0])
    assert result.information[0, 0] > 1e6 and along @ result.information @ along < 1e-6
    # The rule itself: a direction known to worse than 1 cm is dropped from (H, g).
    h, g = well_constrained(np.diag([1e6, 50.0, 1e5]), np.array([1.0, 2.0, 3.0]), 0.01, 2.0)
    assert np.allclose(h, np.diag([1e6, 0.0, 1e5])) and np.allclose(g, [1.0, 0.0, 3.0])


# -- whole routes -------------------------------------------------------------------------------


def test_real_room_route_tracks_far_better_than_odometry_and_maps_the_geometry(
        real_room: Recording, real_room_run: RouteRun) -> None:
    mapper, results = real_room_run.mapper, real_room_run.results
    assert len(results) == sum(1 for m in real_room.messages if m[0] == 'cloud')
    position, heading = pose_errors(results, real_room.truth)
    odometry = np.array(real_room.odometry_errors)
    assert np.median(position) <= 0.03 and position.max() <= 0.08
    assert np.degrees(np.median(heading)) <= 0.5
    assert np.median(odometry) >= 10 * np.median(position)  # 0.42 m against ~0.01 m
    assert mapper.counters['loops'] >= 1  # twice around the obstacle
    points = mapper.model.points(min_hits=2)
    distance = distance_to_geometry(get_world('real_room'), points)
    above_floor = points[:, 2] > 0.05
    assert len(points) > 20_000
    assert np.mean(distance < 0.05) >= 0.95
    assert np.mean(distance[above_floor] < 0.05) >= 0.95  # not just the easy floor


def test_office_corridor_and_open_office(tmp_path: Path) -> None:
    run = record('office_small', until=50.0)
    mapper = new_mapper('office_small')
    results = feed(mapper, run.messages)
    position, _ = pose_errors(results, run.truth)
    assert np.median(position) <= 0.03 and position.max() <= 0.08
    assert np.median(run.odometry_errors) >= 5 * np.median(position)
    points = mapper.model.points(min_hits=2)
    distance = distance_to_geometry(get_world('office_small'), points)
    assert np.mean(distance < 0.05) >= 0.95
    assert np.mean(distance[points[:, 2] > 0.05] < 0.05) >= 0.9


def _key_state(mapper: DepthMapper) -> dict[str, Any]:
    """The variables keyvars.yaml lists, read by their dotted paths below ``mapper``."""
    spec = yaml.safe_load(KEYVARS.read_text())['nodes'][0]['vars']
    values = {}
    for path in spec:
        obj: Any = mapper
        for part in path.split('.')[1:]:
            obj = getattr(obj, part)
        values[path] = obj
    return values


def _write_state(mapper: DepthMapper, values: dict[str, Any]) -> None:
    for path, value in values.items():
        parts = path.split('.')[1:]
        obj: Any = mapper
        for part in parts[:-1]:
            obj = getattr(obj, part)
        setattr(obj, parts[-1], value)


def test_restoring_the_key_state_and_replaying_gives_the_same_state(
        real_room: Recording, real_room_run: RouteRun) -> None:
    # What RORY does: checkpoint the listed variables (through its codec), start a fresh
    # node, restore them, replay the messages that came after. The state must come out equal.
    restored = new_mapper('real_room')
    values = codec.decode_vars(real_room_run.checkpoint)
    loops_at_cut = values['mapper.counters']['loops']
    assert loops_at_cut >= 1  # loop edges and a rebuilt model in it
    _write_state(restored, values)
    feed(restored, real_room.messages[CUT:])
    expected, got = _key_state(real_room_run.mapper), _key_state(restored)
    assert codec.encode_vars(got) == codec.encode_vars(expected)
    assert real_room_run.mapper.counters['loops'] > loops_at_cut


def test_bad_input_is_skipped_and_counted(real_room: Recording) -> None:
    mapper = new_mapper('real_room')
    messages = real_room.messages[:600]  # 6 s
    clouds = [m for m in messages if m[0] == 'cloud']
    feed(mapper, messages[:300])
    before = mapper.counters['frames']
    empty = np.full((60, 80, 3), np.nan, np.float32)
    stamp = clouds[-1][1] + 200_000_000
    mapper.add_odometry(stamp, *messages[299][2])
    out = mapper.add_frame(stamp, empty)
    assert len(out) == 1 and not out[0].tracked and out[0].valid_points == 0
    assert mapper.counters['empty_frames'] == 1 and mapper.counters['frames'] == before + 1
    assert mapper.add_frame(stamp, clouds[0][2]) == []  # not newer: skipped
    assert mapper.counters['stale_frames'] == 1
    assert mapper.add_odometry(stamp - 1, 0.0, 0.0, 0.0) == []
    assert mapper.counters['stale_odometry'] == 1
    inf = clouds[-1][2].copy()
    inf[::2] = np.inf
    mapper.add_odometry(stamp + 200_000_000, *messages[299][2])
    assert len(mapper.add_frame(stamp + 200_000_000, inf)) == 1


def test_frames_wait_for_their_odometry_and_go_on_without_any() -> None:
    run = record('real_room', until=3.0)
    clouds = [m for m in run.messages if m[0] == 'cloud']
    odoms = [m for m in run.messages if m[0] == 'odom']
    # A cloud that arrives before the odometry stamped with it waits for it.
    mapper = new_mapper('real_room')
    feed(mapper, [m for m in odoms if m[1] < clouds[0][1]])
    assert mapper.add_frame(clouds[0][1], clouds[0][2]) == []
    assert len(mapper.pending) == 1
    out = feed(mapper, [m for m in odoms if m[1] == clouds[0][1]])
    assert [r.stamp_ns for r in out] == [clouds[0][1]] and not mapper.pending
    # No odometry at all: frames are still tracked, from the model alone. Nothing but the
    # depth holds the pose then, and the D435's depth noise grows with z^2 (sim/README.md):
    # 0.18 m at worst over these 3 s (0.03-0.04 m with the earlier camera's noise), where a
    # pose left where it started ends as far off as the robot travelled (0.73 m).
    blind = new_mapper('real_room')
    results = feed(blind, clouds)
    assert len(results) == len(clouds) - 1  # the newest waits, in case odometry comes
    position, _ = pose_errors(results, run.truth)
    start, end = run.truth[results[0].stamp_ns], run.truth[results[-1].stamp_ns]
    travel = math.hypot(end[0] - start[0], end[1] - start[1])
    assert position.max() < 0.25 and position.max() < travel / 3


def test_keyframes_hold_their_clouds_and_link_into_the_graph(real_room_run: RouteRun) -> None:
    mapper = real_room_run.mapper
    backend = mapper.backend
    assert isinstance(backend.keyframes[0], Keyframe)
    assert len(backend.keyframes) == mapper.counters['keyframes']
    sequential = [e for e in backend.edges if not e.loop]
    assert [(e.i, e.j) for e in sequential] == [(k - 1, k) for k in
                                                range(1, len(backend.keyframes))]
    assert sum(e.loop for e in backend.edges) == mapper.counters['loops']
    assert all(kf.points.dtype == np.float32 and len(kf.points) == len(kf.weights)
               for kf in backend.keyframes)
    # A backend with nothing to close never moves its keyframes.
    lone = Backend(BackendSettings(), 0.05)
    assert lone.close_loop() is LoopClosure.NONE


def test_a_loop_fit_pins_the_pose_only_if_every_direction_is_constrained() -> None:
    from depth_mapper_backend import pins_pose

    well = np.diag([1.0 / 0.01**2, 1.0 / 0.01**2, 1.0 / 0.0005**2])
    assert pins_pose(well, 0.02)
    # A wall ahead: sliding along it (y) is projected out, the information is singular.
    # Inverting it anyway can give negative variances that would read as "pinned".
    wall = well.copy()
    wall[1, :] = wall[:, 1] = 0.0
    assert not pins_pose(wall, 0.02)
    loose = np.diag([1.0 / 0.05**2, 1.0 / 0.01**2, 1.0 / 0.0005**2])
    assert not pins_pose(loose, 0.02)
    assert not pins_pose(np.full((3, 3), np.nan), 0.02)


def test_odometry_at_a_sample_stamp_does_not_depend_on_later_odometry() -> None:
    # A frame is tracked from the odometry at its stamp, whether that sample was the newest
    # when the frame came or later ones had come too (delivery order varies).
    samples = [(k * 20, 0.1 * k + 0.013, 0.2 * k, 1.29 + 0.0137 * k) for k in range(8)]
    for k in range(7):
        early = DepthMapper(MapperSettings(), np.zeros(3))
        late = DepthMapper(MapperSettings(), np.zeros(3))
        for sample in samples[:k + 1]:
            early.odometry.append(sample)
        for sample in samples:
            late.odometry.append(sample)
        assert late._odometry_at(k * 20) == early._odometry_at(k * 20) == samples[k][1:]
