"""OGBench's evaluation protocol as one episode table (host side), the inputs and keys of its
episodes, and the success rates (on device).

Protocol: every task of the maze, ``episodes`` episodes each, deterministic actions clipped to
[-1, 1], an episode succeeds when it is at the goal at its last step. The AQM agent, its ablations
(other kappas, the stall rule, the paper's rule, no pruning, the flat policy) and test-time layouts
(:mod:`aqm_mjx.envs.shifts`) are rows of the same table. Episode ``(layout, task, e)`` has the same
key id for every agent, so the agents meet identical episodes.

Episode splits. The episodes of an evaluation key come in two named splits (``ProtocolConfig.split``):
``dev``, the key itself, where settings are chosen (every default of the presets was chosen on the
``dev`` episodes of ``PRNGKey(0)``), and ``report``, ``fold_in(key, REPORT_FOLD)``, which no choice
looks at and which every table is measured on. The calibration pass uses neither: its episodes run
between start and goal cells of the training layout that no evaluation task uses
(:func:`calibration_pairs`), on ``fold_in(key, CALIBRATION_FOLD)``.
"""

from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple, Optional

import jax
import jax.numpy as jnp
import numpy as np

from aqm_mjx import config as cfg_lib
from aqm_mjx.agent.rollout import EpisodeInputs, episode_inputs, episode_keys
from aqm_mjx.agent.rules import stall_kappa
from aqm_mjx.config import option
from aqm_mjx.envs import mazes
from aqm_mjx.envs import physics as physics_presets

AQM, FLAT, NO_PRUNING = 'aqm', 'flat', 'no-pruning'
PLANNER = 'planner'  # the one row of a method with its own test-time rule (GAS's, HILP's planning; no budgets)
PAPER_CAL = 'paper=cal'  # the paper's rule at the kappa calibrated on keypoint edges
BACKENDS = ('mjx', 'ogbench')
CALIBRATE = ('none', 'fixed', 'stall')  # ProtocolConfig.calibrate: which budget a calibration pass sets
CALIBRATED = ('', 'fixed', 'stall', 'paper')  # Row.calibrated: which calibrated budget a row takes ('' none)
CALIBRATION_FOLD = 1  # the calibration pass's episodes: fold_in(evaluation key, 1), apart from the evaluation's
REPORT_FOLD = 2  # the report split's episodes: fold_in(evaluation key, 2)
CELLS_FOLD = 3  # which start and goal cells each calibration episode draws: fold_in(its key, 3)
SPLITS = ('dev', 'report')
MIN_PAIR_CELLS = 4  # calibration pairs are at least this many BFS steps apart (legs of several keypoints)


