"""A TTGS-style test-time rule (arXiv 2510.07257) on a dense map of random dataset states
(:mod:`aqm_mjx.mapping.ttgs_nodes`), batched and jittable, around any method's distance ``d``:

1. once per episode, the node nearest the start (``argmin_n d(s, n)``) and the node nearest the
   goal (``argmin_n d(n, g)``), and Dijkstra's shortest path between them on the map's weights;
2. every control step: the goal itself when ``d(s, g) <= T``; else the farthest path point ahead of
   the closest one with ``d(s, p) < T``; else the point after the closest one (the goal once that
   is the path's end and the end is farther than ``T`` from the goal);
3. the method's own controller toward that state.

The closest point only moves forward, as TTGS's; it is searched among the ``window`` points from
the last one on (TTGS searches the whole path every step: a path of more than ``window`` points
ahead of the agent is seen ``window`` points at a time). No budgets, no pruning, no replanning:
TTGS searches once. A path longer than ``max_path`` nodes keeps its last ``max_path`` (the goal's end).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct

from aqm_mjx.interface import Agent, Decide
from aqm_mjx.mapping.graph import Graph


@struct.dataclass
class TTGSState:
    """The batch's TTGS agents, ``[B, ...]`` fields. ``node`` is the subgoal's node (-1: the goal), as
    the AQM agent's, for traces and plots."""

    path: jax.Array  # int32 [B, P] node indices from the start's node to the goal's, -1 padded
    length: jax.Array  # int32 [B] the path's nodes (0: no path, head for the goal)
    closest: jax.Array  # int32 [B] the closest path point so far (moves forward only)
    end_to_goal: jax.Array  # float32 [B] d(last path point, goal)
    goal: jax.Array  # [B, L] the goal's latent
    node: jax.Array  # int32 [B]


