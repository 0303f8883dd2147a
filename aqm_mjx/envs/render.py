"""Top-down pictures of a maze: walls, start, goal, agents, trajectories and graph overlays.

Every later plot (datasets, keypoint maps, plans, pruned edges) draws on :func:`draw_maze`.
"""

from __future__ import annotations

import os

from typing import Optional, Sequence

import numpy as np

from aqm_mjx.envs import mazes


def pyplot():
    import matplotlib  # pylint: disable=import-outside-toplevel

    if matplotlib.get_backend().lower() not in ('agg', 'module://matplotlib_inline.backend_inline'):
        try:
            matplotlib.use('Agg')
        except Exception:  # pragma: no cover - a backend already chosen by the user stays
            pass
    import matplotlib.pyplot as plt  # pylint: disable=import-outside-toplevel

    return plt


def maze_extent(grid: np.ndarray) -> tuple[float, float, float, float]:
    """World (xmin, xmax, ymin, ymax) covered by ``grid [H, W]``."""
    h, w = np.asarray(grid).shape
    half = mazes.MAZE_UNIT / 2
    return (-mazes.MAZE_OFFSET - half, (w - 1) * mazes.MAZE_UNIT - mazes.MAZE_OFFSET + half,
            -mazes.MAZE_OFFSET - half, (h - 1) * mazes.MAZE_UNIT - mazes.MAZE_OFFSET + half)


def draw_maze(ax, grid, *, base_grid=None, start_xy=None, goal_xy=None, agent_xy=None,
              trajectories: Optional[Sequence[np.ndarray]] = None, nodes_xy=None, edges=None,
              pruned_edges=None, path_xy=None, goal_tol: float = 0.5, title: Optional[str] = None):
    """Draw a maze on a matplotlib axis, x to the right and y up (world coordinates).

    Args:
        grid: ``[H, W]`` occupancy grid (1 = wall).
        base_grid: the unmodified layout; cells that differ are drawn as added (red) or opened (green).
        start_xy, goal_xy: ``[2]`` or ``[N, 2]`` points.
        agent_xy: ``[N, 2]`` current agent positions.
        trajectories: list of ``[T, 2]`` x-y paths.
        nodes_xy: ``[K, 2]`` graph nodes (keypoints); edges: ``[E, 2]`` node index pairs;
        pruned_edges: ``[E', 2]`` pairs drawn dashed red; path_xy: ``[L, 2]`` a plan, drawn bold.
    """
    grid = np.asarray(grid)
    x0, x1, y0, y1 = maze_extent(grid)
    ax.set_facecolor('#f4f1ea')
    u = mazes.MAZE_UNIT
    added = False
    for i, j in zip(*np.nonzero(grid)):
        x, y = mazes.ij_to_xy((i, j))
        color, label = '#3b4252', None
        if base_grid is not None and np.asarray(base_grid)[i, j] == 0:
            color = '#bf616a'  # a wall added to the layout (closed corridor, obstacle)
            label, added = (None if added else 'closed cell'), True
        ax.add_patch(_rect(x - u / 2, y - u / 2, u, color, label=label))
    if base_grid is not None:
        for k, (i, j) in enumerate(zip(*np.nonzero((np.asarray(base_grid) == 1) & (grid == 0)))):
            x, y = mazes.ij_to_xy((i, j))
            ax.add_patch(_rect(x - u / 2, y - u / 2, u, '#a3be8c', alpha=0.5,  # an opened passage
                               label='opened cell' if k == 0 else None))
    if edges is not None and nodes_xy is not None:
        nodes = np.asarray(nodes_xy)
        for k, (a, b) in enumerate(np.asarray(edges)):
            ax.plot(nodes[[a, b], 0], nodes[[a, b], 1], color='#5e81ac', lw=0.6, alpha=0.5, zorder=2,
                    label='graph edges' if k == 0 else None)
    if pruned_edges is not None and nodes_xy is not None:
        nodes = np.asarray(nodes_xy)
        for k, (a, b) in enumerate(np.asarray(pruned_edges)):
            ax.plot(nodes[[a, b], 0], nodes[[a, b], 1], color='#bf616a', lw=2.0, ls='--', zorder=6.5,
                    label='pruned edges' if k == 0 else None)
    if nodes_xy is not None:
        nodes = np.asarray(nodes_xy)
        ax.scatter(nodes[:, 0], nodes[:, 1], s=12, color='#5e81ac', zorder=3, label='keypoints')
    for k, tr in enumerate(trajectories or ()):
        tr = np.asarray(tr)
        ax.plot(tr[:, 0], tr[:, 1], lw=1.0, alpha=0.8, zorder=5, color=f'C{k % 10}',
                label='trajectory' if k == 0 else None)
    if path_xy is not None:
        p = np.asarray(path_xy)
        ax.plot(p[:, 0], p[:, 1], color='#d08770', lw=2.5, zorder=6, marker='o', ms=4, label='plan')
    if start_xy is not None:
        s = np.atleast_2d(start_xy)
        ax.scatter(s[:, 0], s[:, 1], marker='s', s=50, color='#ebcb8b', edgecolor='k', zorder=7, label='start')
    if goal_xy is not None:
        g = np.atleast_2d(goal_xy)
        for gx, gy in g:
            ax.add_patch(_circle(gx, gy, goal_tol))
        ax.scatter(g[:, 0], g[:, 1], marker='*', s=120, color='#bf616a', edgecolor='k', zorder=7, label='goal')
    if agent_xy is not None:
        a = np.atleast_2d(agent_xy)
        ax.scatter(a[:, 0], a[:, 1], s=25, color='#b48ead', edgecolor='k', zorder=8, label='agent')
    ax.set_xlim(x0, x1)
    ax.set_ylim(y0, y1)
    ax.set_aspect('equal')
    ax.set_xlabel('x (m)')
    ax.set_ylabel('y (m)')
    if title:  # wrapped to the panel's width (about 6 characters per inch at this size), never clipped
        import textwrap  # pylint: disable=import-outside-toplevel

        ax.set_title(textwrap.fill(title, max(24, int(6.5 * ax.get_figure().get_size_inches()[0]
                                                      / max(1, len(ax.get_figure().axes))))), fontsize=10)
    return ax


