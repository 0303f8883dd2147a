"""The AQM agent's rules at test time, for one environment (``vmap`` them over a batch): plan on the
keypoint graph, switch subgoals, keep a time budget on every leg and, on overrun, mark the leg
untraversable in the environment's own copy of the graph and replan (paper section 4.5).

One control step (:func:`agent_step`, then :func:`replan` and :func:`redirect`; the rollout's
``make_decide`` calls them in this order) runs the paper's phases:

1. follow the leg: the target keypoint is reached within ``switch_radius`` (:func:`follow`);
2. check the budget: the leg's clocks (:func:`_clock`) under the row's rule (:func:`overrun`:
   :func:`fixed_overrun`, the paper's, or :func:`stall_overrun`);
3. prune: the overrun leg goes to ``inf`` in this environment's graph (:func:`_prune`);
4. replan: Floyd-Warshall again for the environments that pruned (:func:`replan`, batched), and the
   next hop from the pruned leg's start (:func:`redirect`).

The leg an agent is on has a kind (:func:`leg_kind`: :data:`LEG_START`, :data:`LEG_EDGE`,
:data:`LEG_GOAL`, :data:`LEG_NONE`); the extensions beyond the paper (parallel cuts, the leg and
cut logs, keep_route) sit in blocks marked EXTENSION.

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
  one budget each (RESULTS.md, section 3.4).
- Leg log: every budgeted leg that ends at its keypoint is recorded as (d(from, to), steps taken,
  longest stall, kind) in ``legs`` (the first :data:`MAX_LEGS`; ``n_legs`` counts all), the measurement
  that calibrates either rule (:mod:`aqm_mjx.evaluation.calibration`).
- ``use_graph=False`` is the flat policy: the target is always the goal.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Callable, Optional

import jax
import jax.numpy as jnp
from flax import struct

from aqm_mjx import config as cfg_lib
from aqm_mjx import presets
from aqm_mjx.agent import plan as planning
from aqm_mjx.agent.planners import CHOICES as PLANNERS
from aqm_mjx.config import option
from aqm_mjx.mapping.graph import Graph

MAX_CUTS = 16  # pruned edges remembered per environment for plots (all are counted in ``pruned``)
MAX_LEGS = 32  # completed legs logged per environment (all are counted in ``n_legs``)
LEG_START, LEG_EDGE, LEG_GOAL = 0, 1, 2  # the kinds of a leg (4th column of the leg log)
LEG_NONE = -1  # not a budgeted leg
LEG_FIELDS = 4  # (d(from, to), steps, longest stall, kind)


@dataclasses.dataclass(frozen=True)
class AgentConfig:
    """Test-time rules of the agent (units are the quasimetric's: control steps). The attachment
    radius of the start and the goal is the graph's own ``tau``."""

    kappa: float = option(presets.default('agent', 'kappa'),
                          'budget slack: B = (1 + kappa) d(z_i, z_j); inf disables pruning. 1 at the cpu preset, not '
                          "the paper's small slack: the learned policy walks slower than the data's expert that d "
                          'measures (RESULTS.md, section 3.4)')
    switch_radius: float = option(presets.default('agent', 'switch_radius'),
                                  'a keypoint counts as reached when d(s, z) <= switch_radius (RESULTS.md)')
    patience: float = option(0.0, "0: the paper's budget (1 + kappa) d; > 0: the stall rule, a leg is cut after this "
                             'many consecutive steps without progress in d(s, target)')
    progress: float = option(1.0, 'stall rule: a step makes progress when d(s, target) falls this far below its best '
                             'on the leg (units of d: control steps)')
    cut_slack: float = option(0.0, "the AQM row's parallel cuts. 0: an overrun cuts its one edge (the paper); in "
                              '(0, 1): it also cuts the edges parallel to it, those whose ends lie within cut_slack '
                              'times the leg of its ends (RESULTS.md, section 3.4)')
    cut_into: bool = option(False, "with parallel cuts: an overrun of z_i -> z_j cuts every edge into z_j's "
                            "neighbourhood, from anywhere, not only from z_i's (its keypoints are taken as unreachable)")
    keep_route: bool = option(False, 'an overrun whose cut would leave no route to the goal is not cut: the leg '
                              'starts again with a fresh budget (the edge may be traversable after all, and it is the '
                              'only way left)')
    replan_slots: int = option(0, 'pruning environments replanned per Floyd-Warshall pass (speed only); '
                               '0: 8 on a CPU, 256 elsewhere')
    planner: str = option('own', "the planner around the method (aqm_mjx.agent.planners): 'own' (as it comes), "
                          "'flat' (no map), 'aqm' (AQM's map, budgets and pruning on the method's distance), 'ttgs' "
                          '(a TTGS-style search on it)', PLANNERS)
    distance_check: bool = option(True, "with planner aqm or ttgs: check the method's distance along the data's "
                                  'trajectories before a map is built (aqm_mjx.mapping.build.distance_check)')
    ttgs_nodes: int = option(4000, 'ttgs: random dataset states as nodes (TTGS: 4,000)')
    ttgs_tau: float = option(24.0, 'ttgs: edges past tau steps are penalised (TTGS: 24 medium and large, 12 giant)')
    ttgs_horizon: float = option(48.0, 'ttgs: T, the subgoal is the farthest path point within T steps (TTGS: 48 '
                                 'medium and large, 24 giant)')
    ttgs_window: int = option(32, 'ttgs: path points searched for the closest one each step (TTGS: the whole path)')

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
        cfg_lib.check_choice('AgentConfig', 'planner', self.planner, PLANNERS)
        cfg_lib.check_positive_int(self, 'ttgs_nodes', 'ttgs_window')
        for name in ('ttgs_tau', 'ttgs_horizon'):
            if not (math.isfinite(getattr(self, name)) and getattr(self, name) > 0):
                raise ValueError(f'AgentConfig.{name} must be a finite number > 0; got {getattr(self, name)}')

    @property
    def ttgs(self) -> dict:
        """The TTGS planner's settings (:func:`aqm_mjx.agent.planners.around`)."""
        return dict(nodes=self.ttgs_nodes, tau=self.ttgs_tau, horizon=self.ttgs_horizon, window=self.ttgs_window)

    @property
    def slots(self) -> int:
        """Replan slots in use: ``replan_slots``, or 8 on a CPU and 256 on an accelerator."""
        return self.replan_slots or (8 if jax.default_backend() == 'cpu' else 256)


# AgentState.prev: where the budgeted leg starts (a keypoint index >= 0, or one of these)
START = -2  # the start leg s -> z_1, whose budget is on the attachment edge
NO_LEG = -1  # no budgeted leg (the flat policy, no path left, or back at z_i after a cut until redirect)


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
    return (first.astype(jnp.int32), jnp.where(on_graph, START, NO_LEG).astype(jnp.int32),
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
    prev = jnp.where(use_graph, prev, NO_LEG).astype(jnp.int32)
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
    return hop, jnp.where(stuck, NO_LEG, k).astype(jnp.int32), leg_budget(leg, kappa, patience, hop >= 0, edges_only), leg


def leg_kind(prev: jax.Array, node: jax.Array) -> jax.Array:
    """The kind of the leg an agent is on: :data:`LEG_START` (s -> z_1), :data:`LEG_EDGE` (z_i ->
    z_j), :data:`LEG_GOAL` (z_n -> g) or :data:`LEG_NONE` (unbudgeted: the flat policy, or no path
    left). int32, any shape."""
    kind = jnp.where(prev == START, LEG_START, jnp.where(node >= 0, LEG_EDGE, LEG_GOAL))
    return jnp.where(prev == NO_LEG, LEG_NONE, kind).astype(jnp.int32)


# The two budget rules (paper section 4.5 and its stall variant). Each row of a batch carries its own
# rule (``patience`` 0 or > 0), so both are evaluated (two scalar tests) and the row's is taken.
def fixed_overrun(t: jax.Array, stall: jax.Array, budget: jax.Array) -> jax.Array:
    """The paper's rule: the leg has taken more than its ``(1 + kappa) d`` steps."""
    return t > budget


def stall_overrun(t: jax.Array, stall: jax.Array, budget: jax.Array) -> jax.Array:
    """The stall rule: more than ``patience`` consecutive steps without progress towards the target."""
    return stall > budget


def overrun(patience: jax.Array, t: jax.Array, stall: jax.Array, budget: jax.Array) -> jax.Array:
    """bool: the leg's budget is spent under the row's rule (``patience`` > 0: the stall rule)."""
    return jnp.where(patience > 0, stall_overrun(t, stall, budget), fixed_overrun(t, stall, budget))


def follow(dist: Callable, graph: Graph, cfg: AgentConfig, a: AgentState, s: jax.Array) -> tuple:
    """FOLLOW THE LEG: ``(reached, d_target)``: whether the target keypoint is within the switch
    radius, and ``d(s, target)`` (the target is the goal when ``node`` is -1). Two distances: the
    rollout computes them once a step and hands them to :func:`reenters` and :func:`agent_step`."""
    d_node = dist(s, graph.z[jnp.maximum(a.node, 0)])
    reached = (a.node >= 0) & (d_node <= cfg.switch_radius)
    return reached, jnp.where(a.node >= 0, d_node, dist(s, a.goal))


def _clock(a: AgentState, d_target: jax.Array, progress: float) -> tuple:
    """The leg's clocks after this step: ``(t, best, stall, max_stall)``: steps on the leg, the best
    ``d(s, target)`` that counted as progress (a fall of more than ``progress``), the current and the
    longest run of steps without progress."""
    progressed = d_target < a.best - progress
    stall = jnp.where(progressed, 0, a.stall + 1).astype(jnp.int32)
    return a.t_edge + 1, jnp.where(progressed, d_target, a.best), stall, jnp.maximum(a.max_stall, stall)


def _prune(a: AgentState, over_kind: jax.Array, cut_slack, cut_into: bool) -> tuple:
    """PRUNE the overrun leg in this environment's graph: ``(w, to_g, banned, cut)``. ``over_kind`` is
    the kind of the leg that overran (:data:`LEG_NONE`: none did). A keypoint edge z_i -> z_j goes to
    ``inf`` in ``w`` (with ``cut_slack`` > 0 also its parallels, :func:`parallel_edges`; ``cut [K, K]``
    marks what was cut), a goal leg cuts z_i's goal attachment, a start leg bans its entry keypoint."""
    i, j = jnp.maximum(a.prev, 0), jnp.maximum(a.node, 0)
    cut = parallel_edges(a.dist, a.w, i, j, a.leg_d, cut_slack, cut_into) & (over_kind == LEG_EDGE)
    to_g = jnp.where(over_kind == LEG_GOAL, a.to_g.at[i].set(jnp.inf), a.to_g)
    banned = a.banned | ((over_kind == LEG_START) & (jnp.arange(a.banned.shape[0]) == j))
    return jnp.where(cut, jnp.inf, a.w), to_g, banned, cut


def _log_leg(a: AgentState, reached: jax.Array, t: jax.Array, max_stall: jax.Array, kind: jax.Array) -> tuple:
    """EXTENSION (calibration): ``(legs, n_legs)`` with the leg that ends here appended as (d(from, to),
    steps, longest stall, kind) when it was budgeted; rows past :data:`MAX_LEGS` are dropped."""
    logged = reached & (kind != LEG_NONE)
    row = jnp.stack([a.leg_d, t.astype(jnp.float32), max_stall.astype(jnp.float32), kind.astype(jnp.float32)])
    return a.legs.at[jnp.where(logged, a.n_legs, MAX_LEGS)].set(row, mode='drop'), a.n_legs + logged.astype(jnp.int32)


def _log_cut(a: AgentState, edge_over: jax.Array) -> jax.Array:
    """EXTENSION (plots): ``cuts`` with the overrun keypoint edge (i, j) appended, the first :data:`MAX_CUTS`."""
    used = jnp.sum(a.cuts[:, 0] >= 0)
    slot = jnp.where(edge_over & (used < MAX_CUTS), used, MAX_CUTS)  # out of range: dropped
    return a.cuts.at[slot].set(jnp.stack([jnp.maximum(a.prev, 0), jnp.maximum(a.node, 0)]).astype(jnp.int32),
                               mode='drop')


def reenters(dist: Callable, graph: Graph, cfg: AgentConfig, a: AgentState, s: jax.Array,
             patience: jax.Array = 0.0, followed: Optional[tuple] = None) -> jax.Array:
    """Whether :func:`agent_step` at ``s`` overruns a start leg, the one case in which it re-attaches
    from ``s`` (``K`` distances, where every other case costs two): the rollout computes that
    attachment only in the steps where some environment of the batch needs it (bool ``[]``).
    ``followed``: :func:`follow`'s result at ``s``, when the caller has it."""
    reached, d_target = follow(dist, graph, cfg, a, s) if followed is None else followed
    t, _, stall, _ = _clock(a, d_target, cfg.progress)
    return ~reached & overrun(patience, t, stall, a.budget) & (leg_kind(a.prev, a.node) == LEG_START)


def agent_step(dist: Callable, graph: Graph, cfg: AgentConfig, a: AgentState, s: jax.Array,
               kappa: jax.Array, patience: jax.Array = 0.0, edges_only: jax.Array = False,
               cut_slack=None, attach: bool = True, followed: Optional[tuple] = None) -> AgentState:
    """One environment's control step of the agent for the current latent ``s [L]``, in the paper's
    phases: follow the leg, check its budget, prune an overrun leg, take the next leg.

    After a keypoint edge or goal leg overrun the target points back at the leg's start keypoint,
    unbudgeted, with ``needs_replan`` set: :func:`replan` (batched over the environments that
    pruned) and :func:`redirect` then choose the next hop from there. After a start leg overrun the
    agent re-attaches from ``s`` without the banned entries. ``patience`` > 0 runs the stall rule
    (``cfg.progress`` is its progress threshold); ``edges_only`` budgets keypoint edges alone;
    ``cut_slack`` (default ``cfg.cut_slack``) sets the parallel cuts. ``attach=False`` (static) skips
    the re-attachment's ``K`` distances: for a step in which :func:`reenters` is False, where the
    result is the same. ``followed``: :func:`follow`'s result at ``s`` (computed here when None).
    """
    cut_slack = cfg.cut_slack if cut_slack is None else cut_slack
    kind = leg_kind(a.prev, a.node)
    # 1. FOLLOW THE LEG: a reached keypoint hands over to the next hop of the best path from it
    reached, d_target = follow(dist, graph, cfg, a, s) if followed is None else followed
    hop, hop_prev, hop_budget, hop_d = _next_leg(a, jnp.maximum(a.node, 0), kappa, patience, edges_only)
    # 2. CHECK THE BUDGET under the row's rule
    t, best, stall, max_stall = _clock(a, d_target, cfg.progress)
    over = ~reached & overrun(patience, t, stall, a.budget)
    over_kind = jnp.where(over, kind, LEG_NONE)
    # 3. PRUNE the overrun leg in this environment's graph
    w, to_g, banned, cut = _prune(a, over_kind, cut_slack, cfg.cut_into)
    # 4. NEXT LEG: after an edge or goal-leg cut, back at z_i to replan (redirect); after a start-leg
    # cut, re-attach from here (2 K + 2 distances per step, used on that overrun only)
    from_s = (planning.attach_start(dist, graph.z, graph.mask & ~banned, s, graph.tau) if attach
              else jnp.full(graph.mask.shape, jnp.inf))
    direct = planning.direct_edge(dist, s, a.goal, graph.tau)
    e_node, e_prev, e_budget, e_d = _entry(a.dist, from_s, to_g, direct, kappa, patience, edges_only)
    back = (over_kind == LEG_EDGE) | (over_kind == LEG_GOAL)
    re_enter = over_kind == LEG_START
    pick = lambda on_hop, on_back, on_entry, keep: jnp.where(  # noqa: E731
        reached, on_hop, jnp.where(back, on_back, jnp.where(re_enter, on_entry, keep)))
    node = pick(hop, a.prev, e_node, a.node)
    prev = pick(hop_prev, NO_LEG, e_prev, a.prev)
    budget = pick(hop_budget, jnp.inf, e_budget, a.budget)
    leg_d = pick(hop_d, jnp.inf, e_d, a.leg_d)
    new_leg = reached | over
    # EXTENSION: the leg log (calibration) and the cut log (plots)
    legs, n_legs = _log_leg(a, reached, t, max_stall, kind)
    cuts = _log_cut(a, over_kind == LEG_EDGE)
    return a.replace(w=w, to_g=to_g, banned=banned, cuts=cuts, node=node.astype(jnp.int32),
                     prev=prev.astype(jnp.int32), t_edge=jnp.where(new_leg, 0, t).astype(jnp.int32),
                     budget=budget.astype(jnp.float32), leg_d=leg_d.astype(jnp.float32),
                     best=jnp.where(new_leg, jnp.inf, best).astype(jnp.float32),
                     stall=jnp.where(new_leg, 0, stall).astype(jnp.int32),
                     max_stall=jnp.where(new_leg, 0, max_stall).astype(jnp.int32),
                     legs=legs, n_legs=n_legs, pruned=a.pruned + over.astype(jnp.int32),
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
    """REPLAN the agents of a batch that pruned this step (``needs_replan``): Floyd-Warshall on
    their weights alone, ``slots`` per pass (:func:`aqm_mjx.agent.plan.replan_pending`); the others
    keep their distances and next hops. Results do not depend on ``slots``."""
    d, n = planning.replan_pending(a.w, a.dist, a.nxt, a.needs_replan, slots)
    return a.replace(dist=d, nxt=n)
