"""The three worlds as data: walls, furniture, machines and pillars, plus start, route and goals.

Everything here is plain geometry in the ``map`` frame (x east, y north, metres, yaw in radians
counter-clockwise from +x). The MJCF model (``sim.model``), the ground-truth occupancy map
(``sim.maps``) and the figures (``sim.render``) are all derived from these definitions, so the
three never disagree.

Every obstacle stands on the floor and is at least 0.4 m tall, so the 2D lidar (0.18 m above the
floor) sees every obstacle the robot can hit, and the 2D map is simply the union of footprints.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

WALL_THICKNESS = 0.1
WALL_HEIGHT = 2.5

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True)
class Pose2D:
    """A planar pose in the map frame."""

    x: float
    y: float
    yaw: float = 0.0


@dataclass(frozen=True)
class Box:
    """An upright box standing on the floor.

    Attributes:
        name: unique geom name in the world (also the name reported on ``/collisions``).
        x: centre x of the footprint (m).
        y: centre y of the footprint (m).
        sx: full length along the box's own x axis (m).
        sy: full width along the box's own y axis (m).
        height: full height (m); the box spans z in [0, height].
        yaw: rotation of the footprint about z (rad).
        kind: what it stands for (``wall``, ``furniture``, ``machine``...), for figures.
    """

    name: str
    x: float
    y: float
    sx: float
    sy: float
    height: float
    yaw: float = 0.0
    kind: str = 'furniture'

    def _local(self, px: FloatArray, py: FloatArray) -> tuple[FloatArray, FloatArray]:
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        dx, dy = px - self.x, py - self.y
        return c * dx + s * dy, -s * dx + c * dy

    def distance(self, px: FloatArray, py: FloatArray) -> FloatArray:
        """Signed distance from points to the footprint (negative inside)."""
        lx, ly = self._local(px, py)
        qx = np.abs(lx) - self.sx / 2
        qy = np.abs(ly) - self.sy / 2
        outside = np.hypot(np.maximum(qx, 0.0), np.maximum(qy, 0.0))
        inside = np.minimum(np.maximum(qx, qy), 0.0)
        return outside + inside

    def overlaps_cells(self, cx: FloatArray, cy: FloatArray, half: float) -> npt.NDArray[np.bool_]:
        """Whether square cells (centres ``cx, cy``, half side ``half``) overlap the footprint.

        Exact for axis-aligned boxes (interval overlap); for rotated boxes the footprint is
        grown by the half cell in its own frame, which errs on the occupied side.
        """
        lx, ly = self._local(cx, cy)
        grow = half if self.yaw == 0.0 else half * math.sqrt(2.0)
        eps = 1e-9  # a footprint edge lying exactly on a cell edge does not occupy that cell
        inside: npt.NDArray[np.bool_] = (np.abs(lx) < self.sx / 2 + grow - eps) & (
            np.abs(ly) < self.sy / 2 + grow - eps
        )
        return inside

    def corners(self) -> list[tuple[float, float]]:
        """Footprint corners in the map frame, counter-clockwise."""
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        hx, hy = self.sx / 2, self.sy / 2
        return [
            (self.x + c * ax - s * ay, self.y + s * ax + c * ay)
            for ax, ay in ((-hx, -hy), (hx, -hy), (hx, hy), (-hx, hy))
        ]


@dataclass(frozen=True)
class Cylinder:
    """An upright cylinder standing on the floor (pillar, bin, plant, round table).

    Attributes:
        name: unique geom name in the world.
        x: centre x (m).
        y: centre y (m).
        radius: radius (m).
        height: full height (m).
        kind: what it stands for, for figures.
    """

    name: str
    x: float
    y: float
    radius: float
    height: float
    kind: str = 'furniture'

    def distance(self, px: FloatArray, py: FloatArray) -> FloatArray:
        """Signed distance from points to the footprint (negative inside)."""
        d: FloatArray = np.hypot(px - self.x, py - self.y) - self.radius
        return d

    def overlaps_cells(self, cx: FloatArray, cy: FloatArray, half: float) -> npt.NDArray[np.bool_]:
        """Whether square cells (centres ``cx, cy``, half side ``half``) overlap the disc.

        Exact: the point of each cell nearest to the centre lies within the radius.
        """
        nx = np.clip(self.x, cx - half, cx + half)
        ny = np.clip(self.y, cy - half, cy + half)
        inside: npt.NDArray[np.bool_] = np.hypot(nx - self.x, ny - self.y) < self.radius - 1e-9
        return inside


Obstacle = Box | Cylinder


@dataclass(frozen=True)
class Noise:
    """Sensor and actuation noise of a world (see sim/README.md, "Noise models").

    Attributes:
        lidar_sigma: range noise standard deviation (m), Gaussian, per beam.
        lidar_sigma_rel: additional noise proportional to range (fraction of range).
        lidar_dropout: probability that a beam returns nothing (published as NaN).
        depth_dropout: probability that a depth pixel returns nothing (NaN point).
        odom_scale_left: left wheel encoder scale error (measured / true travel).
        odom_scale_right: right wheel encoder scale error.
        odom_wheelbase_scale: effective wheel separation / nominal one; the odometry uses the
            nominal value, so every turn is over- or under-counted by this factor.
        odom_wheel_sigma: random encoder error per wheel (m per sqrt(m) travelled).
        slip_mean: mean fraction of wheel travel lost to slip (the body moves less than the
            wheels turn; the encoders count the wheels).
        slip_sigma: standard deviation of that fraction (Ornstein-Uhlenbeck process).
        slip_tau: correlation time of the slip process (s).
    """

    lidar_sigma: float = 0.01
    lidar_sigma_rel: float = 0.0
    lidar_dropout: float = 0.0
    depth_dropout: float = 0.0
    odom_scale_left: float = 1.0015
    odom_scale_right: float = 0.9985
    odom_wheelbase_scale: float = 1.02
    odom_wheel_sigma: float = 0.002
    slip_mean: float = 0.0
    slip_sigma: float = 0.0
    slip_tau: float = 1.0


@dataclass(frozen=True)
class World:
    """One environment: geometry, where the robot starts, the driver's route and named goals.

    Attributes:
        name: world name (``office_small``, ``workshop``, ``real_room``).
        description: one line for help texts and figures.
        bounds: (xmin, ymin, xmax, ymax) enclosing every obstacle (m).
        obstacles: walls, furniture, machines, pillars.
        start: the robot's start pose (also the origin of the ``odom`` frame).
        route: waypoints the scripted driver follows from ``start`` (x, y).
        goals: named goal poses for navigation, from ``start``.
        default_goal: the goal the evaluation uses unless told otherwise.
        noise: the world's sensor and actuation noise.
    """

    name: str
    description: str
    bounds: tuple[float, float, float, float]
    obstacles: tuple[Obstacle, ...]
    start: Pose2D
    route: tuple[tuple[float, float], ...]
    goals: dict[str, Pose2D] = field(default_factory=dict)
    default_goal: str = ''
    noise: Noise = field(default_factory=Noise)

    def clearance(self, px: FloatArray, py: FloatArray) -> FloatArray:
        """Distance from each point to the nearest obstacle footprint (negative inside one)."""
        px = np.asarray(px, dtype=np.float64)
        py = np.asarray(py, dtype=np.float64)
        best = np.full(np.broadcast(px, py).shape, np.inf)
        for obstacle in self.obstacles:
            best = np.minimum(best, obstacle.distance(px, py))
        return best

    def route_length(self) -> float:
        """Length of the driver's route from the start pose (m)."""
        pts = [(self.start.x, self.start.y), *self.route]
        return float(sum(math.dist(a, b) for a, b in itertools.pairwise(pts)))

    def route_clearance(self, step: float = 0.02) -> float:
        """Smallest clearance along the straight segments of the route (m)."""
        pts = [(self.start.x, self.start.y), *self.route]
        worst = math.inf
        for (ax, ay), (bx, by) in itertools.pairwise(pts):
            n = max(2, math.ceil(math.dist((ax, ay), (bx, by)) / step) + 1)
            s = np.linspace(0.0, 1.0, n)
            worst = min(worst, float(self.clearance(ax + s * (bx - ax), ay + s * (by - ay)).min()))
        return worst


