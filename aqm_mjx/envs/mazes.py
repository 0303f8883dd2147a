"""Maze layouts, tasks and the cell <-> world geometry of OGBench's locomaze.

The layouts, tasks and constants are those of ``ogbench/locomaze/maze.py`` (checked against the
installed ``ogbench`` package in ``tests/test_envs.py``). A layout is an occupancy grid: ``1`` is a
wall block, ``0`` free floor. Cell ``(i, j)`` is centred at ``x = 4 j - 4, y = 4 i - 4``.
"""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np

MAZE_UNIT = 4.0  #: side of one maze cell (m)
MAZE_OFFSET = 4.0  #: world x (y) of column (row) 0 is -MAZE_OFFSET
MAZE_HEIGHT = 0.5  #: wall height in maze units (walls are 2 m tall)
START_GOAL_NOISE = 1.0  #: start and goal are cell centres + U(-1, 1) * MAZE_UNIT / 4 per axis

_LAYOUTS = {
    'arena': [
        '11111111',
        '10000001',
        '10000001',
        '10000001',
        '10000001',
        '10000001',
        '10000001',
        '11111111',
    ],
    'medium': [
        '11111111',
        '10011001',
        '10010001',
        '11000111',
        '10010001',
        '10100101',
        '10001001',
        '11111111',
    ],
    'large': [
        '111111111111',
        '100001000001',
        '101101010101',
        '100000010001',
        '101111011101',
        '100101000001',
        '110101010111',
        '100100010001',
        '111111111111',
    ],
    'giant': [
        '1111111111111111',
        '1010000001100001',
        '1010110101001101',
        '1000100100010001',
        '1011101111110101',
        '1000100010000101',
        '1110101001010111',
        '1000100100010001',
        '1010101111110101',
        '1011100010001101',
        '1000001000100001',
        '1111111111111111',
    ],
    'teleport': [
        '111111111111',
        '100000101001',
        '110100010011',
        '110111000001',
        '100001010101',
        '101101010101',
        '101101010101',
        '100001000101',
        '111111111111',
    ],
}

# (init cell, goal cell) of OGBench's evaluation tasks, in OGBench's order (task ids 1..5).
_TASKS = {
    'arena': [((1, 1), (6, 6))],
    'medium': [((1, 1), (6, 6)), ((6, 1), (1, 6)), ((5, 3), (4, 2)), ((6, 5), (6, 1)), ((2, 6), (1, 1))],
    'large': [((1, 1), (7, 10)), ((5, 4), (7, 1)), ((7, 4), (1, 10)), ((3, 8), (5, 4)), ((1, 1), (5, 4))],
    'giant': [((1, 1), (10, 14)), ((1, 14), (10, 1)), ((8, 14), (1, 1)), ((8, 3), (5, 12)), ((5, 9), (3, 8))],
    'teleport': [((1, 10), (7, 1)), ((1, 1), (7, 10)), ((5, 6), (7, 10)), ((7, 1), (7, 10)), ((5, 6), (7, 1))],
}

# Teleport maze: an inbound portal within TELEPORT_RADIUS * 1.5 of the agent sends it to one of the
# outbound portals, uniformly at random.
TELEPORT_IN = ((4, 6), (5, 1))
TELEPORT_OUT = ((1, 7), (6, 1), (6, 10))
TELEPORT_RADIUS = 1.0

MAZE_NAMES = tuple(_LAYOUTS)


@dataclasses.dataclass(frozen=True)
class Task:
    """One evaluation task: start and goal cells and their centres (no noise)."""

    task_id: int  # 1-based, as in OGBench
    init_ij: tuple[int, int]
    goal_ij: tuple[int, int]
    init_xy: tuple[float, float]
    goal_xy: tuple[float, float]


def check_maze_name(maze: str) -> str:
    if maze not in _LAYOUTS:
        raise ValueError(f'unknown maze {maze!r}; expected one of {", ".join(MAZE_NAMES)}')
    return maze


def layout(maze: str) -> np.ndarray:
    """The occupancy grid of a maze: int8 ``[H, W]``, 1 = wall."""
    rows = _LAYOUTS[check_maze_name(maze)]
    return np.array([[int(c) for c in r] for r in rows], dtype=np.int8)


def ij_to_xy(ij, xp=np):
    """Cell centre(s): ``ij [..., 2]`` -> ``xy [..., 2]`` (x from column j, y from row i); ``xp=jnp``
    inside a jitted program (float32 there, float64 with numpy)."""
    ij = xp.asarray(ij, dtype=np.float64 if xp is np else xp.float32)
    return xp.stack([ij[..., 1] * MAZE_UNIT - MAZE_OFFSET, ij[..., 0] * MAZE_UNIT - MAZE_OFFSET], axis=-1)


