"""Global planner: A* on the costmap, 8-connected (Hart, Nilsson and Raphael 1968).

A step into a cell costs its length (1 or sqrt 2 cells) times the cell's ``step_cost``
multiplier (1 in the open, more near obstacles, inf where lethal), so the octile distance is an
admissible heuristic and the plan is the cheapest one on the grid. Ties break on the cell index,
so the same inputs always give the same plan. Plain Python over flat lists: a 400 x 300 grid is
planned in tens of milliseconds for the usual indoor goal.
"""

from __future__ import annotations

import heapq
import math
from collections import deque

import numpy as np

from navigator_costmap import Costmap
from navigator_geometry import FloatArray

SQRT2 = math.sqrt(2.0)
_OCTILE = SQRT2 - 2.0


def nearest_free_cell(costmap: Costmap, cell: tuple[int, int],
                      max_distance: float) -> tuple[int, int] | None:
    """The nearest non-lethal cell to ``cell`` within ``max_distance`` (m), breadth first."""
    h, w = costmap.shape
    if costmap.contains(cell) and not costmap.lethal[cell]:
        return cell
    limit = max_distance / costmap.resolution
    r0, c0 = cell
    seen = {cell}
    queue = deque([cell])
    best: tuple[float, tuple[int, int]] | None = None
    while queue:
        r, c = queue.popleft()
        for nr, nc in ((r + 1, c), (r - 1, c), (r, c + 1), (r, c - 1)):
            if (nr, nc) in seen or math.hypot(nr - r0, nc - c0) > limit:
                continue
            seen.add((nr, nc))
            if not (0 <= nr < h and 0 <= nc < w):
                continue
            if not costmap.lethal[nr, nc]:
                d = math.hypot(nr - r0, nc - c0)
                if best is None or (d, (nr, nc)) < best:
                    best = (d, (nr, nc))
            queue.append((nr, nc))
    return None if best is None else best[1]


def astar(costmap: Costmap, start: tuple[int, int],
          goal: tuple[int, int]) -> list[tuple[int, int]] | None:
    """The cheapest 8-connected cell path from start to goal, both included; None if none.

    Both cells must be on the grid and not lethal (see ``nearest_free_cell``).
    """
    if not (costmap.contains(start) and costmap.contains(goal)):
        return None
    if costmap.lethal[start] or costmap.lethal[goal]:
        return None
    h, w = costmap.shape
    # The outer ring is lethal (build_costmap), so neighbours of a free cell never leave the
    # grid and the flat index needs no bounds checks.
    mult: list[float] = costmap.step_cost.ravel().tolist()
    n_cells = h * w
    g = [math.inf] * n_cells
    parent = [-1] * n_cells
    closed = bytearray(n_cells)
    s = start[0] * w + start[1]
    t = goal[0] * w + goal[1]
    gr, gc = goal
    neighbours = ((1, 1.0), (-1, 1.0), (w, 1.0), (-w, 1.0),
                  (w + 1, SQRT2), (w - 1, SQRT2), (-w + 1, SQRT2), (-w - 1, SQRT2))
    g[s] = 0.0
    heap: list[tuple[float, int]] = [(0.0, s)]
    inf = math.inf
    while heap:
        _, idx = heapq.heappop(heap)
        if closed[idx]:
            continue
        if idx == t:
            break
        closed[idx] = 1
        g_idx = g[idx]
        for offset, length in neighbours:
            n = idx + offset
            m = mult[n]
            if m == inf or closed[n]:
                continue
            cand = g_idx + length * m
            if cand < g[n]:
                g[n] = cand
                parent[n] = idx
                r, c = divmod(n, w)
                dr = abs(r - gr)
                dc = abs(c - gc)
                heapq.heappush(heap, (cand + dr + dc + _OCTILE * min(dr, dc), n))
    if t != s and parent[t] < 0:
        return None
    cells = [t]
    while cells[-1] != s:
        cells.append(parent[cells[-1]])
    cells.reverse()
    return [divmod(i, w) for i in cells]


def cells_to_points(costmap: Costmap, cells: list[tuple[int, int]]) -> FloatArray:
    """Cell centres of a cell path as map points ``(N, 2)``."""
    rc = np.asarray(cells, dtype=np.float64).reshape(-1, 2)
    xs = costmap.origin_x + (rc[:, 1] + 0.5) * costmap.resolution
    ys = costmap.origin_y + (rc[:, 0] + 0.5) * costmap.resolution
    return np.column_stack([xs, ys])


def smooth_path(points: FloatArray, costmap: Costmap, passes: int = 3) -> FloatArray:
    """Soften the grid's 45-degree staircase with a few 3-point averages, never into lethal
    cells; the end points stay where they are."""
    out = points.copy()
    if len(out) < 3:
        return out
    for _ in range(passes):
        averaged = out.copy()
        averaged[1:-1] = 0.25 * out[:-2] + 0.5 * out[1:-1] + 0.25 * out[2:]
        ok = ~costmap.lethal_at(averaged)
        ok[0] = ok[-1] = False
        out[ok] = averaged[ok]
    return out