def walls(
    name: str,
    a: tuple[float, float],
    b: tuple[float, float],
    doors: Sequence[tuple[float, float]] = (),
    *,
    thickness: float = WALL_THICKNESS,
    height: float = WALL_HEIGHT,
) -> list[Box]:
    """An axis-aligned wall from ``a`` to ``b`` (centre line), cut by door openings.

    Args:
        name: prefix of the pieces' names (``name_0``, ``name_1``...).
        a: one end of the centre line.
        b: the other end; the wall must be horizontal or vertical.
        doors: (centre, width) of each opening, the centre measured along the wall's axis in
            map coordinates (x for a horizontal wall, y for a vertical one).
        thickness: wall thickness (m).
        height: wall height (m).

    Returns:
        The wall's pieces; each is extended by half the thickness at ends that are not a door
        edge, so that walls meeting at a corner leave no gap.

    Raises:
        ValueError: the wall is not axis-aligned, or a door does not fit in it.
    """
    (ax, ay), (bx, by) = a, b
    horizontal = ay == by
    if not horizontal and ax != bx:
        raise ValueError(f'wall {name!r}: {a} -> {b} is not axis-aligned')
    lo, hi = (min(ax, bx), max(ax, bx)) if horizontal else (min(ay, by), max(ay, by))
    fixed = ay if horizontal else ax
    half_t = thickness / 2
    # Intervals along the axis; flags say whether each end is a door edge (not extended).
    cuts: list[tuple[float, float, bool, bool]] = []
    start, start_is_door = lo, False
    for centre, width in sorted(doors):
        d0, d1 = centre - width / 2, centre + width / 2
        if d0 < start or d1 > hi:
            raise ValueError(f'wall {name!r}: door at {centre} (width {width}) does not fit')
        cuts.append((start, d0, start_is_door, True))
        start, start_is_door = d1, True
    cuts.append((start, hi, start_is_door, False))
    pieces = []
    for k, (s0, s1, door0, door1) in enumerate(cuts):
        e0 = s0 if door0 else s0 - half_t
        e1 = s1 if door1 else s1 + half_t
        if e1 - e0 <= 1e-9:
            continue
        centre, length = (e0 + e1) / 2, e1 - e0
        if horizontal:
            pieces.append(Box(f'{name}_{k}', centre, fixed, length, thickness, height, kind='wall'))
        else:
            pieces.append(Box(f'{name}_{k}', fixed, centre, thickness, length, height, kind='wall'))
    return pieces


