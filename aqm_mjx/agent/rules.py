"""The AQM agent at test time, vectorised: every environment follows its own keypoint plan, keeps a
time budget on the edge it traverses and, on overrun, prunes that edge in its own copy of the graph
and replans (paper section 4.5). Physics, policy, planning and pruning run in one jitted program:
``lax.scan`` over control steps, ``vmap`` over environments, no host round trip per step.

Agent rules (per environment; fields of :class:`AgentConfig`):

- Start: attach the state and the goal to the graph (:func:`aqm_mjx.plan.attach`, radius ``tau``)
  and take the best plan s -> z_first -> ... -> z_last -> g (or go straight to g).
- Subgoal switching: the target keypoint z_j counts as reached when ``d(s, z_j) <= switch_radius``.
  From a reached keypoint the agent re-chooses the best last keypoint and steps to the next hop of
  its Floyd-Warshall path; at the last keypoint the target becomes the goal.
- Budget: the edge z_i -> z_j gets ``B = (1 + kappa) * w(z_i, z_j)`` control steps. On overrun the
  agent sets ``w(z_i, z_j) = inf`` in its own weight matrix, replans, and heads from where it is to
  the next hop after z_i on the new best path, as the budgeted edge z_i -> hop. The legs from the start and into the goal are
  not budgeted (they are not graph edges). ``kappa = inf`` disables pruning.
- ``use_graph=False`` is the flat policy: the target is always the goal.

The quasimetric, the encoder of states into its inputs and the low-level controller are functions
of an ``aux`` pytree passed as an argument (so parameters and tables are not compile-time constants).
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable, Optional

import jax
import jax.numpy as jnp
from flax import struct

from aqm_mjx import plan as planning
from aqm_mjx.graph import Graph

MAX_CUTS = 16  # pruned edges remembered per environment for plots (all are counted in ``pruned``)


@dataclasses.dataclass(frozen=True)
class AgentConfig:
    """Test-time rules of the agent (units are the quasimetric's: control steps)."""

    kappa: float = 0.25  # budget slack: B = (1 + kappa) * d(z_i, z_j); inf disables pruning (see README)
    switch_radius: float = 5.0  # a keypoint is reached when d(s, z) <= switch_radius
    tau: float = 20.0  # attachment radius of the start and the goal (the graph's tau)
    use_graph: bool = True  # False: the flat policy, aimed at the goal all the time
    replan_slots: int = 8  # pruning environments replanned per Floyd-Warshall pass (speed only; GPU: more)

    def __post_init__(self):
        if not (self.kappa >= 0):
            raise ValueError(f'kappa must be >= 0 (inf disables pruning); got {self.kappa}')
        if not (self.switch_radius > 0 and self.tau > 0):
            raise ValueError('switch_radius and tau must be > 0')
        if int(self.replan_slots) < 1:
            raise ValueError(f'replan_slots must be >= 1; got {self.replan_slots}')


START = -2  # AgentState.prev on the start leg (s -> z_1), whose budget is on the attachment edge


@struct.dataclass
class AgentState:
    """One environment's planner state (a leading batch axis when vmapped).

    Every leg of the path (s, z_1, ..., z_n, g) runs under a budget (1 + kappa) d(from, to):
    the start leg s -> z_1 (``prev == START``), keypoint edges z_i -> z_j (``prev == i``, ``node ==
    j``) and the goal leg z_n -> g (``prev == n``, ``node == -1``). On an overrun the leg is marked
    untraversable: a keypoint edge in ``w``, a goal attachment in ``to_g``, a start attachment by
    banning that keypoint as an entry and re-attaching from where the agent stands.
    """

    w: jax.Array  # [K, K] this environment's (pruned) weights
    dist: jax.Array  # [K, K] all-pairs distances of w
    nxt: jax.Array  # int32 [K, K] next hops of w
    to_g: jax.Array  # [K] keypoint -> goal attachment weights (pruned goal legs: inf)
    goal: jax.Array  # [L] the goal's latent (re-attaching the start leg)
    banned: jax.Array  # bool [K] keypoints whose start leg overran (not used as entries again)
    node: jax.Array  # int32 target keypoint (-1: the goal)
    prev: jax.Array  # int32 start of the budgeted leg: a keypoint, START, or -1 (no budget)
    t_edge: jax.Array  # int32 steps spent on the current leg
    budget: jax.Array  # float32 steps allowed on the current leg (inf: none)
    pruned: jax.Array  # int32 legs marked untraversable so far (edges, goal and start attachments)
    cuts: jax.Array  # int32 [MAX_CUTS, 2] the first MAX_CUTS pruned keypoint edges (i, j), -1 padded (plots)
    needs_replan: jax.Array  # bool: w or to_g changed this step


def _entry(a_dist: jax.Array, from_s: jax.Array, to_g: jax.Array, direct: jax.Array, kappa) -> tuple:
    """First target of the best plan and its start-leg budget: ``(node, prev, budget)``."""
    first = planning.plan(a_dist, from_s, to_g, direct).first
    on_graph = first >= 0
    budget = jnp.where(on_graph, (1.0 + kappa) * from_s[jnp.maximum(first, 0)], jnp.inf)
    return first.astype(jnp.int32), jnp.where(on_graph, START, -1).astype(jnp.int32), budget.astype(jnp.float32)


def agent_init(dist: Callable, graph: Graph, cfg: AgentConfig, s: jax.Array, g: jax.Array,
               use_graph: jax.Array = True, kappa: Optional[jax.Array] = None) -> AgentState:
    """Plan from latent ``s [L]`` to latent ``g [L]`` on ``graph`` (one environment); the start leg's
    budget uses ``kappa`` (default ``cfg.kappa``)."""
    kappa = cfg.kappa if kappa is None else kappa
    d_kk, nxt = planning.floyd_warshall(graph.w)
    from_s, to_g, direct = planning.attach(dist, graph.z, graph.mask, s, g, cfg.tau)
    node, prev, budget = _entry(d_kk, from_s, to_g, direct, kappa)
    node = jnp.where(use_graph, node, -1).astype(jnp.int32)
    prev = jnp.where(use_graph, prev, -1).astype(jnp.int32)
    budget = jnp.where(use_graph, budget, jnp.inf).astype(jnp.float32)
    k = graph.w.shape[0]
    return AgentState(w=graph.w, dist=d_kk, nxt=nxt.astype(jnp.int32), to_g=to_g, goal=g, banned=jnp.zeros(k, bool),
                      node=node, prev=prev, t_edge=jnp.int32(0), budget=budget, pruned=jnp.int32(0),
                      cuts=jnp.full((MAX_CUTS, 2), -1, jnp.int32), needs_replan=jnp.bool_(False))


def _next_leg(a: AgentState, k: jax.Array, kappa: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
    """From keypoint ``k``: ``(hop, prev, budget)``. The hop is the next keypoint towards the best
    last keypoint, or -1 (the goal) when ``k`` is that keypoint (a goal leg budgeted by
    ``to_g[k]``) or when no path is left (unbudgeted, ``prev`` -1)."""
    total = a.dist[k] + a.to_g
    last = jnp.argmin(total).astype(jnp.int32)
    stuck = ~jnp.isfinite(total[last])
    hop = jnp.where((k == last) | stuck, -1, a.nxt[k, last]).astype(jnp.int32)
    leg = jnp.where(hop >= 0, a.w[k, jnp.maximum(hop, 0)], a.to_g[k])
    budget = jnp.where(stuck, jnp.inf, (1.0 + kappa) * leg).astype(jnp.float32)
    return hop, jnp.where(stuck, -1, k).astype(jnp.int32), budget


def agent_step(dist: Callable, graph: Graph, cfg: AgentConfig, a: AgentState, s: jax.Array,
               kappa: jax.Array) -> AgentState:
    """Update one environment's target for the current latent ``s [L]`` (switch, time, prune).

    On a keypoint edge or goal leg overrun the target points back at the leg's start keypoint,
    unbudgeted; :func:`replan` and :func:`redirect` then choose the next hop from there. On a start
    leg overrun the agent re-attaches from ``s`` without the banned entries.
    """
    k = jnp.maximum(a.node, 0)
    reached = (a.node >= 0) & (dist(s, graph.z[k]) <= cfg.switch_radius)
    # SWITCH: from the reached keypoint, the next hop of the best path
    hop, hop_prev, hop_budget = _next_leg(a, k, kappa)
    # OVERRUN: mark the leg untraversable
    t = a.t_edge + 1
    over = ~reached & (t > a.budget)
    edge_over = over & (a.prev >= 0) & (a.node >= 0)
    goal_over = over & (a.prev >= 0) & (a.node < 0)
    start_over = over & (a.prev == START) & (a.node >= 0)
    i, j = jnp.maximum(a.prev, 0), k
    w = jnp.where(edge_over, a.w.at[i, j].set(jnp.inf), a.w)
    to_g = jnp.where(goal_over, a.to_g.at[i].set(jnp.inf), a.to_g)
    banned = a.banned | (start_over & (jnp.arange(a.banned.shape[0]) == k))
    used = jnp.sum(a.cuts[:, 0] >= 0)  # keypoint edges cut so far (pruned also counts attachments)
    slot = jnp.where(edge_over & (used < MAX_CUTS), used, MAX_CUTS)  # out of range: dropped
    cuts = a.cuts.at[slot].set(jnp.stack([i, j]).astype(jnp.int32), mode='drop')
    # re-attach from here (used on a start-leg overrun only; 2 K + 2 distances per step)
    from_s = planning.attach_start(dist, graph.z, graph.mask & ~banned, s, cfg.tau)
    direct = planning.direct_edge(dist, s, a.goal, cfg.tau)
    e_node, e_prev, e_budget = _entry(a.dist, from_s, to_g, direct, kappa)
    back = edge_over | goal_over
    node = jnp.where(reached, hop, jnp.where(back, a.prev, jnp.where(start_over, e_node, a.node)))
    prev = jnp.where(reached, hop_prev, jnp.where(back, -1, jnp.where(start_over, e_prev, a.prev)))
    budget = jnp.where(reached, hop_budget, jnp.where(back, jnp.inf, jnp.where(start_over, e_budget, a.budget)))
    return a.replace(w=w, to_g=to_g, banned=banned, cuts=cuts, node=node.astype(jnp.int32),
                     prev=prev.astype(jnp.int32), t_edge=jnp.where(reached | over, 0, t).astype(jnp.int32),
                     budget=budget.astype(jnp.float32), pruned=a.pruned + over.astype(jnp.int32), needs_replan=back)


def redirect(a: AgentState, kappa: jax.Array) -> AgentState:
    """After a prune and :func:`replan`: from the pruned leg's start z_i, take the next hop of the
    new best path straight away (a budgeted leg from z_i), rather than walking back to z_i."""
    i = jnp.maximum(a.node, 0)  # agent_step pointed node back at z_i
    hop, prev, budget = _next_leg(a, i, kappa)
    go = a.needs_replan
    return a.replace(node=jnp.where(go, hop, a.node).astype(jnp.int32),
                     prev=jnp.where(go, prev, a.prev).astype(jnp.int32),
                     budget=jnp.where(go, budget, a.budget).astype(jnp.float32), t_edge=jnp.where(go, 0, a.t_edge))


def replan(a: AgentState, slots: int = 8) -> AgentState:
    """Recompute distances and next hops of the agents of a batch that pruned an edge this step.

    The cost follows the number of pruning environments, not the batch: a ``lax.while_loop`` takes
    up to ``slots`` of them per pass (gathered by index), runs Floyd-Warshall on those and writes
    the results back; a step without overruns costs one test. Results do not depend on ``slots``.
    """
    b = a.w.shape[0]
    slots = max(1, min(int(slots), b))

    def one_pass(c):
        d, n, pending = c
        idx = jnp.nonzero(pending, size=slots, fill_value=b)[0]  # b: an empty slot (dropped on write)
        src = jnp.minimum(idx, b - 1)
        dd, nn = planning.floyd_warshall_batch(a.w[src], chunk=slots)
        d = d.at[idx].set(dd, mode='drop')
        n = n.at[idx].set(nn.astype(jnp.int32), mode='drop')
        return d, n, pending.at[idx].set(False, mode='drop')

    d, n, _ = jax.lax.while_loop(lambda c: jnp.any(c[2]), one_pass, (a.dist, a.nxt, a.needs_replan))
    return a.replace(dist=d, nxt=n)


def make_evaluate(env, encode: Callable, dist: Callable, controller: Callable, cfg: AgentConfig, steps: int,
                  record_actions: bool = False):
    """Build the jittable evaluation program.

    Args:
        env: a :class:`aqm_mjx.envs.MazeEnv`.
        encode: ``(aux, obs [D]) -> latent [L]``.
        dist: ``(aux, latent, latent) -> scalar`` time-to-reach.
        controller: ``(aux, obs [D], subgoal_obs [D], t, key) -> action [A]``.
        cfg: agent rules; steps: control steps per episode.
        record_actions: also return the clipped actions ``[T, B, A]`` (benchmarks replay them).
    Returns:
        ``run(aux, graph, keys [B, 2, 2], task_ids [B], grids [B, H, W], kappa [B], use_graph [B])
        -> dict`` with ``success [B]`` (success at the last step), ``pruned [B]``, ``xy [T, B, 2]``
        and ``node [T, B]``. ``kappa`` and ``use_graph`` per environment put ablations (no pruning
        with ``kappa = inf``, several kappas, the flat policy) in one batch; ``cfg.kappa`` and
        ``cfg.use_graph`` are the defaults of :func:`defaults`.
    """

    def run(aux: Any, graph: Graph, keys, task_ids, grids, kappa, use_graph):
        d = lambda x, y: dist(aux, x, y)  # noqa: E731
        k_reset, k_act = keys[:, 0], keys[:, 1]
        states = jax.vmap(env.reset)(k_reset, task_ids, grids)
        enc = jax.vmap(lambda o: encode(aux, o))
        agents = jax.vmap(lambda s, g, u, kp: agent_init(d, graph, cfg, s, g, u, kp))(
            enc(states.obs), enc(states.goal), use_graph, kappa)

        def body(carry, t):
            states, agents = carry
            # PLAN: switch, time and prune per environment, then replan where an edge was cut
            agents = jax.vmap(lambda a, s, kp: agent_step(d, graph, cfg, a, s, kp))(agents, enc(states.obs), kappa)
            agents = replan(agents, cfg.replan_slots)
            agents = jax.vmap(redirect)(agents, kappa)
            sub = jnp.where((agents.node >= 0)[:, None], graph.obs[jnp.maximum(agents.node, 0)], states.goal)
            # ACT and STEP
            keys_t = jax.vmap(lambda k: jax.random.fold_in(k, t))(k_act)
            actions = jnp.clip(jax.vmap(lambda o, g, k: controller(aux, o, g, t, k))(states.obs, sub, keys_t), -1.0, 1.0)
            states = jax.vmap(env.step)(states, actions)
            trace = (states.data.qpos[:, :2], agents.node) + ((actions,) if record_actions else ())
            return (states, agents), trace

        (states, agents), trace = jax.lax.scan(body, (states, agents), jnp.arange(steps))
        out = dict(success=states.success, pruned=agents.pruned, cuts=agents.cuts, xy=trace[0], node=trace[1],
                   goal_xy=states.goal_xy)
        if record_actions:
            out['actions'] = trace[2]
        return out

    return run


def split_keys(key: jax.Array, n: int) -> jax.Array:
    """``[n, 2, 2]`` keys: (reset, actions) per episode."""
    return jax.random.split(key, (n, 2))


def episode_inputs(key: jax.Array, task_ids, grids, kappa, use_graph) -> tuple:
    """``(keys, task_ids, grids, kappa, use_graph)`` for ``run`` with fixed dtypes (int32, int8,
    float32, bool), so that new tasks, seeds, walls or kappas never change the compiled signature."""
    task_ids = jnp.asarray(task_ids, jnp.int32)
    n = task_ids.shape[0]
    grids = jnp.asarray(grids, jnp.int8)
    if grids.ndim == 2:
        grids = jnp.broadcast_to(grids, (n,) + grids.shape)
    kappa = jnp.broadcast_to(jnp.asarray(kappa, jnp.float32), (n,))
    use_graph = jnp.broadcast_to(jnp.asarray(use_graph, bool), (n,))
    return split_keys(key, n), task_ids, grids, kappa, use_graph


def defaults(cfg: AgentConfig, n: int) -> tuple[jax.Array, jax.Array]:
    """Per-environment ``(kappa [n], use_graph [n])`` from the config."""
    return jnp.full((n,), cfg.kappa, jnp.float32), jnp.full((n,), cfg.use_graph, bool)


# ------------------------------------------------------------------ exact maze distance (no learning)
def maze_distance_aux(grid, sub: int = 4, speed: float = 0.12) -> dict:
    """A stand-in quasimetric: exact shortest-path length in ``grid`` (``sub x sub`` squares per
    cell) divided by ``speed`` (m per control step), i.e. a time-to-reach in control steps.
    Use with :func:`maze_encode` and :func:`maze_dist`."""
    from aqm_mjx.envs import mazes  # pylint: disable=import-outside-toplevel

    return dict(table=jnp.asarray(mazes.geodesic_table(grid, sub)) / speed,
                grid_shape=jnp.array(jnp.shape(grid), jnp.int32), sub=jnp.int32(sub))


def maze_encode(aux: dict, obs: jax.Array) -> jax.Array:
    """``obs [D]`` -> ``[1]`` float index of its square in :func:`maze_distance_aux`'s table."""
    from aqm_mjx.envs import mazes  # pylint: disable=import-outside-toplevel

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
        hold the squares' centre x-y in their first two entries, zeros elsewhere).
    """
    import numpy as np  # pylint: disable=import-outside-toplevel

    from aqm_mjx import graph as graphs  # pylint: disable=import-outside-toplevel
    from aqm_mjx import keypoints  # pylint: disable=import-outside-toplevel
    from aqm_mjx.envs import mazes  # pylint: disable=import-outside-toplevel

    aux = maze_distance_aux(grid, sub, speed)
    free = np.flatnonzero(np.isfinite(np.asarray(aux['table'])).any(1))
    cand = jnp.asarray(free, jnp.float32)[:, None]
    d = lambda x, y: maze_dist(aux, x, y)  # noqa: E731
    d_steps = delta / speed
    kp = keypoints.iwe(d, cand, jax.random.PRNGKey(seed), d_steps, max_keypoints)
    if bool(kp.overflow):
        raise ValueError(f'more than {max_keypoints} keypoints at delta {delta} m; raise max_keypoints')
    idx = free[np.asarray(kp.index)[np.asarray(kp.mask)]]
    k = len(idx)
    z = jnp.asarray(idx, jnp.float32)[:, None]
    mask = jnp.ones(k, bool)
    w = graphs.build_graph(d, z, mask, d_steps)
    obs = np.zeros((k, obs_size), np.float32)
    obs[:, :2] = mazes.subcell_to_xy(idx, np.shape(grid), sub)
    return aux, Graph(z=z, obs=jnp.asarray(obs), mask=mask, w=w)