@dataclasses.dataclass(frozen=True)
class ProtocolConfig:
    """Which episodes an evaluation runs and how many at a time."""

    episodes: int = option(50, 'episodes per task, agent and layout (OGBench: 50)')
    tasks: tuple[int, ...] = option((), "task ids to run; empty: all of the maze's (1..5)")
    horizon: int = option(0, "control steps per episode; 0: the environment's limit (1000 for the ant)")
    envs: int = option(1024, 'environments per jitted call; the episode table runs in chunks of this size (0: as '
                       'many as the memory estimate allows, at most 65,536, one compile)')
    ablations: tuple[str, ...] = option((NO_PRUNING, FLAT), "agents run beside AQM on the same episodes: "
                                        "'no-pruning', 'flat', 'kappa=X' (the fixed budget at slack X), "
                                        "'stall=P' (the stall rule at patience P)")
    backend: str = option('mjx', "physics of the episodes: 'mjx' (our MJX copy: one jitted program, any device) or "
                          "'ogbench' (OGBench's own MuJoCo environments stepped on the host, the agent one jitted "
                          "call per control step). The cpu presets' run and evaluate take 'ogbench' on a host "
                          "without an accelerator unless a backend or an MJX physics preset is named",
                          choices=BACKENDS)
    physics_preset: str = option('ogbench', "backend 'mjx': the physics of our MJX copy, a named setting of the "
                                 "fidelity study (RESULTS 7.6): 'ogbench' (OGBench's: RK4, Newton 100/50), 'fast' "
                                 "(Newton 4/8, 2.2x faster, inside OGBench's intervals on the closures) or another of its rows", choices=physics_presets.NAMES)
    workers: int = option(0, "backend 'ogbench': processes that step the environments (0: this process)")
    calibrate: str = option('none', "the AQM row's budget in the controller's own time: 'none' (agent.kappa and "
                            "agent.patience as set), 'fixed' (kappa) or 'stall' (patience) from a no-pruning pass on "
                            "the training layout before the evaluation", choices=CALIBRATE)
    false_alarm: float = option(0.005, 'calibrate: the fraction of traversable legs of the calibration pass that '
                                'the calibrated budget would cut')
    stall_scale: float = option(0.0, "calibrate='stall': > 0 sets patience to this multiple of the calibration "
                                "pass's 90th percentile of the longest stall (stable across calibration keys) "
                                'instead of its false_alarm quantile')
    calibration_episodes: int = option(100, 'calibrate: episodes of the calibration pass, between start and goal '
                                       'cells of the training layout that no evaluation task uses')
    split: str = option('report', "which episodes of the evaluation key: 'report' (no setting was chosen on them; "
                        "every table) or 'dev' (where settings are chosen)", choices=SPLITS)
    curve_episodes: int = option(0, "learning curve: development episodes per task of the training layout, run at "
                                 "every checkpoint while a run trains (the planner without pruning); 0: none")
    curve_backend: str = option('', "learning curve: physics of its episodes ('mjx', 'ogbench'; '': the protocol's "
                                "backend)", choices=('',) + BACKENDS)

    def __post_init__(self):
        cfg_lib.check_types(self)
        cfg_lib.check_positive_int(self, 'episodes', 'calibration_episodes')
        if isinstance(self.envs, bool) or not isinstance(self.envs, int) or self.envs < 0:
            raise ValueError(f'ProtocolConfig.envs must be an integer >= 0 (0: chosen from the memory estimate); '
                             f'got {self.envs!r}')
        cfg_lib.check_choice(type(self).__name__, 'calibrate', self.calibrate, CALIBRATE)
        cfg_lib.check_choice(type(self).__name__, 'split', self.split, SPLITS)
        if not 0.0 < self.false_alarm < 1.0:
            raise ValueError(f'ProtocolConfig.false_alarm must be in (0, 1); got {self.false_alarm!r}')
        if not math.isfinite(self.stall_scale) or self.stall_scale < 0:
            raise ValueError(f'ProtocolConfig.stall_scale must be a finite number >= 0 (0: the false_alarm '
                             f'quantile); got {self.stall_scale!r}')
        if self.curve_backend not in ('',) + BACKENDS:
            raise ValueError(f'unknown ProtocolConfig.curve_backend {self.curve_backend!r}; expected one of '
                             f'{", ".join(BACKENDS)} or empty (the protocol\'s backend)')
        if self.physics_preset not in physics_presets.NAMES:
            raise ValueError(f'unknown ProtocolConfig.physics_preset {self.physics_preset!r}; expected one of '
                             f'{", ".join(physics_presets.NAMES)} (the fidelity study\'s rows, RESULTS 7.6)')
        if self.backend not in BACKENDS:
            raise ValueError(f'unknown ProtocolConfig.backend {self.backend!r}; expected one of {", ".join(BACKENDS)}')
        if isinstance(self.workers, bool) or not isinstance(self.workers, int) or self.workers < 0:
            raise ValueError(f'ProtocolConfig.workers must be an integer >= 0; got {self.workers!r}')
        if isinstance(self.curve_episodes, bool) or not isinstance(self.curve_episodes, int) or self.curve_episodes < 0:
            raise ValueError(f'ProtocolConfig.curve_episodes must be an integer >= 0 (0: no curve); '
                             f'got {self.curve_episodes!r}')
        if isinstance(self.horizon, bool) or not isinstance(self.horizon, int) or self.horizon < 0:
            raise ValueError(f'ProtocolConfig.horizon must be an integer >= 0 (0: the limit); got {self.horizon!r}')
        repeated = sorted({t for t in self.tasks if self.tasks.count(t) > 1})
        if repeated:
            raise ValueError(f'ProtocolConfig.tasks repeats task(s) {repeated}: each task id once '
                             '(--episodes sets how often a task runs)')
        agent_specs(1.0, self.ablations)  # validates the ablation names


def _number(a: str, what: str, finite: bool = False) -> float:
    try:
        x = float(a.split('=', 1)[1])
    except ValueError:
        raise ValueError(f'ablation {a!r}: {what} must be a number') from None
    if not x >= 0 or (finite and not math.isfinite(x)):
        raise ValueError(f'ablation {a!r}: {what} must be {"a finite number " if finite else ""}>= 0')
    return x


class Row(NamedTuple):
    """One agent of the episode table: its name and per-environment budget."""

    name: str
    kappa: float  # budget slack (inf: no pruning)
    use_graph: bool  # False: the flat policy
    patience: float  # 0: the fixed budget (1 + kappa) d; > 0: the stall rule
    edges_only: bool = False  # budget keypoint edges alone, not start and goal legs (the paper's rule)
    cut_slack: float = 0.0  # parallel cuts (0: the overrun edge alone)
    calibrated: str = ''  # which calibrated budget replaces kappa / patience: one of CALIBRATED ('' none)