def _room(name: str, x0: float, y0: float, x1: float, y1: float) -> list[Box]:
    """Four closed walls around the rectangle (x0, y0)-(x1, y1)."""
    return [
        *walls(f'{name}_south', (x0, y0), (x1, y0)),
        *walls(f'{name}_north', (x0, y1), (x1, y1)),
        *walls(f'{name}_west', (x0, y0), (x0, y1)),
        *walls(f'{name}_east', (x1, y0), (x1, y1)),
    ]


def _bounds(obstacles: Iterable[Obstacle]) -> tuple[float, float, float, float]:
    xs: list[float] = []
    ys: list[float] = []
    for o in obstacles:
        if isinstance(o, Box):
            for cx, cy in o.corners():
                xs.append(cx)
                ys.append(cy)
        else:
            xs += [o.x - o.radius, o.x + o.radius]
            ys += [o.y - o.radius, o.y + o.radius]
    return round(min(xs), 6), round(min(ys), 6), round(max(xs), 6), round(max(ys), 6)


def _office_small() -> World:
    """A 12 m x 9 m office: a corridor with three rooms south and two north, doors, furniture."""
    obstacles: list[Obstacle] = [
        *_room('outer', 0.0, 0.0, 12.0, 9.0),
        # Corridor (y 3.5-5.0) walls with one door per room.
        *walls('corridor_s', (0.0, 3.5), (12.0, 3.5), doors=[(2.0, 1.0), (6.0, 1.0), (10.0, 1.0)]),
        *walls('corridor_n', (0.0, 5.0), (12.0, 5.0), doors=[(3.0, 1.0), (9.0, 1.0)]),
        *walls('divider_ab', (4.0, 0.0), (4.0, 3.5)),
        *walls('divider_bc', (8.0, 0.0), (8.0, 3.5)),
        *walls('divider_de', (6.0, 5.0), (6.0, 9.0)),
        # Corridor: pilasters and a bench give scan matching something to hold on to.
        Box('pilaster_1', 4.0, 3.65, 0.3, 0.2, WALL_HEIGHT, kind='wall'),
        Box('pilaster_2', 8.0, 3.65, 0.3, 0.2, WALL_HEIGHT, kind='wall'),
        Box('pilaster_3', 6.0, 4.85, 0.3, 0.2, WALL_HEIGHT, kind='wall'),
        Box('bench', 4.75, 4.775, 1.5, 0.35, 0.45),
        Cylinder('water_cooler', 11.7, 4.25, 0.15, 1.1),
        # Room A (x 0-4, y 0-3.5): two desks, a cabinet, a plant.
        Box('desk_a1', 1.0, 0.45, 1.4, 0.7, 0.75),
        Box('desk_a2', 3.0, 0.45, 1.4, 0.7, 0.75),
        Box('cabinet_a', 0.35, 2.5, 0.5, 1.0, 1.8),
        Cylinder('plant_a', 3.6, 3.1, 0.2, 1.0),
        # Room B (x 4-8, y 0-3.5): two desks, a round table, a shelf.
        Box('desk_b1', 5.0, 0.35, 1.2, 0.6, 0.75),
        Box('desk_b2', 7.0, 0.35, 1.2, 0.6, 0.75),
        Cylinder('round_table', 6.0, 1.95, 0.4, 0.75),
        Box('shelf_b', 7.75, 2.6, 0.4, 1.2, 1.6),
        # Room C (x 8-12, y 0-3.5): storage shelves and boxes.
        Box('shelf_c', 11.7, 1.7, 0.5, 2.4, 2.0),
        Box('rack_c', 10.0, 0.3, 2.0, 0.5, 1.5),
        Box('crate_c1', 8.5, 0.45, 0.6, 0.6, 0.6),
        Box('crate_c2', 9.0, 2.6, 0.7, 0.5, 0.8, yaw=0.5),
        # Room D (x 0-6, y 5-9): open office with two desk islands, a printer, a plant.
        Box('island_d1', 1.5, 7.3, 1.8, 1.2, 0.75),
        Box('island_d2', 4.3, 7.3, 1.8, 1.2, 0.75),
        Box('printer_d', 5.6, 5.4, 0.6, 0.5, 1.0),
        Cylinder('plant_d', 0.4, 5.45, 0.25, 1.2),
        # Room E (x 6-12, y 5-9): meeting room with a table, a sofa, a cabinet, a plant.
        Box('meeting_table', 9.0, 7.1, 2.4, 1.2, 0.75),
        Box('sofa_e', 11.5, 7.0, 0.8, 1.8, 0.8),
        Box('cabinet_e', 7.2, 8.7, 1.6, 0.45, 1.2),
        Cylinder('plant_e', 6.45, 5.45, 0.2, 1.0),
    ]
    route = (
        (3.0, 4.25),
        (3.0, 6.1),  # through room D's door
        (3.0, 8.4),  # up the aisle between the desk islands, around the east island
        (5.6, 8.4),
        (5.6, 6.2),
        (3.0, 6.1),  # back at the door: a loop closure
        (3.0, 4.25),
        (9.0, 4.25),  # along the corridor, past the doors of rooms B and C
        (9.0, 5.9),  # into the meeting room
        (10.65, 6.0),
        (10.65, 8.1),
        (9.0, 8.1),
    )
    return World(
        name='office_small',
        description='12 x 9 m office: corridor, five rooms with doors and furniture',
        bounds=_bounds(obstacles),
        obstacles=tuple(obstacles),
        start=Pose2D(0.8, 4.25, 0.0),
        route=route,
        goals={
            'storage': Pose2D(10.0, 1.6, -math.pi / 2),
            'meeting_room': Pose2D(10.6, 8.2, math.pi / 2),
            'open_office': Pose2D(3.0, 8.3, math.pi / 2),
        },
        default_goal='storage',
    )


