"""Test-time shifts of a maze: our AntMaze counterpart of the paper's gates and obstacles (section 5.1.3).

A shift is an occupancy grid of the same shape as the maze, given to the environments at reset
(walls are per-environment data, so a batch may mix variants without recompiling):

- ``close-I-J`` adds a wall in free cell (I, J) that lies on the shortest route of at least one
  evaluation task, chosen so that every task stays solvable and no free cell is cut off: an
  alternative route always exists, only longer.
- ``open-I-J`` removes interior wall (I, J) between two free cells on opposite sides, so that at
  least one task gets a shorter route.

:func:`suite` picks, deterministically, the closures that lengthen the tasks' routes most and the
openings that shorten them most (ties broken row-major), spread so that no two chosen cells touch.
"""

from __future__ import annotations

import numpy as np

from aqm_mjx.envs import mazes

BASE = 'base'


def route_lengths(grid, maze: str) -> np.ndarray:
    """BFS steps from start to goal cell of each evaluation task of ``maze`` in ``grid``: int64
    ``[tasks]``, -1 where the goal cannot be reached."""
    return np.array([mazes.bfs_from(grid, t.init_ij)[t.goal_ij] for t in mazes.tasks(maze)], np.int64)


def _connected(grid) -> bool:
    free = np.argwhere(np.asarray(grid) == 0)
    return len(free) == 0 or int((mazes.bfs_from(grid, tuple(free[0])) >= 0).sum()) == len(free)


def candidates(maze: str) -> dict[str, tuple[np.ndarray, int]]:
    """Every valid single-cell shift of ``maze``: name -> (grid, score), where score is how many
    BFS steps the tasks' routes get longer (closures) or shorter (openings) in total."""
    if maze == 'teleport':
        raise ValueError('no shift suite for the teleport maze: its portals are not in the grid, so route '
                         'lengths (and which corridors have alternatives) are not defined by walls alone')
    base = mazes.layout(maze)
    ref = route_lengths(base, maze)
    ends = {t.init_ij for t in mazes.tasks(maze)} | {t.goal_ij for t in mazes.tasks(maze)}
    h, w = base.shape
    out = {}
    for i in range(1, h - 1):
        for j in range(1, w - 1):
            g = base.copy()
            if base[i, j] == 0:
                if (i, j) in ends:
                    continue
                g[i, j] = 1
                lengths = route_lengths(g, maze)
                if (lengths < 0).any() or not _connected(g):
                    continue
                score = int((lengths - ref).sum())
                if score > 0:
                    out[f'close-{i}-{j}'] = (g, score)
            else:
                opposite = (base[i - 1, j] == 0 and base[i + 1, j] == 0) or (base[i, j - 1] == 0 and base[i, j + 1] == 0)
                if not opposite:
                    continue
                g[i, j] = 0
                score = int((ref - route_lengths(g, maze)).sum())
                if score > 0:
                    out[f'open-{i}-{j}'] = (g, score)
    return out


def _cell(name: str) -> tuple[int, int]:
    _, i, j = name.split('-')
    return int(i), int(j)


def suite(maze: str, n_close: int = 3, n_open: int = 2) -> dict[str, np.ndarray]:
    """The evaluation variants of ``maze``: ``{'base': layout, 'close-I-J': grid, ..., 'open-I-J':
    grid, ...}`` (int8 ``[H, W]``), at most ``n_close`` closures and ``n_open`` openings."""
    cands = candidates(maze)
    out = {BASE: mazes.layout(maze)}
    for kind, n in (('close', n_close), ('open', n_open)):
        ranked = sorted((k for k in cands if k.startswith(kind)), key=lambda k: (-cands[k][1], _cell(k)))
        chosen: list[tuple[int, int]] = []
        for k in ranked:
            if len(chosen) == n:
                break
            c = _cell(k)
            if all(max(abs(c[0] - o[0]), abs(c[1] - o[1])) > 1 for o in chosen):
                chosen.append(c)
                out[k] = cands[k][0]
    return out


def variant(maze: str, name: str) -> np.ndarray:
    """One variant by name: ``'base'``, a name from :func:`suite`, or any valid ``close-I-J`` /
    ``open-I-J`` from :func:`candidates`."""
    if name == BASE:
        return mazes.layout(maze)
    cands = candidates(maze)
    if name not in cands:
        listed = ', '.join(suite(maze))
        raise ValueError(f'unknown shift {name!r} for maze {maze!r}; its suite is: {listed} (any close-I-J on a '
                         f'task route with an alternative, or open-I-J that shortens a route, also works)')
    return cands[name][0]