def xy_to_ij(xy):
    """Cell index of positions (jittable): ``xy [..., 2]`` -> int32 ``ij [..., 2]`` (row i from y,
    column j from x); OGBench's ``xy_to_ij``."""
    ij = jnp.floor((jnp.asarray(xy)[..., ::-1] + MAZE_OFFSET + 0.5 * MAZE_UNIT) / MAZE_UNIT)
    return ij.astype(jnp.int32)


def tasks(maze: str) -> tuple[Task, ...]:
    """OGBench's evaluation tasks of a maze (5, or 1 for the arena)."""
    out = []
    for k, (init_ij, goal_ij) in enumerate(_TASKS[check_maze_name(maze)]):
        out.append(Task(k + 1, init_ij, goal_ij, tuple(ij_to_xy(init_ij).tolist()), tuple(ij_to_xy(goal_ij).tolist())))
    return tuple(out)


def validate_grid(grid, maze: str) -> np.ndarray:
    """Check a user-supplied occupancy grid for ``maze`` and return it as int8 ``[H, W]``.

    Raises:
        ValueError: wrong number of dimensions, a shape other than the maze's, non-finite values,
            values other than 0 and 1, or a grid whose border is not all wall (the agent could
            leave the maze).
    """
    ref = layout(maze)
    arr = np.asarray(grid)
    if arr.dtype == object:
        raise ValueError('grid must be a numeric array, got an object array')
    if arr.ndim != 2:
        raise ValueError(f'grid must be 2-D [rows, cols]; got shape {arr.shape}')
    if arr.shape != ref.shape:
        raise ValueError(f'grid for maze {maze!r} must have shape {ref.shape}; got {arr.shape}')
    if np.issubdtype(arr.dtype, np.floating) and not np.all(np.isfinite(arr)):
        raise ValueError('grid contains NaN or inf')
    bad = ~np.isin(arr, (0, 1))
    if bad.any():
        i, j = np.argwhere(bad)[0]
        raise ValueError(f'grid values must be 0 (free) or 1 (wall); cell ({i}, {j}) is {arr[i, j].item()!r}')
    border = np.concatenate([arr[0], arr[-1], arr[:, 0], arr[:, -1]])
    if not np.all(border == 1):
        raise ValueError('grid border must be all walls (1), or the agent could leave the maze')
    return arr.astype(np.int8)


def wall_distance(xy, grid) -> np.ndarray:
    """Distance from points ``xy [..., 2]`` to the nearest wall block of ``grid [H, W]`` (numpy).

    Negative inside a block. Brute force over all blocks; for checks and plots, not hot loops.
    """
    cells = ij_to_xy(np.argwhere(np.asarray(grid) == 1))  # [C, 2]
    d = np.abs(np.asarray(xy, dtype=np.float64)[..., None, :] - cells) - MAZE_UNIT / 2  # per-axis gap
    outside = np.linalg.norm(np.maximum(d, 0.0), axis=-1)
    inside = np.minimum(np.max(d, axis=-1), 0.0)
    return np.min(outside + inside, axis=-1)


NEIGHBOURS = ((-1, 0), (0, -1), (1, 0), (0, 1))  # OGBench's BFS order: up, left, down, right in (i, j)


def bfs_from(grid, src: tuple[int, int]) -> np.ndarray:
    """BFS step counts from cell ``src`` to every cell: int64 ``[H, W]``, -1 for walls and cells
    with no path (NumPy only, so collection does not need SciPy)."""
    g = np.asarray(grid)
    h, w = g.shape
    dist = -np.ones((h, w), np.int64)
    if g[src] != 0:
        return dist
    dist[src] = 0
    frontier = [src]
    while frontier:
        nxt = []
        for i, j in frontier:
            for di, dj in NEIGHBOURS:
                ni, nj = i + di, j + dj
                if 0 <= ni < h and 0 <= nj < w and g[ni, nj] == 0 and dist[ni, nj] < 0:
                    dist[ni, nj] = dist[i, j] + 1
                    nxt.append((ni, nj))
        frontier = nxt
    return dist


def bfs_steps(grid) -> np.ndarray:
    """Cell-to-cell BFS step counts: int64 ``[H*W, H*W]`` over flat cells ``i * W + j``, -1 where
    either cell is a wall or there is no path."""
    g = np.asarray(grid)
    h, w = g.shape
    out = -np.ones((h * w, h * w), np.int64)
    for src in np.flatnonzero(g.reshape(-1) == 0):
        out[src] = bfs_from(g, divmod(int(src), w)).reshape(-1)
    return out