def _workshop() -> World:
    """A 20 m x 14 m hall: machines along the walls, racks, an office, a field of nine pillars."""
    obstacles: list[Obstacle] = [
        *_room('outer', 0.0, 0.0, 20.0, 14.0),
        # A small office in the north-east corner, door on its west wall.
        *walls('office_w', (16.0, 10.0), (16.0, 14.0), doors=[(11.2, 1.0)]),
        *walls('office_s', (16.0, 10.0), (20.0, 10.0)),
        Box('office_desk', 18.6, 13.5, 1.6, 0.7, 0.75),
        Box('office_cabinet', 19.6, 11.0, 0.5, 1.2, 1.8),
        # Structural columns along the long walls.
        *[Box(f'column_s{k}', x, 0.25, 0.4, 0.4, WALL_HEIGHT, kind='wall')
          for k, x in enumerate((5.0, 10.0, 15.0))],
        *[Box(f'column_n{k}', x, 13.75, 0.4, 0.4, WALL_HEIGHT, kind='wall')
          for k, x in enumerate((5.0, 10.0))],
        # Machines along the north wall.
        Box('lathe', 2.6, 13.35, 2.6, 0.9, 1.3, kind='machine'),
        Box('milling_machine', 7.5, 13.1, 1.5, 1.4, 1.9, kind='machine'),
        Cylinder('drill_press', 11.6, 13.4, 0.35, 1.7, kind='machine'),
        Box('cnc_center', 13.6, 12.9, 2.2, 1.6, 2.1, kind='machine'),
        # South side: workbenches, a compressor, pallets.
        Box('workbench_1', 2.5, 0.5, 2.0, 0.8, 0.9),
        Box('workbench_2', 7.5, 0.5, 2.0, 0.8, 0.9),
        Cylinder('compressor', 12.0, 0.75, 0.45, 1.2, kind='machine'),
        Box('pallet_1', 17.5, 0.8, 1.2, 1.0, 1.0),
        Box('press', 3.5, 3.5, 1.5, 1.0, 1.8, kind='machine'),
        Box('welding_table', 0.6, 9.0, 0.8, 1.6, 0.9),
        # Shelving racks forming an aisle in the east half.
        Box('rack_1', 15.0, 5.0, 0.6, 4.0, 2.2),
        Box('rack_2', 17.8, 5.0, 0.6, 4.0, 2.2),
        Box('big_machine', 12.5, 9.6, 2.0, 1.4, 1.6, kind='machine'),
        Box('tool_cart', 10.5, 3.0, 0.8, 0.5, 0.9, yaw=0.35),
        # The route-planning case: nine pillars between start and goal (3 x 3, 1.5 m apart).
        *[
            Cylinder(f'pillar_{3 * i + j + 1}', 6.0 + 1.5 * i, 5.5 + 1.5 * j, 0.2, 2.0,
                     kind='pillar')
            for i in range(3)
            for j in range(3)
        ],
    ]
    route = (
        (3.0, 10.3),
        (10.4, 10.5),  # along the machines on the north side
        (10.6, 8.2),
        (13.9, 7.6),  # past the big machine, to the end of the racks
        (11.0, 4.5),
        (5.0, 4.5),  # south of the pillar field
        (5.0, 6.25),
        (10.0, 6.25),  # between two rows of pillars
        (11.5, 7.0),
    )
    return World(
        name='workshop',
        description='20 x 14 m hall: machines, racks, an office, nine pillars',
        bounds=_bounds(obstacles),
        obstacles=tuple(obstacles),
        start=Pose2D(2.0, 7.0, 0.0),
        route=route,
        goals={
            # Behind the nine pillars, as in the paper's route-planning case (its Fig. 2).
            'behind_pillars': Pose2D(11.5, 7.0, 0.0),
            'office': Pose2D(18.0, 12.0, math.pi / 2),
            'rack_aisle': Pose2D(16.4, 3.0, -math.pi / 2),
        },
        default_goal='behind_pillars',
    )