def dijkstra(w: jax.Array, mask: jax.Array, source: jax.Array, target: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Dense Dijkstra from ``source`` on weights ``w [K, K]`` (``inf``: no edge), over ``mask [K]``
    nodes, stopping once ``target`` is settled: ``(dist [K], prev [K])`` (``prev`` -1 for none)."""
    k = w.shape[0]
    dist = jnp.full((k,), jnp.inf).at[source].set(0.0)
    prev = jnp.full((k,), -1, jnp.int32)
    done = ~mask

    def cond(c):
        dist, _, done, i = c
        return (i < k) & ~done[target] & jnp.isfinite(jnp.min(jnp.where(done, jnp.inf, dist)))

    def body(c):
        dist, prev, done, i = c
        u = jnp.argmin(jnp.where(done, jnp.inf, dist))
        done = done.at[u].set(True)
        alt = dist[u] + w[u]
        better = (alt < dist) & ~done
        return jnp.where(better, alt, dist), jnp.where(better, u.astype(jnp.int32), prev), done, i + 1

    dist, prev, _, _ = jax.lax.while_loop(cond, body, (dist, prev, done, jnp.int32(0)))
    return dist, prev


def path_nodes(prev: jax.Array, source: jax.Array, target: jax.Array, reached: jax.Array,
               max_path: int) -> tuple[jax.Array, jax.Array]:
    """The path ``source -> target`` read back from Dijkstra's ``prev``: ``(path [max_path] int32, -1
    padded, length)``; length 0 when ``reached`` is False; the last ``max_path`` nodes when longer."""
    def back(c, _):
        node, going = c
        out = jnp.where(going, node, -1)
        going = going & (node != source)
        return (jnp.where(going, prev[node], node), going), out

    _, rev = jax.lax.scan(back, (target, reached), None, length=max_path)
    length = jnp.sum(rev >= 0).astype(jnp.int32)
    i = jnp.arange(max_path)
    path = jnp.where(i < length, rev[jnp.clip(length - 1 - i, 0, max_path - 1)], -1)
    return path, length


def subgoal(d_goal, d_window, idx, length, closest, end_to_goal, path, horizon: float):
    """One agent's choice (step 2): ``(closest, node)`` with ``node`` -1 for the goal.

    ``d_goal``: d(s, g); ``d_window [W]``: d(s, p) of the path points ``idx [W]`` (``inf`` past the
    path's end); ``closest`` the previous closest point."""
    valid = idx < length
    d_window = jnp.where(valid, d_window, jnp.inf)
    closest = jnp.where(jnp.any(valid), idx[jnp.argmin(d_window)], closest)
    ahead = valid & (idx > closest) & (d_window < horizon)
    far = jnp.max(jnp.where(ahead, idx, -1))
    nxt = jnp.minimum(closest + 1, length - 1)
    to_goal_after = (nxt == length - 1) & (end_to_goal > horizon)
    pick = jnp.where(far >= 0, far, jnp.where(to_goal_after, -1, nxt))
    node = jnp.where((d_goal <= horizon) | (length == 0) | (pick < 0), -1, path[jnp.clip(pick, 0, path.shape[0] - 1)])
    return closest, node


def make_decide(agent: Agent, horizon: float, window: int = 32, max_path: int = 256) -> Decide:
    """The TTGS rule's :class:`~aqm_mjx.interface.Decide` for ``agent`` (its ``encode``, ``dist`` and
    ``controller``); ``horizon`` is ``T`` (steps), ``window`` the path points searched a step. An
    episode row with ``use_graph`` False heads for the goal (the method flat)."""
    encode, dist, controller = agent.encode, agent.dist, agent.controller

    def init(aux, graph: Graph, obs, goal, inputs):
        enc = jax.vmap(lambda o: encode(aux, o))
        zs, zg = enc(obs), enc(goal)
        p = min(int(max_path), graph.mask.shape[0])

        def one(z, g, use):
            to_nodes = jnp.where(graph.mask, jax.vmap(lambda n: dist(aux, z, n))(graph.z), jnp.inf)
            from_nodes = jnp.where(graph.mask, jax.vmap(lambda n: dist(aux, n, g))(graph.z), jnp.inf)
            src, dst = jnp.argmin(to_nodes), jnp.argmin(from_nodes)
            dd, prev = dijkstra(graph.w, graph.mask, src, dst)
            path, length = path_nodes(prev, src, dst, jnp.isfinite(dd[dst]) & use, p)
            end = graph.z[jnp.maximum(path[jnp.maximum(length - 1, 0)], 0)]
            return path, length, dist(aux, end, g)

        # 2 K distances an environment: a few environments at a time, so memory does not grow with B x K
        # (a network distance at K = 4,000 and B = 100 took over 20 GB vmapped)
        path, length, end_to_goal = jax.lax.map(lambda x: one(*x), (zs, zg, inputs.use_graph), batch_size=8)
        b = obs.shape[0]
        return TTGSState(path=path, length=length, closest=jnp.zeros((b,), jnp.int32), end_to_goal=end_to_goal,
                         goal=zg, node=jnp.full((b,), -1, jnp.int32))

    def act(aux, graph: Graph, agents: TTGSState, obs, goal, done, t, inputs):
        w = min(int(window), agents.path.shape[1])
        zs = jax.vmap(lambda o: encode(aux, o))(obs)

        def one(z, zg, path, length, closest, end):
            idx = closest + jnp.arange(w)
            pts = graph.z[jnp.maximum(path[jnp.clip(idx, 0, path.shape[0] - 1)], 0)]
            d_window = jax.vmap(lambda q: dist(aux, z, q))(pts)
            return subgoal(dist(aux, z, zg), d_window, idx, length, closest, end, path, horizon)

        closest, node = jax.vmap(one)(zs, agents.goal, agents.path, agents.length, agents.closest, agents.end_to_goal)
        closest = jnp.where(done, agents.closest, closest)
        node = jnp.where(done, agents.node, node)
        sub = jnp.where((node >= 0)[:, None], graph.obs[jnp.maximum(node, 0)], goal)
        keys_t = jax.vmap(lambda k: jax.random.fold_in(k, t))(inputs.keys[:, 1])
        actions = jax.vmap(lambda o, g, k: controller(aux, o, g, t, k))(obs, sub, keys_t)
        return jnp.clip(actions, -1.0, 1.0), agents.replace(closest=closest, node=node)

    return Decide(init, act)
