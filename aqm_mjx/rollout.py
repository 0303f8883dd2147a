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
from typing import Any, Callable

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


@struct.dataclass
class AgentState:
    """One environment's planner state (a leading batch axis when vmapped)."""

    w: jax.Array  # [K, K] this environment's (pruned) weights
    dist: jax.Array  # [K, K] all-pairs distances of w
    nxt: jax.Array  # int32 [K, K] next hops of w
    to_g: jax.Array  # [K] keypoint -> goal attachment weights
    node: jax.Array  # int32 target keypoint (-1: the goal)
    prev: jax.Array  # int32 keypoint the budgeted edge started at (-1: no budget running)
    t_edge: jax.Array  # int32 steps spent on the current leg
    budget: jax.Array  # float32 steps allowed on the current edge (inf: none)
    pruned: jax.Array  # int32 edges pruned so far
    cuts: jax.Array  # int32 [MAX_CUTS, 2] the first MAX_CUTS pruned edges (i, j), -1 padded (for plots)
    needs_replan: jax.Array  # bool: w changed this step


def agent_init(dist: Callable, graph: Graph, cfg: AgentConfig, s: jax.Array, g: jax.Array,
               use_graph: jax.Array = True) -> AgentState:
    """Plan from latent ``s [L]`` to latent ``g [L]`` on ``graph`` (one environment)."""
    d_kk, nxt = planning.floyd_warshall(graph.w)
    from_s, to_g, direct = planning.attach(dist, graph.z, graph.mask, s, g, cfg.tau)
    p = planning.plan(d_kk, from_s, to_g, direct)
    node = jnp.where(use_graph, p.first, -1).astype(jnp.int32)
    return AgentState(w=graph.w, dist=d_kk, nxt=nxt.astype(jnp.int32), to_g=to_g, node=node,
                      prev=jnp.int32(-1), t_edge=jnp.int32(0), budget=jnp.float32(jnp.inf),
                      pruned=jnp.int32(0), cuts=jnp.full((MAX_CUTS, 2), -1, jnp.int32), needs_replan=jnp.bool_(False))


def _next_leg(a: AgentState, k: jax.Array, kappa: jax.Array) -> tuple[jax.Array, jax.Array]:
    """From keypoint ``k``: the next hop towards the best last keypoint (-1: aim at the goal, when
    ``k`` is that keypoint or no path is left) and the budget of the edge ``k -> hop``."""
    total = a.dist[k] + a.to_g
    last = jnp.argmin(total).astype(jnp.int32)
    hop = jnp.where((k == last) | ~jnp.isfinite(total[last]), -1, a.nxt[k, last])
    budget = jnp.where(hop >= 0, (1.0 + kappa) * a.w[k, jnp.maximum(hop, 0)], jnp.inf)
    return hop, budget


def agent_step(dist: Callable, graph: Graph, cfg: AgentConfig, a: AgentState, s: jax.Array,
               kappa: jax.Array) -> AgentState:
    """Update one environment's target for the current latent ``s [L]`` (switch, time, prune).

    On an overrun the target points back at the pruned edge's start, unbudgeted; :func:`replan`
    and :func:`redirect` then choose the next hop from there.
    """
    k = jnp.maximum(a.node, 0)
    reached = (a.node >= 0) & (dist(s, graph.z[k]) <= cfg.switch_radius)
    # SWITCH: from the reached keypoint, the next hop of the best path
    hop, budget = _next_leg(a, k, kappa)
    # OVERRUN: prune the edge
    t = a.t_edge + 1
    overrun = ~reached & (a.prev >= 0) & (a.node >= 0) & (t > a.budget)
    i, j = jnp.maximum(a.prev, 0), k
    w = jnp.where(overrun, a.w.at[i, j].set(jnp.inf), a.w)
    slot = jnp.where(overrun & (a.pruned < MAX_CUTS), a.pruned, MAX_CUTS)  # out of range: dropped
    cuts = a.cuts.at[slot].set(jnp.stack([i, j]).astype(jnp.int32), mode='drop')
    node = jnp.where(reached, hop, jnp.where(overrun, a.prev, a.node)).astype(jnp.int32)
    prev = jnp.where(reached, jnp.where(hop >= 0, k, -1), jnp.where(overrun, -1, a.prev)).astype(jnp.int32)
    return a.replace(w=w, cuts=cuts, node=node, prev=prev, t_edge=jnp.where(reached | overrun, 0, t).astype(jnp.int32),
                     budget=jnp.where(reached, budget, jnp.where(overrun, jnp.inf, a.budget)).astype(jnp.float32),
                     pruned=a.pruned + overrun.astype(jnp.int32), needs_replan=overrun)


def redirect(a: AgentState, kappa: jax.Array) -> AgentState:
    """After a prune and :func:`replan`: from the pruned edge's start z_i, take the next hop of the
    new best path straight away (a budgeted edge z_i -> hop), rather than walking back to z_i."""
    i = jnp.maximum(a.node, 0)  # agent_step pointed node back at z_i
    hop, budget = _next_leg(a, i, kappa)
    go = a.needs_replan
    return a.replace(node=jnp.where(go, hop, a.node).astype(jnp.int32),
                     prev=jnp.where(go, jnp.where(hop >= 0, i, -1), a.prev).astype(jnp.int32),
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
        agents = jax.vmap(lambda s, g, u: agent_init(d, graph, cfg, s, g, u))(enc(states.obs), enc(states.goal),
                                                                               use_graph)

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