def _real_room() -> World:
    """A 5 m x 4 m room with one obstacle, noisier sensors and slipping wheels."""
    obstacles: list[Obstacle] = [
        *walls('wall_south', (0.0, 0.0), (5.0, 0.0)),
        *walls('wall_north', (0.0, 4.0), (5.0, 4.0)),
        *walls('wall_east', (5.0, 0.0), (5.0, 4.0)),
        # The west wall has a (closed) door: a recess the wall's depth (10 cm), the leaf flush
        # with the wall's outer face so that no gap joins the room to the outside.
        *walls('wall_west', (0.0, 0.0), (0.0, 4.0), doors=[(2.9, 0.9)]),
        Box('door_leaf', -0.075, 2.9, 0.05, 1.0, 2.0, kind='wall'),
        Box('radiator', 2.5, 0.11, 1.2, 0.12, 0.6, kind='wall'),
        Box('corner_column', 4.8, 3.8, 0.3, 0.3, WALL_HEIGHT, kind='wall'),
        # The one obstacle.
        Box('obstacle', 2.5, 2.0, 0.6, 0.5, 0.7),
    ]
    route = (
        (4.05, 0.8),
        (4.05, 3.15),
        (1.0, 3.15),
        (1.0, 0.8),
        (4.05, 0.8),
        (4.05, 3.15),
        (1.0, 3.15),
        (1.0, 1.4),
    )
    return World(
        name='real_room',
        description='5 x 4 m room, one obstacle, lidar noise and dropouts, wheel slip',
        bounds=_bounds(obstacles),
        obstacles=tuple(obstacles),
        start=Pose2D(0.8, 0.8, 0.0),
        route=route,
        goals={'far_corner': Pose2D(4.1, 3.2, math.pi / 2)},
        default_goal='far_corner',
        noise=Noise(
            lidar_sigma=0.02,
            lidar_sigma_rel=0.01,
            lidar_dropout=0.03,
            depth_dropout=0.02,
            odom_scale_left=1.003,
            odom_scale_right=0.995,
            odom_wheelbase_scale=1.03,
            odom_wheel_sigma=0.004,
            slip_mean=0.03,
            slip_sigma=0.03,
            slip_tau=0.5,
        ),
    )


WORLDS: dict[str, World] = {w.name: w for w in (_office_small(), _workshop(), _real_room())}


def get_world(name: str) -> World:
    """The world called ``name``.

    Raises:
        KeyError: no such world; the message lists the known ones.
    """
    try:
        return WORLDS[name]
    except KeyError:
        raise KeyError(f'unknown world {name!r} (known: {", ".join(sorted(WORLDS))})') from None
