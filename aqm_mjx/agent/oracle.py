"""An agent without learning, for checking the planner, the pruning and the protocol: the exact BFS
maze distance as the quasimetric, IWE keypoints under it, and the scripted expert steered along the
maze's BFS as the controller.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from aqm_mjx import presets
from aqm_mjx.data import expert
from aqm_mjx.envs import mazes
from aqm_mjx.interface import Agent
from aqm_mjx.mapping.graph import Graph, build_graph, components, edge_list
from aqm_mjx.mapping.keypoints import iwe


def maze_distance_aux(grid, sub: int = 4, speed: float = 0.12) -> dict:
    """A stand-in quasimetric: exact shortest-path length in ``grid`` (``sub x sub`` squares per
    cell) divided by ``speed`` (m per control step), i.e. a time-to-reach in control steps.
    Use with :func:`maze_encode` and :func:`maze_dist`."""
    return dict(table=jnp.asarray(mazes.geodesic_table(grid, sub)) / speed,
                grid_shape=jnp.array(jnp.shape(grid), jnp.int32), sub=jnp.int32(sub))


def maze_encode(aux: dict, obs: jax.Array) -> jax.Array:
    """``obs [D]`` -> ``[1]`` float index of its square in :func:`maze_distance_aux`'s table."""
    return mazes.xy_to_subcell(obs[:2], aux['grid_shape'], aux['sub'], xp=jnp).astype(jnp.float32)[None]


def maze_dist(aux: dict, x: jax.Array, y: jax.Array) -> jax.Array:
    return aux['table'][x[0].astype(jnp.int32), y[0].astype(jnp.int32)]


def maze_graph(grid, delta: float = 4.0, speed: float = 0.12, sub: int = 4, max_keypoints: int = 128,
               obs_size: int = 29, seed: int = 0) -> tuple[dict, Graph]:
    """IWE keypoints and their tau = 2 delta graph under the exact maze distance of ``grid``.

    Args:
        delta: repel radius in metres (converted to steps with ``speed``).
    Returns:
        (aux for :func:`maze_encode` / :func:`maze_dist`, :class:`Graph` whose keypoint observations
        hold the squares' centre x-y in their first two entries, zeros elsewhere; its ``tau`` is
        ``2 delta``, in steps).
    """
    aux = maze_distance_aux(grid, sub, speed)
    free = np.flatnonzero(np.isfinite(np.asarray(aux['table'])).any(1))
    cand = jnp.asarray(free, jnp.float32)[:, None]
    d = lambda x, y: maze_dist(aux, x, y)  # noqa: E731
    d_steps = delta / speed
    kp = iwe(d, cand, jax.random.PRNGKey(seed), d_steps, max_keypoints)
    if bool(kp.overflow):
        raise ValueError(f'more than {max_keypoints} keypoints at delta {delta} m; raise max_keypoints')
    idx = free[np.asarray(kp.index)[np.asarray(kp.mask)]]
    k = len(idx)
    z = jnp.asarray(idx, jnp.float32)[:, None]
    mask = jnp.ones(k, bool)
    w = build_graph(d, z, mask, d_steps)
    obs = np.zeros((k, obs_size), np.float32)
    obs[:, :2] = mazes.subcell_to_xy(idx, np.shape(grid), sub)
    return aux, Graph(z=z, obs=jnp.asarray(obs), mask=mask, w=w, tau=jnp.float32(2.0 * d_steps))


def oracle_agent(env, grid=None, delta: float = 4.0, speed: float = 0.12) -> tuple[Agent, Graph, dict]:
    """An agent without learning, for checking the planner, the pruning and the protocol.

    The quasimetric is the exact BFS maze distance of ``grid`` (default: the maze's layout) as a
    time-to-reach at ``speed`` m per control step, the keypoints are IWE's at ``delta`` m
    (:func:`maze_graph`), and the controller steers along ``grid``'s BFS toward the
    current target: the scripted trot for the ant, a unit displacement for the point. On any other
    layout both the map and the controller are out of date, as a learned agent's would be.

    Returns:
        (agent, graph (its ``tau`` is 2 ``delta``, in steps), :class:`~aqm_mjx.agent.rules.AgentConfig`
        keywords that match it: ``switch_radius`` 1.5 m in steps and the paper preset's ``kappa``
        (0.25): its distance is exact, so the slack can be small).
    """
    grid = np.asarray(env.layout if grid is None else grid)
    aux, graph = maze_graph(grid, delta=delta, speed=speed, obs_size=env.obs_size)
    aux['bfs'] = jnp.asarray(expert.bfs_next_cell(grid))

    def controller(aux, o, g, t, key):
        del key
        cmd = expert.waypoint_command(o[:2], g[:2], aux['bfs'], grid.shape)
        if env.agent == 'ant':
            return expert.gait_action(o[:15], o[15:], cmd, t)
        return cmd / (jnp.linalg.norm(cmd) + 1e-6)

    agent = Agent(maze_encode, maze_dist, controller, aux)
    return agent, graph, dict(switch_radius=1.5 / speed, kappa=presets.RUN['paper']['agent']['kappa'])


def keypoint_map_panels(maze: str, deltas, n_candidates: int = 20000, sub: int = 4, seed: int = 0):
    """IWE keypoints and tau = 2 delta edges with the exact maze distance as the quasimetric, one
    panel per delta (the paper's Figures 11-13, with a stand-in for a trained quasimetric)."""
    grid = mazes.layout(maze)
    table = jnp.asarray(mazes.geodesic_table(grid, sub))
    rng = np.random.default_rng(seed)
    free = np.argwhere(grid == 0)
    xy = mazes.ij_to_xy(free[rng.integers(len(free), size=n_candidates)]) + rng.uniform(-1.9, 1.9, (n_candidates, 2))
    cand = jnp.asarray(mazes.xy_to_subcell(xy, grid.shape, sub))[:, None]

    def lookup(table):
        return lambda x, y: table[x[0], y[0]]

    # The table and candidates are arguments: captured as constants XLA would constant-fold them.
    select = jax.jit(lambda table, cand, key, delta: iwe(lookup(table), cand, key, delta, 512))
    dist = lookup(table)
    panels = []
    for delta in deltas:
        kp = select(table, cand, jax.random.PRNGKey(seed), float(delta))
        idx = np.asarray(kp.index)[np.asarray(kp.mask)]
        w = build_graph(dist, cand[jnp.asarray(idx)], jnp.ones(len(idx), bool), float(delta))
        _, ncomp = components(w, jnp.ones(len(idx), bool))
        panels.append(dict(nodes_xy=xy[idx], edges=edge_list(w),
                           title=f'delta {delta:g} m: {len(idx)} keypoints, {int(ncomp)} component(s)'))
    return grid, panels