def agent_specs(kappa: float, ablations, plans: bool = True, patience: float = 0.0,
                cut_slack: float = 0.0, own_rule: bool = False) -> list[Row]:
    """The rows of the table: the AQM agent at ``kappa``, ``patience`` (0: the fixed budget) and
    ``cut_slack`` first, then the ablations (``'kappa=X'``: the fixed budget at X; ``'stall=P'``: the
    stall rule at patience P, with the AQM row's kappa; both with the AQM row's parallel cuts;
    ``'paper=X'``: the paper's rule, a fixed budget (1 + X) d on keypoint edges alone, one cut per
    overrun; ``'paper=cal'``: the same at the kappa a calibration pass gives for keypoint edges);
    for a method without a quasimetric (``plans`` False) the flat controller alone; for a method with
    a rule of its own (``own_rule``: GAS's) its planner alone, unbudgeted (:data:`PLANNER`)."""
    if own_rule:
        return [Row(PLANNER, math.inf, True, 0.0)]
    if not plans:
        return [Row(FLAT, math.inf, False, 0.0)]
    out = [Row(AQM, float(kappa), True, float(patience), cut_slack=float(cut_slack))]
    for a in ablations:
        if a == NO_PRUNING:
            out.append(Row(a, math.inf, True, 0.0))
        elif a == FLAT:
            out.append(Row(a, math.inf, False, 0.0))
        elif a == PAPER_CAL:
            out.append(Row(a, 1.0, True, 0.0, edges_only=True, calibrated='paper'))
        elif isinstance(a, str) and a.startswith('paper='):
            out.append(Row(a, _number(a, 'kappa'), True, 0.0, edges_only=True))
        elif isinstance(a, str) and a.startswith('kappa='):
            out.append(Row(a, _number(a, 'kappa'), True, 0.0, cut_slack=float(cut_slack)))
        elif isinstance(a, str) and a.startswith('stall='):
            p = _number(a, 'patience', finite=True)
            if p == 0:
                raise ValueError(f'ablation {a!r}: patience must be > 0 (0 is the fixed budget: kappa=X)')
            out.append(Row(a, stall_kappa(float(kappa)), True, p, cut_slack=float(cut_slack)))
        else:
            raise ValueError(f'unknown ablation {a!r}; expected {NO_PRUNING!r}, {FLAT!r}, kappa=X, stall=P, paper=X '
                             f'or {PAPER_CAL!r}')
    names = [spec[0] for spec in out]
    if len(set(names)) != len(names):
        raise ValueError(f'ablations repeat an agent: {names}')
    return out


def needs_calibration(protocol: 'ProtocolConfig') -> bool:
    """Whether an evaluation under ``protocol`` runs a calibration pass first (the AQM row's
    ``calibrate``, or a row such as ``'paper=cal'`` that takes a calibrated budget)."""
    return protocol.calibrate != 'none' or PAPER_CAL in protocol.ablations


class Table(NamedTuple):
    """One row per episode (numpy, host side)."""

    agent: np.ndarray  # int [E] index into the agent specs
    variant: np.ndarray  # int [E] index into the layouts
    task: np.ndarray  # int32 [E] task id (1-based; 0: a calibration episode between ``pairs`` cells)
    episode: np.ndarray  # int [E] episode number within (layout, task)
    seed_id: np.ndarray  # int32 [E] key id: the same for every agent on one (layout, task, episode)
    kappa: np.ndarray  # float32 [E]
    use_graph: np.ndarray  # bool [E]
    group: np.ndarray  # int32 [E] (agent, layout, task) cell of the rate table, row-major
    patience: np.ndarray  # float32 [E] (0: the fixed budget)
    edges_only: np.ndarray  # bool [E] keypoint edges alone are budgeted (the paper's rule)
    cut_slack: np.ndarray  # float32 [E] parallel cuts
    calibrated: np.ndarray  # int8 [E] index into CALIBRATED: which calibrated budget the row takes


