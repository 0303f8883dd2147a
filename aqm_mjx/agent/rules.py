"""The AQM agent's rules at test time, for one environment (``vmap`` them over a batch): plan on the
keypoint graph, switch subgoals, keep a time budget on every leg and, on overrun, mark the leg
untraversable in the environment's own copy of the graph and replan (paper section 4.5).

- Start: attach the state and the goal to the graph (:func:`aqm_mjx.agent.plan.attach`, radius
  ``graph.tau``) and take the best plan s -> z_first -> ... -> z_last -> g (or go straight to g).
- Subgoal switching: the target keypoint z_j counts as reached when ``d(s, z_j) <= switch_radius``.
  From a reached keypoint the agent re-chooses the best last keypoint and steps to the next hop of
  its Floyd-Warshall path; at the last keypoint the target becomes the goal.
- Budgets: every leg of the path (s, z_1, ..., z_n, g) gets ``B = (1 + kappa) d(from, to)`` control
  steps. A keypoint edge that overruns is set to ``inf`` in the environment's weights, a goal leg
  cuts that goal attachment, a start leg bans that entry keypoint and re-attaches from where the
  agent stands. After a prune the agent replans and heads from where it is to the next hop after the
  pruned leg's start. ``kappa = inf`` disables pruning.
- ``use_graph=False`` is the flat policy: the target is always the goal.
"""

from __future__ import annotations

import dataclasses
from typing import Callable

import jax
import jax.numpy as jnp
from flax import struct

from aqm_mjx import config as cfg_lib
from aqm_mjx.agent import plan as planning
from aqm_mjx.config import option
from aqm_mjx.mapping.graph import Graph

MAX_CUTS = 16  # pruned edges remembered per environment for plots (all are counted in ``pruned``)


@dataclasses.dataclass(frozen=True)
class AgentConfig:
    """Test-time rules of the agent (units are the quasimetric's: control steps). The attachment
    radius of the start and the goal is the graph's own ``tau``."""

    kappa: float = option(1.0, 'budget slack: B = (1 + kappa) d(z_i, z_j); inf disables pruning. 1, not the '
                          "paper's small slack: at the cpu preset the learned policy walks slower than the data's "
                          'expert that d measures (RESULTS.md, kappa sweep)')
    switch_radius: float = option(10.0, 'a keypoint counts as reached when d(s, z) <= switch_radius (RESULTS.md)')
    replan_slots: int = option(0, 'pruning environments replanned per Floyd-Warshall pass (speed only); '
                               '0: 8 on a CPU, 256 elsewhere')

    def __post_init__(self):
        cfg_lib.check_types(self)
        if not (self.kappa >= 0):
            raise ValueError(f'AgentConfig.kappa must be >= 0 (inf disables pruning); got {self.kappa}')
        if not self.switch_radius > 0:
            raise ValueError(f'AgentConfig.switch_radius must be > 0; got {self.switch_radius}')
        if isinstance(self.replan_slots, bool) or not isinstance(self.replan_slots, int) or self.replan_slots < 0:
            raise ValueError(f'AgentConfig.replan_slots must be an integer >= 0 (0: by device); got {self.replan_slots}')

    @property
    def slots(self) -> int:
        """Replan slots in use: ``replan_slots``, or 8 on a CPU and 256 on an accelerator."""
        return self.replan_slots or (8 if jax.default_backend() == 'cpu' else 256)


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


def agent_init(dist: Callable, graph: Graph, s: jax.Array, g: jax.Array, kappa: jax.Array,
               use_graph: jax.Array = True) -> AgentState:
    """Plan from latent ``s [L]`` to latent ``g [L]`` on ``graph`` (one environment); the start leg's
    budget uses ``kappa`` (per environment: an ablation is a row of the batch)."""
    d_kk, nxt = planning.floyd_warshall(graph.w)
    from_s, to_g, direct = planning.attach(dist, graph.z, graph.mask, s, g, graph.tau)
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
    from_s = planning.attach_start(dist, graph.z, graph.mask & ~banned, s, graph.tau)
    direct = planning.direct_edge(dist, s, a.goal, graph.tau)
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