def _rect(x, y, s, color, alpha=1.0, label=None):
    from matplotlib.patches import Rectangle  # pylint: disable=import-outside-toplevel

    return Rectangle((x, y), s, s, facecolor=color, edgecolor='none', alpha=alpha, zorder=1, label=label)


def _circle(x, y, r):
    from matplotlib.patches import Circle  # pylint: disable=import-outside-toplevel

    return Circle((x, y), r, facecolor='none', edgecolor='#bf616a', lw=1, ls=':', zorder=6)


def render_maze(grid, path: Optional[str] = None, *, figsize=None, dpi: int = 100, **kwargs):
    """Draw a maze (see :func:`draw_maze` for the overlays) and save it as a PNG if ``path`` is given.

    Returns:
        The matplotlib Figure (closed after saving when ``path`` is given).
    """
    plt = pyplot()
    h, w = np.asarray(grid).shape
    fig, ax = plt.subplots(figsize=figsize or (0.5 * w + 1.5, 0.5 * h + 1.0), dpi=dpi)
    draw_maze(ax, grid, **kwargs)
    handles, labels = ax.get_legend_handles_labels()
    if handles:
        ax.legend(loc='upper left', bbox_to_anchor=(1.01, 1.0), fontsize=8, frameon=False)
    return finish(plt, fig, path)


def render_panels(grid, panels: Sequence[dict], path: Optional[str] = None, *, ncols: int = 3, dpi: int = 100):
    """Several maze pictures side by side (e.g. keypoint maps for several delta values).

    Args:
        grid: ``[H, W]`` occupancy grid shared by the panels.
        panels: one dict of :func:`draw_maze` keyword arguments per panel (``title`` included; a
            ``grid`` entry replaces the shared grid in that panel, e.g. a shifted layout).
        path: PNG to write (the figure is then closed).
    """
    plt = pyplot()
    h, w = np.asarray(grid).shape
    n = len(panels)
    ncols = min(ncols, n)
    nrows = (n + ncols - 1) // ncols
    fig, axes = plt.subplots(nrows, ncols, figsize=(ncols * (0.45 * w + 1.0), nrows * (0.45 * h + 1.0)), dpi=dpi,
                             squeeze=False)
    legend = {}
    for ax, kw in zip(axes.ravel(), panels):
        kw = dict(kw)
        draw_maze(ax, kw.pop('grid', grid), **kw)
        for h, lab in zip(*ax.get_legend_handles_labels()):
            legend.setdefault(lab, h)  # one legend for every panel: each kind of mark once
    for ax in axes.ravel()[n:]:
        ax.axis('off')
    if legend:
        fig.legend(list(legend.values()), list(legend), loc='upper center', bbox_to_anchor=(0.5, 0.0),
                   ncol=min(len(legend), 8), fontsize=8, frameon=False)
    return finish(plt, fig, path)


def finish(plt, fig, path):
    """Lay out ``fig``, save it to ``path`` when given (and close it there); returns the figure. The
    saved picture is cut to everything drawn, so titles, colour-bar labels and legends outside the
    axes are never clipped."""
    fig.tight_layout()
    if path is not None:
        os.makedirs(os.path.dirname(path) or '.', exist_ok=True)
        fig.savefig(path, bbox_inches='tight', pad_inches=0.1)
        plt.close(fig)
    return fig