def episode_table(specs, n_variants: int, task_ids, episodes: int) -> Table:
    """Every agent x layout x task x episode, in that order."""
    specs = [Row(*s) for s in specs]
    a, v, t, e = np.meshgrid(np.arange(len(specs)), np.arange(n_variants), np.asarray(task_ids), np.arange(episodes),
                             indexing='ij')
    a, v, t, e = (x.reshape(-1) for x in (a, v, t, e))
    n_tasks = len(task_ids)
    task_pos = np.searchsorted(np.sort(task_ids), t) if n_tasks else t
    seed_id = ((v * n_tasks + task_pos) * episodes + e).astype(np.int32)
    col = lambda f, dt: np.array([getattr(specs[i], f) for i in a], dt)  # noqa: E731
    group = ((a * n_variants + v) * n_tasks + task_pos).astype(np.int32)
    cal = np.array([CALIBRATED.index(specs[i].calibrated) for i in a], np.int8)
    return Table(a, v, t.astype(np.int32), e, seed_id, col('kappa', np.float32), col('use_graph', bool), group,
                 col('patience', np.float32), col('edges_only', bool), col('cut_slack', np.float32), cal)


class Episodes(NamedTuple):
    """Everything the episode table of an evaluation depends on (host side)."""

    variants: dict  # {name: grid [H, W]}
    grids: np.ndarray  # int8 [V, H, W], validated
    task_ids: list  # sorted task ids ([0] for a calibration pass)
    specs: list  # agent_specs(...): Row per agent
    table: Table
    steps: int  # control steps per episode
    split: str = 'dev'  # which episodes of the key: SPLITS ('dev': the key itself)
    pairs: Optional[np.ndarray] = None  # int32 [P, 4] start and goal cells of task-0 (calibration) episodes

    @property
    def agents(self) -> list:
        return [s[0] for s in self.specs]

    @property
    def shape(self) -> tuple[int, int, int]:
        """(agents, layouts, tasks) of the rate table."""
        return len(self.specs), len(self.grids), len(self.task_ids)


def plan_episodes(env, protocol: ProtocolConfig, kappa: float, variants: Optional[dict] = None,
                  plans: bool = True, patience: float = 0.0, cut_slack: float = 0.0, own_rule: bool = False) -> Episodes:
    """Validate the layouts and task ids of an evaluation and lay out its episode table
    (``kappa``, ``patience``, ``cut_slack``: the AQM agent's budget slack, rule and parallel cuts;
    ``plans`` False: a method without a quasimetric, one flat row). The episode keys do not depend
    on the agents, so every method meets the same episodes."""
    variants = {'base': env.layout} if variants is None else dict(variants)
    grids = np.stack([mazes.validate_grid(g, env.maze) for g in variants.values()])
    valid_ids = {t.task_id for t in mazes.tasks(env.maze)}
    task_ids = sorted(protocol.tasks) if protocol.tasks else sorted(valid_ids)
    bad = [t for t in task_ids if t not in valid_ids]
    if bad:
        raise ValueError(f'task ids {bad} do not exist in maze {env.maze!r} (it has {sorted(valid_ids)})')
    specs = agent_specs(kappa, protocol.ablations, plans, patience, cut_slack, own_rule)
    table = episode_table(specs, len(grids), task_ids, protocol.episodes)
    return Episodes(variants, grids, task_ids, specs, table, int(protocol.horizon or env.max_episode_steps),
                    protocol.split)


def calibration_pairs(grid, maze: str, min_cells: int = MIN_PAIR_CELLS) -> np.ndarray:
    """The start and goal cells a calibration episode may draw: int32 ``[P, 4]`` (init i, j, goal i, j),
    every ordered pair of free cells of ``grid`` (the training layout) at least ``min_cells`` BFS
    steps apart, neither of which is a start or goal cell of an evaluation task of ``maze``.

    Raises:
        ValueError: the layout has no such pair (a maze too small for the rule).
    """
    grid = mazes.validate_grid(grid, maze)
    used = {t.init_ij for t in mazes.tasks(maze)} | {t.goal_ij for t in mazes.tasks(maze)}
    free = [tuple(int(x) for x in c) for c in np.argwhere(grid == 0) if tuple(int(x) for x in c) not in used]
    out = []
    for a in free:
        steps = mazes.bfs_from(grid, a)
        out += [a + b for b in free if b != a and steps[b] >= min_cells]
    if not out:
        raise ValueError(f'maze {maze!r}: no two free cells outside the evaluation tasks lie {min_cells} or more '
                         'steps apart; nothing to calibrate on')
    return np.asarray(out, np.int32)


def calibration_protocol(protocol: ProtocolConfig) -> ProtocolConfig:
    """The protocol of the calibration pass before an evaluation: the agent alone (run it without
    pruning), ``protocol.calibration_episodes`` episodes, the same horizon and backend, no split
    (its key is ``fold_in(key, CALIBRATION_FOLD)`` of the evaluation's)."""
    return dataclasses.replace(protocol, episodes=protocol.calibration_episodes, ablations=(), calibrate='none',
                               tasks=(), split='dev')


