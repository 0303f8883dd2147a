"""GAS's test-time rule (Baek et al., 2025, "Graph-Assisted Stitching"), batched: on GAS's graph
(:mod:`aqm_mjx.mapping.gas_nodes`), every control step

1. attaches the goal: nodes within ``max(H, 1.2 min_n ||n - phi(g)||)`` of ``phi(g)`` join it, weighted
   by that distance (once per episode), so ``to_goal[n]`` is node n's shortest-path distance to the goal;
2. chooses the path's start: among the nodes within ``H`` of ``phi(s)``, the one minimising
   ``||phi(s) - n|| + to_goal[n]``; when none is that near, the last one stays;
3. takes the subgoal: the furthest node of that shortest path (the goal included) within ``H`` of
   ``phi(s)``, else the path's start; once the path is the start and the goal alone (2 nodes), the
   goal for the rest of the episode;
4. acts: the skill policy toward ``(target - phi(s)) / (||target - phi(s)|| + 1e-10)``.

As GAS's ``evaluate_with_graph`` with the shortest paths computed per episode (its strategy (1),
which its authors found equal to caching them per task). There is no budget and no pruning: GAS's
graph is fixed. A node lies on the start's shortest path when ``D[start, n] + to_goal[n]`` equals
``to_goal[start]`` up to a relative ``1e-4`` (Floyd-Warshall distances, so nearly tied routes count
as one); the path's order is ``D[start, n]``.
"""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp
from flax import struct

from aqm_mjx.agent import plan as planning
from aqm_mjx.interface import Decide
from aqm_mjx.mapping.graph import Graph

PATH_TOL = 1e-4  # relative slack of "on the shortest path"


@struct.dataclass
class GASState:
    """The batch's GAS agents: ``[B, ...]`` fields, and the graph's all-pairs distances (shared).

    ``node`` is the target node (-1: the goal), as the AQM agent's, for traces and plots."""

    dist: jax.Array  # [K, K] all-pairs shortest-path distances of the graph (one for the batch)
    to_goal: jax.Array  # [B, K] each node's shortest-path distance to the episode's goal (inf: none)
    goal: jax.Array  # [B, L] phi(goal)
    start: jax.Array  # int32 [B] the path's start node
    final: jax.Array  # bool [B] heading for the goal for the rest of the episode
    node: jax.Array  # int32 [B] the current target node (-1: the goal)


def goal_attachment(centers: jax.Array, mask: jax.Array, phi_g: jax.Array, horizon: float) -> jax.Array:
    """``[K]``: ``||n - phi(g)||`` for the nodes within ``max(H, 1.2 min ||n - phi(g)||)`` (strictly), else inf."""
    d = jnp.where(mask, jnp.linalg.norm(centers - phi_g, axis=-1), jnp.inf)
    return jnp.where(d < jnp.maximum(horizon, 1.2 * jnp.min(d)), d, jnp.inf)


def distances_to_goal(dist: jax.Array, attach: jax.Array) -> jax.Array:
    """``[K]``: ``min_m dist[n, m] + attach[m]``, each node's shortest-path distance to the goal."""
    return jnp.min(dist + attach[None, :], axis=1)


def on_path(dist: jax.Array, to_goal: jax.Array, start: jax.Array, mask: jax.Array) -> jax.Array:
    """bool ``[K]``: the nodes of a shortest path from ``start`` to the goal (``start`` included)."""
    total = to_goal[start]
    via = dist[start] + to_goal
    return mask & jnp.isfinite(via) & (via <= total + PATH_TOL * (1.0 + total))


def target(dist: jax.Array, to_goal: jax.Array, centers: jax.Array, mask: jax.Array, phi_s: jax.Array,
           phi_g: jax.Array, start: jax.Array, final: jax.Array, horizon: float) -> tuple:
    """One agent's step 2-3: ``(start, final, node, target latent [L])`` (``node`` -1: the goal)."""
    d_s = jnp.where(mask, jnp.linalg.norm(centers - phi_s, axis=-1), jnp.inf)
    near = (d_s <= horizon) & jnp.isfinite(to_goal)
    start = jnp.where(jnp.any(near), jnp.argmin(jnp.where(near, d_s + to_goal, jnp.inf)), start).astype(jnp.int32)
    path = on_path(dist, to_goal, start, mask)
    final = final | (jnp.sum(path) <= 1)  # the path is [start, goal]
    within = path & (d_s <= horizon)
    furthest = jnp.argmax(jnp.where(within, dist[start], -jnp.inf)).astype(jnp.int32)
    node = jnp.where(jnp.any(within), furthest, start)
    to_g = final | (jnp.linalg.norm(phi_g - phi_s) <= horizon)  # the goal is the path's furthest node
    node = jnp.where(to_g, -1, node).astype(jnp.int32)
    return start, final, node, jnp.where(to_g, phi_g, centers[jnp.maximum(node, 0)])


def make_decide(encode: Callable, act: Callable, horizon: float):
    """GAS's :class:`~aqm_mjx.interface.Decide` half of a control step.

    Args:
        encode: ``(aux, obs [D]) -> phi [L]``.
        act: ``(aux, obs [D], phi_obs [L], target [L]) -> action [A]`` (the skill policy's mean toward
            the target, :attr:`aqm_mjx.interface.Agent.skill`).
        horizon: ``H`` (GAS's ``way_steps``): the start search and subgoal radius, in TDR units.
    Returns:
        ``(init, act)`` as :func:`aqm_mjx.agent.rollout.make_decide`'s; an episode row with
        ``use_graph`` False heads for the goal from the start (GAS's policy, flat).
    """
    def init(aux, graph: Graph, obs, goal, inputs):
        enc = jax.vmap(lambda o: encode(aux, o))
        dist = planning.shortest_distances(graph.w)
        phi_o, phi_g = enc(obs), enc(goal)
        attach = jax.vmap(lambda g: goal_attachment(graph.z, graph.mask, g, horizon))(phi_g)
        to_goal = jax.lax.map(lambda a: distances_to_goal(dist, a), attach, batch_size=8)
        start = jnp.argmin(jnp.where(graph.mask[None], jnp.linalg.norm(graph.z[None] - phi_o[:, None], axis=-1),
                                     jnp.inf), axis=1).astype(jnp.int32)
        return GASState(dist=dist, to_goal=to_goal, goal=phi_g, start=start, final=~inputs.use_graph,
                        node=jnp.full(start.shape, -1, jnp.int32))

    def step(aux, graph: Graph, agents: GASState, obs, goal, done, t, inputs):
        del goal, done, t
        phi_s = jax.vmap(lambda o: encode(aux, o))(obs)
        start, final, node, z = jax.vmap(
            lambda tg, ps, pg, st, fi: target(agents.dist, tg, graph.z, graph.mask, ps, pg, st, fi, horizon))(
            agents.to_goal, phi_s, agents.goal, agents.start, agents.final)
        actions = jax.vmap(lambda o, s, k: act(aux, o, s, k))(obs, phi_s, z)
        return jnp.clip(actions, -1.0, 1.0), agents.replace(start=start, final=final, node=node)

    return Decide(init, step)