def geodesic_table(grid, sub: int = 2) -> np.ndarray:
    """Exact shortest-path distances (m) between the sub-cells of a maze's free space.

    Each cell is split into ``sub x sub`` squares; moves go to the 4 neighbours (one square,
    ``MAZE_UNIT / sub`` m). Returns float32 ``[H*W*sub*sub, H*W*sub*sub]``, ``inf`` where either
    square is in a wall or unreachable. Index squares with :func:`xy_to_subcell`. A stand-in for a
    trained quasimetric in tests and planning checks.
    """
    from scipy.sparse import coo_matrix  # pylint: disable=import-outside-toplevel
    from scipy.sparse.csgraph import shortest_path  # pylint: disable=import-outside-toplevel

    g = np.kron(np.asarray(grid), np.ones((sub, sub), dtype=np.int8))
    h, w = g.shape
    free = g == 0
    idx = np.arange(h * w).reshape(h, w)
    rows, cols = [], []
    for a, b in (((slice(None), slice(0, -1)), (slice(None), slice(1, None))),
                 ((slice(0, -1), slice(None)), (slice(1, None), slice(None)))):
        ok = free[a] & free[b]
        rows.append(idx[a][ok])
        cols.append(idx[b][ok])
    r, c = np.concatenate(rows), np.concatenate(cols)
    adj = coo_matrix((np.ones(len(r)), (r, c)), shape=(h * w, h * w)).tocsr()
    out = shortest_path(adj, method='D', directed=False, unweighted=True).astype(np.float32) * (MAZE_UNIT / sub)
    out[~free.reshape(-1)] = np.inf
    out[:, ~free.reshape(-1)] = np.inf
    return out


def xy_to_subcell(xy, grid_shape, sub: int = 2, xp=np):
    """Index into :func:`geodesic_table` of points ``xy [..., 2]``.

    ``xp=jax.numpy`` gives the jittable version (int32; ``grid_shape`` and ``sub`` may be arrays).
    """
    xy = xp.asarray(xy, dtype=np.float64) if xp is np else xp.asarray(xy)
    index_dtype = np.int64 if xp is np else jnp.int32
    step = MAZE_UNIT / sub
    col = xp.floor((xy[..., 0] + MAZE_OFFSET + MAZE_UNIT / 2) / step).astype(index_dtype)
    row = xp.floor((xy[..., 1] + MAZE_OFFSET + MAZE_UNIT / 2) / step).astype(index_dtype)
    h, w = grid_shape[0] * sub, grid_shape[1] * sub
    return xp.clip(row, 0, h - 1) * w + xp.clip(col, 0, w - 1)


def subcell_to_xy(index, grid_shape, sub: int = 2) -> np.ndarray:
    """Centre ``[..., 2]`` of :func:`geodesic_table` squares (the inverse of :func:`xy_to_subcell`)."""
    row, col = np.divmod(np.asarray(index), grid_shape[1] * sub)
    step = MAZE_UNIT / sub
    return np.stack([col, row], -1) * step - MAZE_OFFSET - MAZE_UNIT / 2 + step / 2


# ------------------------------------------------------------------------- cells the datasets use
def free_cells(grid) -> np.ndarray:
    """int32 ``[F, 2]`` (i, j) of the free cells, row-major."""
    return np.argwhere(np.asarray(grid) == 0).astype(np.int32)


def junction_cells(grid) -> np.ndarray:
    """int32 ``[V, 2]`` free cells that are not straight corridor cells (OGBench's navigate goals).

    A corridor cell has free cells on two opposite sides and walls on the other two.
    """
    g = np.asarray(grid)
    h, w = g.shape

    def wall(i, j):
        return not (0 <= i < h and 0 <= j < w) or g[i, j] != 0

    keep = []
    for i, j in free_cells(g):
        vertical = not wall(i - 1, j) and not wall(i + 1, j) and wall(i, j - 1) and wall(i, j + 1)
        horizontal = not wall(i, j - 1) and not wall(i, j + 1) and wall(i - 1, j) and wall(i + 1, j)
        if not (vertical or horizontal):
            keep.append((i, j))
    return np.asarray(keep, np.int32).reshape(-1, 2)


def cells_at_bfs_distance(grid, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Cells exactly ``k`` BFS steps from each free cell.

    Returns:
        ``cells`` int32 ``[F, C, 2]`` (padded with the start cell itself) and ``count`` int32 ``[F]``
        for the free cells in :func:`free_cells` order. Where no cell is ``k`` steps away the count is
        1 and the only entry is the start cell (OGBench's fallback).
    """
    g = np.asarray(grid)
    w = g.shape[1]
    steps = bfs_steps(g)
    found = []
    for i0, j0 in free_cells(g):
        ring = [divmod(int(c), w) for c in np.flatnonzero(steps[i0 * w + j0] == k)]
        found.append(ring or [(int(i0), int(j0))])
    width = max(len(r) for r in found)
    cells = np.zeros((len(found), width, 2), np.int32)
    for n, ring in enumerate(found):
        cells[n] = np.asarray(ring + [ring[0]] * (width - len(ring)), np.int32)
    return cells, np.asarray([len(r) for r in found], np.int32)
