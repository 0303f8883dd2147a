"""Small synthetic datasets with known shortest paths, for tests and quick experiments.

``grid_walks`` makes random walks on a directed grid graph: states are the (x, y) of grid cells,
actions the attempted move, and some edges are one-way, so the true time-to-reach is asymmetric.
"""

from __future__ import annotations

from collections import deque

import numpy as np

MOVES = np.array([(1, 0), (-1, 0), (0, 1), (0, -1)], np.int64)  # +x, -x, +y, -y


def one_way_grid(size: int = 5, one_way_column: int = 2, open_rows=(4,)) -> dict:
    """A ``size x size`` grid whose edges from column ``one_way_column`` to the next go in +x only,
    except in ``open_rows`` (so every cell still reaches every other, some by a detour).

    Returns:
        dict with ``size`` and ``allowed`` bool ``[size, size, 4]``: move k from cell (x, y) allowed.
    """
    allowed = np.zeros((size, size, 4), bool)
    for x in range(size):
        for y in range(size):
            for k, (dx, dy) in enumerate(MOVES):
                nx, ny = x + dx, y + dy
                ok = 0 <= nx < size and 0 <= ny < size
                if ok and dx == -1 and x == one_way_column + 1 and y not in open_rows:  # one-way: no way back
                    ok = False
                allowed[x, y, k] = ok
    return dict(size=size, allowed=allowed)


def shortest_steps(grid: dict) -> np.ndarray:
    """BFS step counts ``[size*size, size*size]`` (from cell ``x * size + y`` to cell ...)."""
    n, allowed = grid['size'], grid['allowed']
    out = np.full((n * n, n * n), np.inf)
    for src in range(n * n):
        out[src, src] = 0
        q = deque([src])
        while q:
            c = q.popleft()
            x, y = divmod(c, n)
            for k, (dx, dy) in enumerate(MOVES):
                if allowed[x, y, k]:
                    nc = (x + dx) * n + (y + dy)
                    if out[src, nc] == np.inf:
                        out[src, nc] = out[src, c] + 1
                        q.append(nc)
    return out


def grid_walks(grid: dict, episodes: int = 400, steps: int = 40, seed: int = 0) -> dict:
    """Uniform random walks (a forbidden move stays put) in OGBench's file layout.

    Returns:
        dict with ``observations [E*T, 2]`` (cell x, y as floats), ``actions [E*T, 2]`` (attempted
        move), ``terminals [E*T]`` and ``cells [E*T]`` (flat cell index ``x * size + y``).
    """
    rng = np.random.default_rng(seed)
    n, allowed = grid['size'], grid['allowed']
    obs = np.zeros((episodes, steps, 2), np.float32)
    act = np.zeros((episodes, steps, 2), np.float32)
    for e in range(episodes):
        x, y = rng.integers(0, n, 2)
        for t in range(steps):
            k = rng.integers(0, 4)
            obs[e, t] = (x, y)
            act[e, t] = MOVES[k]
            if allowed[x, y, k]:
                x, y = x + MOVES[k][0], y + MOVES[k][1]
    term = np.zeros((episodes, steps), bool)
    term[:, -1] = True
    o = obs.reshape(-1, 2)
    return dict(observations=o, actions=act.reshape(-1, 2), terminals=term.reshape(-1),
                cells=(o[:, 0] * n + o[:, 1]).astype(np.int64))


def point_walks(maze: str = 'medium', n_traj: int = 40, t_len: int = 50, step: float = 0.2, seed: int = 0) -> dict:
    """Gaussian random walks of a point from random free cells of ``maze``, in OGBench's layout for
    ``pointmaze-MAZE`` (states: the point's x-y; the action is the next displacement over
    ``2 * step``, clipped to [-1, 1]). They ignore walls: enough to exercise training, mapping and
    evaluation end to end in seconds, not to learn a skill."""
    from aqm_mjx.envs import mazes  # pylint: disable=import-outside-toplevel

    rng = np.random.default_rng(seed)
    free = mazes.ij_to_xy(np.argwhere(mazes.layout(maze) == 0))
    xy = free[rng.integers(len(free), size=n_traj)][:, None] + np.cumsum(rng.normal(0, step, (n_traj, t_len, 2)), 1)
    obs = xy.reshape(-1, 2).astype(np.float32)
    term = np.zeros((n_traj, t_len), np.float32)
    term[:, -1] = 1
    act = np.zeros_like(xy)
    act[:, :-1] = np.clip(np.diff(xy, axis=1) / (2 * step), -1, 1)
    return dict(observations=obs, actions=act.reshape(-1, 2).astype(np.float32), terminals=term.reshape(-1))
