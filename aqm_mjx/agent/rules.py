"""The AQM agent's rules at test time, for one environment (``vmap`` them over a batch): plan on the
keypoint graph, switch subgoals, keep a time budget on every leg and, on overrun, mark the leg
untraversable in the environment's own copy of the graph and replan (paper section 4.5).

- Start: attach the state and the goal to the graph (:func:`aqm_mjx.agent.plan.attach`, radius
  ``graph.tau``) and take the best plan s -> z_first -> ... -> z_last -> g (or go straight to g).
- Subgoal switching: the target keypoint z_j counts as reached when ``d(s, z_j) <= switch_radius``.
  From a reached keypoint the agent re-chooses the best last keypoint and steps to the next hop of
  its Floyd-Warshall path; at the last keypoint the target becomes the goal.
- Budgets: every leg of the path (s, z_1, ..., z_n, g) gets ``B = (1 + kappa) d(from, to)`` control
  steps (the fixed rule, ``patience = 0``), or, with ``patience > 0``, the stall rule: a leg
  overruns after ``patience`` consecutive steps in which d(s, target) did not fall ``progress``
  below its best on that leg, however long the leg takes while it makes progress. With
  ``edges_only`` (per environment) only keypoint-to-keypoint edges are budgeted, as section 4.5
  states it: the start leg s -> z_1 and the goal leg z_n -> g run unbudgeted. The paper's rule is
  the fixed rule with ``edges_only`` and no parallel cuts (``protocol`` row ``paper=X``). A keypoint edge
  that overruns is set to ``inf`` in the environment's weights, a goal leg cuts that goal
  attachment, a start leg bans that entry keypoint and re-attaches from where the agent stands.
  After a prune the agent replans and heads from where it is to the next hop after the pruned leg's
  start. ``kappa = inf`` disables pruning under either rule.
- Parallel cuts (``cut_slack`` > 0, per environment; 0 is the paper's single cut): a keypoint edge
  z_i -> z_j that overruns also takes with it every edge z_a -> z_b that starts within ``cut_slack
  * w(i, j)`` of z_i and ends within that of z_j (map distances, either way). The overrun says z_j's
  side cannot be reached from z_i's in the leg's time: edges between the same two neighbourhoods
  cross the same blockage. Without them a closed corridor crossed by k such edges costs k overruns,
  one budget each (RESULTS.md, section 9).
- Leg log: every leg that ends at its keypoint is recorded as (d(from, to), steps taken, longest
  stall, kind) in ``legs`` (kind :data:`LEG_START`, :data:`LEG_EDGE` or :data:`LEG_GOAL`) (the first :data:`MAX_LEGS`; ``n_legs`` counts all), the measurement that
  calibrates either rule (:mod:`aqm_mjx.evaluation.calibration`).
- ``use_graph=False`` is the flat policy: the target is always the goal.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Callable

import jax
import jax.numpy as jnp
from flax import struct

from aqm_mjx import config as cfg_lib
from aqm_mjx import presets
from aqm_mjx.agent import plan as planning
from aqm_mjx.config import option
from aqm_mjx.mapping.graph import Graph

MAX_CUTS = 16  # pruned edges remembered per environment for plots (all are counted in ``pruned``)
MAX_LEGS = 32  # completed legs logged per environment (all are counted in ``n_legs``)
LEG_START, LEG_EDGE, LEG_GOAL = 0, 1, 2  # the kinds of a leg (4th column of the leg log)
LEG_FIELDS = 4  # (d(from, to), steps, longest stall, kind)


@dataclasses.dataclass(frozen=True)
class AgentConfig:
    """Test-time rules of the agent (units are the quasimetric's: control steps). The attachment
    radius of the start and the goal is the graph's own ``tau``."""

    kappa: float = option(presets.default('agent', 'kappa'),
                          'budget slack: B = (1 + kappa) d(z_i, z_j); inf disables pruning. 1 at the cpu preset, not '
                          "the paper's small slack: the learned policy walks slower than the data's expert that d "
                          'measures (RESULTS.md, kappa sweep)')
    switch_radius: float = option(presets.default('agent', 'switch_radius'),
                                  'a keypoint counts as reached when d(s, z) <= switch_radius (RESULTS.md)')
    patience: float = option(0.0, "0: the paper's budget (1 + kappa) d; > 0: the stall rule, a leg is cut after this "
                             'many consecutive steps without progress in d(s, target)')
    progress: float = option(1.0, 'stall rule: a step makes progress when d(s, target) falls this far below its best '
                             'on the leg (units of d: control steps)')
    cut_slack: float = option(0.0, "the AQM row's parallel cuts. 0: an overrun cuts its one edge (the paper); in "
                              '(0, 1): it also cuts the edges parallel to it, those whose ends lie within cut_slack '
                              'times the leg of its ends (RESULTS.md, section 9)')
    cut_into: bool = option(False, "with parallel cuts: an overrun of z_i -> z_j cuts every edge into z_j's "
                            "neighbourhood, from anywhere, not only from z_i's (its keypoints are taken as unreachable)")
    keep_route: bool = option(False, 'an overrun whose cut would leave no route to the goal is not cut: the leg '
                              'starts again with a fresh budget (the edge may be traversable after all, and it is the '
                              'only way left)')
    replan_slots: int = option(0, 'pruning environments replanned per Floyd-Warshall pass (speed only); '
                               '0: 8 on a CPU, 256 elsewhere')

    def __post_init__(self):
        cfg_lib.check_types(self)
        if not (self.kappa >= 0):
            raise ValueError(f'AgentConfig.kappa must be >= 0 (inf disables pruning); got {self.kappa}')
        if not self.switch_radius > 0:
            raise ValueError(f'AgentConfig.switch_radius must be > 0; got {self.switch_radius}')
        if not (math.isfinite(self.patience) and self.patience >= 0):
            raise ValueError(f'AgentConfig.patience must be a finite number >= 0 (0: the fixed budget); '
                             f'got {self.patience}')
        if not (math.isfinite(self.progress) and self.progress >= 0):
            raise ValueError(f'AgentConfig.progress must be a finite number >= 0; got {self.progress}')
        if not 0 <= self.cut_slack < 1:
            raise ValueError(f'AgentConfig.cut_slack must be in [0, 1) (0: cut the overrun edge alone); '
                             f'got {self.cut_slack}')
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
    budget: jax.Array  # float32 steps (fixed rule) or stalled steps (stall rule) allowed on the leg (inf: none)
    leg_d: jax.Array  # float32 d(from, to) of the current leg (inf: no budgeted leg)
    best: jax.Array  # float32 the lowest d(s, target) on this leg that counted as progress (inf at its start)
    stall: jax.Array  # int32 consecutive steps without progress on this leg
    max_stall: jax.Array  # int32 the longest such run on this leg
    legs: jax.Array  # float32 [MAX_LEGS, LEG_FIELDS] completed legs: (d(from, to), steps, longest stall, kind); -1 padded
    n_legs: jax.Array  # int32 legs completed (all of them; the first MAX_LEGS are in ``legs``)
    pruned: jax.Array  # int32 legs marked untraversable so far (edges, goal and start attachments)
    removed: jax.Array  # int32 keypoint edges set to inf so far (overrun edges; with cut_slack, their parallels)
    cuts: jax.Array  # int32 [MAX_CUTS, 2] the first MAX_CUTS pruned keypoint edges (i, j), -1 padded (plots)
    needs_replan: jax.Array  # bool: w or to_g changed this step
    kept: jax.Array  # int32 overruns not cut because their cut would have left no route (keep_route)


def stall_kappa(kappa):
    """``kappa``, or 1 where it is inf. Under the stall rule kappa only says whether a leg is budgeted
    (:func:`leg_budget`), so a row moved onto the stall rule needs a finite one. Host floats or arrays."""
    if isinstance(kappa, (int, float)):
        return float(kappa) if math.isfinite(kappa) else 1.0
    return jnp.where(jnp.isfinite(kappa), kappa, 1.0)


def leg_budget(leg_d: jax.Array, kappa: jax.Array, patience: jax.Array, edge: jax.Array = True,
               edges_only: jax.Array = False) -> jax.Array:
    """A leg's budget: ``(1 + kappa) leg_d`` steps (``patience`` 0, the fixed rule) or ``patience``
    stalled steps (the stall rule); ``inf`` when ``kappa`` is, when the leg is unbudgeted (``leg_d``
    inf), or when ``edges_only`` and the leg is not a keypoint edge (``edge`` False: a start or goal leg)."""
    fixed = (1.0 + kappa) * leg_d
    stall = jnp.where(jnp.isfinite(kappa) & jnp.isfinite(leg_d), patience, jnp.inf)
    budget = jnp.where(patience > 0, stall, fixed)
    return jnp.where(edges_only & ~edge, jnp.inf, budget).astype(jnp.float32)


def parallel_edges(dist: jax.Array, w: jax.Array, i: jax.Array, j: jax.Array, leg: jax.Array,
                   slack, into: bool = False) -> jax.Array:
    """The edges an overrun of ``z_i -> z_j`` (length ``leg``) cuts: bool ``[K, K]``.

    ``slack`` 0: the edge (i, j) alone. ``slack`` in (0, 1): also every edge (a, b) whose start lies
    within ``slack * leg`` of z_i and whose end lies within ``slack * leg`` of z_j, in map distance
    either way (``dist``: map distances ``[K, K]``, ``w``: edge weights ``[K, K]``). ``slack < 1``
    keeps the edges out of z_j and into z_i (``dist[i, j] = leg``) uncut. ``slack`` may be traced
    (a per-environment value); a Python 0 skips the neighbourhoods at trace time. ``into`` (static):
    the edges into z_j's neighbourhood from every keypoint, not only from z_i's."""
    k = w.shape[0]
    one = (jnp.arange(k)[:, None] == i) & (jnp.arange(k)[None, :] == j)
    if isinstance(slack, (int, float)) and not slack:
        return one
    lim = slack * leg
    near_i = (jnp.minimum(dist[i], dist[:, i]) <= lim) | into  # [K] starts next to z_i (with into: any)
    near_j = jnp.minimum(dist[j], dist[:, j]) <= lim  # [K] ends next to z_j
    off = ~jnp.eye(k, dtype=bool)  # a keypoint's zero-weight edge to itself is never cut
    return one | ((slack > 0) & near_i[:, None] & near_j[None, :] & jnp.isfinite(w) & off)


def _entry(a_dist: jax.Array, from_s: jax.Array, to_g: jax.Array, direct: jax.Array, kappa, patience,
           edges_only=False) -> tuple:
    """First target of the best plan, its start-leg budget and length: ``(node, prev, budget, leg_d)``."""
    first = planning.plan(a_dist, from_s, to_g, direct).first
    on_graph = first >= 0
    leg_d = jnp.where(on_graph, from_s[jnp.maximum(first, 0)], jnp.inf).astype(jnp.float32)
    return (first.astype(jnp.int32), jnp.where(on_graph, START, -1).astype(jnp.int32),
            leg_budget(leg_d, kappa, patience, False, edges_only), leg_d)


def agent_init(dist: Callable, graph: Graph, s: jax.Array, g: jax.Array, kappa: jax.Array,
               use_graph: jax.Array = True, patience: jax.Array = 0.0, edges_only: jax.Array = False) -> AgentState:
    """Plan from latent ``s [L]`` to latent ``g [L]`` on ``graph`` (one environment); the start leg's
    budget uses ``kappa``, ``patience`` and ``edges_only`` (per environment: an ablation is a row of
    the batch)."""
    d_kk, nxt = planning.floyd_warshall(graph.w)
    from_s, to_g, direct = planning.attach(dist, graph.z, graph.mask, s, g, graph.tau)
    node, prev, budget, leg_d = _entry(d_kk, from_s, to_g, direct, kappa, patience, edges_only)
    node = jnp.where(use_graph, node, -1).astype(jnp.int32)
    prev = jnp.where(use_graph, prev, -1).astype(jnp.int32)
    budget = jnp.where(use_graph, budget, jnp.inf).astype(jnp.float32)
    leg_d = jnp.where(use_graph, leg_d, jnp.inf).astype(jnp.float32)
    k = graph.w.shape[0]
    return AgentState(w=graph.w, dist=d_kk, nxt=nxt.astype(jnp.int32), to_g=to_g, goal=g, banned=jnp.zeros(k, bool),
                      node=node, prev=prev, t_edge=jnp.int32(0), budget=budget, leg_d=leg_d,
                      best=jnp.float32(jnp.inf), stall=jnp.int32(0), max_stall=jnp.int32(0),
                      legs=jnp.full((MAX_LEGS, LEG_FIELDS), -1.0, jnp.float32), n_legs=jnp.int32(0), pruned=jnp.int32(0),
                      removed=jnp.int32(0), cuts=jnp.full((MAX_CUTS, 2), -1, jnp.int32), needs_replan=jnp.bool_(False),
                      kept=jnp.int32(0))


def _next_leg(a: AgentState, k: jax.Array, kappa: jax.Array, patience: jax.Array, edges_only=False) -> tuple:
    """From keypoint ``k``: ``(hop, prev, budget, leg_d)``. The hop is the next keypoint towards the
    best last keypoint (:func:`aqm_mjx.agent.plan.next_subgoal`), or -1 (the goal) when ``k`` is that
    keypoint (a goal leg budgeted by ``to_g[k]``) or when no path is left (unbudgeted, ``prev`` -1)."""
    total = a.dist[k] + a.to_g
    last = jnp.argmin(total).astype(jnp.int32)
    stuck = ~jnp.isfinite(total[last])
    hop = jnp.where(stuck, -1, planning.next_subgoal(a.nxt, k, last)).astype(jnp.int32)
    leg = jnp.where(stuck, jnp.inf, jnp.where(hop >= 0, a.w[k, jnp.maximum(hop, 0)], a.to_g[k])).astype(jnp.float32)
    return hop, jnp.where(stuck, -1, k).astype(jnp.int32), leg_budget(leg, kappa, patience, hop >= 0, edges_only), leg


def agent_step(dist: Callable, graph: Graph, cfg: AgentConfig, a: AgentState, s: jax.Array,
               kappa: jax.Array, patience: jax.Array = 0.0, edges_only: jax.Array = False,
               cut_slack=None) -> AgentState:
    """Update one environment's target for the current latent ``s [L]`` (switch, time, prune, log).

    On a keypoint edge or goal leg overrun the target points back at the leg's start keypoint,
    unbudgeted; :func:`replan` and :func:`redirect` then choose the next hop from there. On a start
    leg overrun the agent re-attaches from ``s`` without the banned entries. ``patience`` > 0 runs
    the stall rule (``cfg.progress`` is its progress threshold); ``edges_only`` budgets keypoint
    edges alone; ``cut_slack`` (default ``cfg.cut_slack``) sets the parallel cuts.
    """
    cut_slack = cfg.cut_slack if cut_slack is None else cut_slack
    k = jnp.maximum(a.node, 0)
    d_node = dist(s, graph.z[k])
    reached = (a.node >= 0) & (d_node <= cfg.switch_radius)
    # SWITCH: from the reached keypoint, the next hop of the best path
    hop, hop_prev, hop_budget, hop_d = _next_leg(a, k, kappa, patience, edges_only)
    # PROGRESS on the leg (the stall rule's clock; logged for both rules)
    d_target = jnp.where(a.node >= 0, d_node, dist(s, a.goal))
    progressed = d_target < a.best - cfg.progress
    best = jnp.where(progressed, d_target, a.best)
    stall = jnp.where(progressed, 0, a.stall + 1).astype(jnp.int32)
    max_stall = jnp.maximum(a.max_stall, stall)
    # OVERRUN: mark the leg untraversable
    t = a.t_edge + 1
    over = ~reached & jnp.where(patience > 0, stall > a.budget, t > a.budget)
    # LOG the leg that ends here
    logged = reached & (a.prev != -1)
    kind = jnp.where(a.prev == START, LEG_START, jnp.where(a.node >= 0, LEG_EDGE, LEG_GOAL))
    row = jnp.stack([a.leg_d, t.astype(jnp.float32), max_stall.astype(jnp.float32), kind.astype(jnp.float32)])
    legs = a.legs.at[jnp.where(logged, a.n_legs, MAX_LEGS)].set(row, mode='drop')
    edge_over = over & (a.prev >= 0) & (a.node >= 0)
    goal_over = over & (a.prev >= 0) & (a.node < 0)
    start_over = over & (a.prev == START) & (a.node >= 0)
    i, j = jnp.maximum(a.prev, 0), k
    cut = parallel_edges(a.dist, a.w, i, j, a.leg_d, cut_slack, cfg.cut_into) & edge_over
    w = jnp.where(cut, jnp.inf, a.w)
    to_g = jnp.where(goal_over, a.to_g.at[i].set(jnp.inf), a.to_g)
    banned = a.banned | (start_over & (jnp.arange(a.banned.shape[0]) == k))
    used = jnp.sum(a.cuts[:, 0] >= 0)  # keypoint edges cut so far (pruned also counts attachments)
    slot = jnp.where(edge_over & (used < MAX_CUTS), used, MAX_CUTS)  # out of range: dropped
    cuts = a.cuts.at[slot].set(jnp.stack([i, j]).astype(jnp.int32), mode='drop')
    # re-attach from here (used on a start-leg overrun only; 2 K + 2 distances per step)
    from_s = planning.attach_start(dist, graph.z, graph.mask & ~banned, s, graph.tau)
    direct = planning.direct_edge(dist, s, a.goal, graph.tau)
    e_node, e_prev, e_budget, e_d = _entry(a.dist, from_s, to_g, direct, kappa, patience, edges_only)
    back = edge_over | goal_over
    node = jnp.where(reached, hop, jnp.where(back, a.prev, jnp.where(start_over, e_node, a.node)))
    prev = jnp.where(reached, hop_prev, jnp.where(back, -1, jnp.where(start_over, e_prev, a.prev)))
    budget = jnp.where(reached, hop_budget, jnp.where(back, jnp.inf, jnp.where(start_over, e_budget, a.budget)))
    leg_d = jnp.where(reached, hop_d, jnp.where(back, jnp.inf, jnp.where(start_over, e_d, a.leg_d)))
    new_leg = reached | over
    return a.replace(w=w, to_g=to_g, banned=banned, cuts=cuts, node=node.astype(jnp.int32),
                     prev=prev.astype(jnp.int32), t_edge=jnp.where(new_leg, 0, t).astype(jnp.int32),
                     budget=budget.astype(jnp.float32), leg_d=leg_d.astype(jnp.float32),
                     best=jnp.where(new_leg, jnp.inf, best).astype(jnp.float32),
                     stall=jnp.where(new_leg, 0, stall).astype(jnp.int32),
                     max_stall=jnp.where(new_leg, 0, max_stall).astype(jnp.int32),
                     legs=legs, n_legs=a.n_legs + logged.astype(jnp.int32),
                     pruned=a.pruned + over.astype(jnp.int32),
                     removed=a.removed + jnp.sum(cut & jnp.isfinite(a.w)).astype(jnp.int32), needs_replan=back)


def redirect(a: AgentState, kappa: jax.Array, patience: jax.Array = 0.0, edges_only: jax.Array = False) -> AgentState:
    """After a prune and :func:`replan`: from the pruned leg's start z_i, take the next hop of the
    new best path straight away (a budgeted leg from z_i), rather than walking back to z_i."""
    i = jnp.maximum(a.node, 0)  # agent_step pointed node back at z_i
    hop, prev, budget, leg_d = _next_leg(a, i, kappa, patience, edges_only)
    go = a.needs_replan
    return a.replace(node=jnp.where(go, hop, a.node).astype(jnp.int32),
                     prev=jnp.where(go, prev, a.prev).astype(jnp.int32),
                     budget=jnp.where(go, budget, a.budget).astype(jnp.float32),
                     leg_d=jnp.where(go, leg_d, a.leg_d).astype(jnp.float32), t_edge=jnp.where(go, 0, a.t_edge),
                     best=jnp.where(go, jnp.inf, a.best).astype(jnp.float32),
                     stall=jnp.where(go, 0, a.stall).astype(jnp.int32),
                     max_stall=jnp.where(go, 0, a.max_stall).astype(jnp.int32))


def has_route(a: AgentState) -> jax.Array:
    """bool: after a prune and :func:`replan`, a path is left from the pruned leg's start z_i (where
    :func:`agent_step` pointed ``node``) to the goal."""
    i = jnp.maximum(a.node, 0)
    return jnp.isfinite(jnp.min(a.dist[i] + a.to_g))


def keep_last_route(old: AgentState, new: AgentState) -> AgentState:
    """``keep_route``: an environment whose prune this step left no route to the goal (``new``, after
    :func:`replan`) takes back ``old``'s graph and leg, with the leg's clock started again; it counts
    the overrun in ``kept``, not in ``pruned``. Others keep ``new``."""
    lost = new.needs_replan & ~has_route(new)
    restart = old.replace(t_edge=jnp.zeros_like(old.t_edge), best=jnp.full_like(old.best, jnp.inf),
                          stall=jnp.zeros_like(old.stall), max_stall=jnp.zeros_like(old.max_stall),
                          needs_replan=jnp.zeros_like(old.needs_replan), kept=old.kept + 1)
    return jax.tree.map(lambda r, n: jnp.where(lost, r, n), restart, new)


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


