"""Top-down figures of a world (matplotlib, no display needed): geometry, route, goals, paths."""

from __future__ import annotations

import csv
import math
from collections.abc import Mapping, Sequence
from pathlib import Path

import matplotlib

matplotlib.use('Agg')  # headless: never try to open a window

import matplotlib.pyplot as plt
from matplotlib.axes import Axes
from matplotlib.patches import Circle, Polygon

from .maps import OccupancyMap
from .worlds import Box, Pose2D, World

_COLOURS = {
    'wall': '#404040',
    'furniture': '#b08850',
    'machine': '#5078a0',
    'pillar': '#c04040',
}

Path2D = Sequence[tuple[float, float]]


def read_path(csv_path: Path) -> dict[str, list[tuple[float, float]]]:
    """Read a ``path.csv`` written by ``sim run``.

    Returns:
        ``{'ground_truth': [(x, y)...], 'odometry': [(x, y)...]}``, both in the map frame (the
        odometry is placed at the start pose given in the file's ``start_*`` columns).

    Raises:
        ValueError: a required column is missing (the message names the file and column).
    """
    with open(csv_path, newline='') as f:
        rows = list(csv.DictReader(f))
    required = ('x', 'y', 'odom_x', 'odom_y', 'start_x', 'start_y', 'start_yaw')
    if rows:
        for name in required:
            if name not in rows[0]:
                raise ValueError(f'{csv_path}: column {name!r} missing')
    truth = [(float(r['x']), float(r['y'])) for r in rows]
    odom = []
    for r in rows:
        sx, sy, syaw = float(r['start_x']), float(r['start_y']), float(r['start_yaw'])
        ox, oy = float(r['odom_x']), float(r['odom_y'])
        c, s = math.cos(syaw), math.sin(syaw)
        odom.append((sx + c * ox - s * oy, sy + s * ox + c * oy))
    return {'ground_truth': truth, 'odometry': odom}


def render_world(
    world: World,
    out: Path,
    *,
    paths: dict[str, Path2D] | None = None,
    grid: OccupancyMap | None = None,
    show_route: bool = True,
    show_goals: bool = True,
    title: str | None = None,
    dpi: int = 120,
) -> Path:
    """Draw ``world`` from above and write it as a PNG.

    Args:
        world: the world to draw.
        out: PNG file to write (parent folders are created).
        paths: named paths to overlay (e.g. ground truth and odometry from ``read_path``).
        grid: an occupancy grid to draw underneath the geometry (e.g. a map a SLAM node built).
        show_route: draw the scripted driver's route.
        show_goals: draw the world's named goal poses.
        title: figure title (default: the world's name and description).
        dpi: resolution.

    Returns:
        ``out``.
    """
    xmin, ymin, xmax, ymax = world.bounds
    width = xmax - xmin
    height = ymax - ymin
    scale = 8.0 / max(width, height)
    fig, ax = plt.subplots(figsize=(max(4.0, width * scale) + 1.5, max(3.0, height * scale) + 1.0))
    try:
        draw_world(ax, world, paths=paths, grid=grid, show_route=show_route,
                   show_goals=show_goals)
        ax.set_xlabel('x (m, map frame)')
        ax.set_ylabel('y (m)')
        ax.set_title(title if title is not None else f'{world.name}: {world.description}',
                     fontsize=9)
        ax.legend(loc='upper left', bbox_to_anchor=(1.0, 1.0), fontsize=8)
        out.parent.mkdir(parents=True, exist_ok=True)
        fig.tight_layout()
        fig.savefig(out, dpi=dpi)
    finally:
        plt.close(fig)
    return out


def draw_world(
    ax: Axes,
    world: World,
    *,
    paths: Mapping[str, Path2D] | None = None,
    grid: OccupancyMap | None = None,
    show_route: bool = True,
    show_goals: bool = True,
    obstacle_alpha: float = 1.0,
) -> None:
    """Draw ``world`` from above on ``ax`` (see :func:`render_world`; figures with several
    panels call this once per panel)."""
    xmin, ymin, xmax, ymax = world.bounds
    if grid is not None:
        import numpy as np

        shade = np.where(grid.data < 0, 0.8, 1.0 - np.clip(grid.data, 0, 100) / 100.0)
        ax.imshow(
            shade, cmap='gray', vmin=0.0, vmax=1.0, origin='lower', interpolation='nearest',
            extent=(grid.origin_x, grid.origin_x + grid.width * grid.resolution,
                    grid.origin_y, grid.origin_y + grid.height * grid.resolution),
            alpha=0.6,
        )
    for o in world.obstacles:
        colour = _COLOURS.get(o.kind, '#808080')
        if isinstance(o, Box):
            ax.add_patch(Polygon(o.corners(), closed=True, facecolor=colour, edgecolor='none',
                                 alpha=obstacle_alpha))
        else:
            ax.add_patch(Circle((o.x, o.y), o.radius, facecolor=colour, edgecolor='none',
                                alpha=obstacle_alpha))
    if show_route:
        pts = [(world.start.x, world.start.y), *world.route]
        ax.plot([p[0] for p in pts], [p[1] for p in pts], ':', color='#30a030', lw=1.0,
                label='route')
    _pose_marker(ax, world.start, 'start', '#30a030')
    if show_goals:
        for name, goal in world.goals.items():
            _pose_marker(ax, goal, name, '#d08000')
    styles = ['-', '--', '-.', ':']
    colours = ['#1060d0', '#d02020', '#8020c0', '#000000']
    for k, (name, path) in enumerate((paths or {}).items()):
        if path:
            ax.plot([p[0] for p in path], [p[1] for p in path], styles[k % len(styles)],
                    color=colours[k % len(colours)], lw=1.4, label=name)
    ax.set_xlim(xmin - 0.3, xmax + 0.3)
    ax.set_ylim(ymin - 0.3, ymax + 0.3)
    ax.set_aspect('equal')
    ax.grid(True, lw=0.3, alpha=0.5)


def _pose_marker(ax: Axes, pose: Pose2D, label: str, colour: str) -> None:
    ax.plot([pose.x], [pose.y], 'o', color=colour, ms=5)
    ax.annotate('', xy=(pose.x + 0.4 * math.cos(pose.yaw), pose.y + 0.4 * math.sin(pose.yaw)),
                xytext=(pose.x, pose.y), arrowprops={'arrowstyle': '->', 'color': colour})
    ax.annotate(label, (pose.x, pose.y), textcoords='offset points', xytext=(4, 4), fontsize=7,
                color=colour)