def calibration_episodes(env, protocol: ProtocolConfig, layout=None) -> Episodes:
    """The episode table of the calibration pass: :func:`calibration_protocol`, no pruning, on
    ``layout`` (default the maze's: the training layout), each episode between two cells of
    :func:`calibration_pairs` (task id 0), drawn from its own key: no evaluation task, start or goal
    cell, and no evaluation key."""
    p = calibration_protocol(protocol)
    grid = env.layout if layout is None else layout
    grids = mazes.validate_grid(grid, env.maze)[None]
    specs = agent_specs(math.inf, ())
    table = episode_table(specs, 1, [0], p.episodes)
    return Episodes({'train': grids[0]}, grids, [0], specs, table, int(p.horizon or env.max_episode_steps), 'dev',
                    calibration_pairs(grids[0], env.maze))


def split_key(key: jax.Array, split: str) -> jax.Array:
    """The key of a split's episodes: ``key`` for ``'dev'``, ``fold_in(key, REPORT_FOLD)`` for ``'report'``."""
    if split not in SPLITS:
        raise ValueError(f'unknown episode split {split!r}; expected one of {", ".join(SPLITS)}')
    return key if split == 'dev' else jax.random.fold_in(key, REPORT_FOLD)


def table_inputs(episodes: Episodes, key: jax.Array, rows=None, budgets: Optional[dict] = None) -> EpisodeInputs:
    """The rollout inputs of table ``rows`` (default: all), episode keys from the split's key
    (:func:`split_key`) and each row's ``seed_id``: the one place where the table becomes a batch.

    ``budgets``: ``{kind: (kappa, patience)}`` for the rows whose ``calibrated`` is that kind (from a
    calibration pass; traced values allowed). Task-0 rows draw their cells from ``episodes.pairs``."""
    t = episodes.table
    rows = np.arange(len(t.task)) if rows is None else np.asarray(rows)
    key = split_key(key, episodes.split)
    ids = t.seed_id[rows]
    kappa, patience = jnp.asarray(t.kappa[rows]), jnp.asarray(t.patience[rows])
    for kind, (k, p) in (budgets or {}).items():
        mine = jnp.asarray(t.calibrated[rows] == CALIBRATED.index(kind))
        kappa, patience = jnp.where(mine, k, kappa), jnp.where(mine, p, patience)
    cells = None
    if episodes.pairs is not None:
        pick = jax.vmap(lambda k: jax.random.randint(k, (), 0, len(episodes.pairs)))(
            episode_keys(jax.random.fold_in(key, CELLS_FOLD), ids)[:, 0])
        cells = jnp.where(jnp.asarray(t.task[rows] == 0)[:, None], jnp.asarray(episodes.pairs)[pick], 0)
    return episode_inputs(episode_keys(key, ids), t.task[rows], episodes.grids[t.variant[rows]], kappa,
                          t.use_graph[rows], patience, t.edges_only[rows], t.cut_slack[rows], cells)


def success_rates(episodes: Episodes, success, pruned) -> tuple[jax.Array, jax.Array]:
    """Per-episode outcomes in table order (``[E]``) -> ``(rates [agents, layouts, tasks],
    mean prunes [agents, layouts])``; pure and jittable (``segment_sum`` over the table's groups)."""
    a, v, n_t = episodes.shape
    group = jnp.asarray(episodes.table.group)
    per_group = len(episodes.table.task) // (a * v * n_t)
    rates = jax.ops.segment_sum(jnp.asarray(success).astype(jnp.float32), group, a * v * n_t) / per_group
    prunes = jax.ops.segment_sum(jnp.asarray(pruned).astype(jnp.float32), group, a * v * n_t) / per_group
    return rates.reshape(a, v, n_t), prunes.reshape(a, v, n_t).mean(-1)


def format_summary(rates, agents, variants, tasks, pruned=None) -> dict:
    """``rates [agents, layouts, tasks]`` (and optional mean prunes ``[agents, layouts]``) ->
    ``{agent: {layout: {'task_T': rate, ..., 'mean': rate(, 'pruned_mean': x)}}}``."""
    rates = np.asarray(rates)
    out = {}
    for ai, a in enumerate(agents):
        out[a] = {}
        for vi, v in enumerate(variants):
            row = {f'task_{t}': float(rates[ai, vi, ti]) for ti, t in enumerate(tasks)}
            row['mean'] = float(rates[ai, vi].mean())
            if pruned is not None:
                row['pruned_mean'] = float(np.asarray(pruned)[ai, vi])
            out[a][v] = row
    return out
