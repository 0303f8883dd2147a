"""OGBench's evaluation protocol as one episode table (host side), the inputs and keys of its
episodes, and the success rates (on device).

Protocol: every task of the maze, ``episodes`` episodes each, deterministic actions clipped to
[-1, 1], an episode succeeds when it is at the goal at its last step. The AQM agent, its ablations
(other kappas, the stall rule, no pruning, the flat policy) and test-time layouts (:mod:`aqm_mjx.envs.shifts`) are
rows of the same table. Episode ``(layout, task, e)`` has the same key id for every agent, so the
agents meet identical episodes.
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
from aqm_mjx.config import option
from aqm_mjx.envs import mazes

AQM, FLAT, NO_PRUNING = 'aqm', 'flat', 'no-pruning'
BACKENDS = ('mjx', 'ogbench')
CALIBRATE = ('none', 'fixed', 'stall')  # ProtocolConfig.calibrate: which budget a calibration pass sets
CALIBRATION_FOLD = 1  # the calibration pass's episodes: fold_in(evaluation key, 1), apart from the evaluation's


@dataclasses.dataclass(frozen=True)
class ProtocolConfig:
    """Which episodes an evaluation runs and how many at a time."""

    episodes: int = option(50, 'episodes per task, agent and layout (OGBench: 50)')
    tasks: tuple[int, ...] = option((), "task ids to run; empty: all of the maze's (1..5)")
    horizon: int = option(0, "control steps per episode; 0: the environment's limit (1000 for the ant)")
    envs: int = option(1024, 'environments per jitted call; the episode table runs in chunks of this size')
    ablations: tuple[str, ...] = option((NO_PRUNING, FLAT), "agents run beside AQM on the same episodes: "
                                        "'no-pruning', 'flat', 'kappa=X' (the fixed budget at slack X), "
                                        "'stall=P' (the stall rule at patience P)")
    backend: str = option('mjx', "physics of the episodes: 'mjx' (our MJX copy: one jitted program, any device) or "
                          "'ogbench' (OGBench's own MuJoCo environments stepped on the host, the agent one jitted "
                          "call per control step)", choices=BACKENDS)
    workers: int = option(0, "backend 'ogbench': processes that step the environments (0: this process)")
    calibrate: str = option('none', "the AQM row's budget in the controller's own time: 'none' (agent.kappa and "
                            "agent.patience as set), 'fixed' (kappa) or 'stall' (patience) from a no-pruning pass on "
                            "the training layout before the evaluation", choices=CALIBRATE)
    false_alarm: float = option(0.005, 'calibrate: the fraction of traversable legs of the calibration pass that '
                                'the calibrated budget would cut')
    calibration_episodes: int = option(4, 'calibrate: episodes per task of the calibration pass (other episodes '
                                       "than the evaluation's)")

    def __post_init__(self):
        cfg_lib.check_types(self)
        cfg_lib.check_positive_int(self, 'episodes', 'envs', 'calibration_episodes')
        cfg_lib.check_choice(type(self).__name__, 'calibrate', self.calibrate, CALIBRATE)
        if not 0.0 < self.false_alarm < 1.0:
            raise ValueError(f'ProtocolConfig.false_alarm must be in (0, 1); got {self.false_alarm!r}')
        if self.backend not in BACKENDS:
            raise ValueError(f'unknown ProtocolConfig.backend {self.backend!r}; expected one of {", ".join(BACKENDS)}')
        if isinstance(self.workers, bool) or not isinstance(self.workers, int) or self.workers < 0:
            raise ValueError(f'ProtocolConfig.workers must be an integer >= 0; got {self.workers!r}')
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


def agent_specs(kappa: float, ablations, plans: bool = True,
                patience: float = 0.0) -> list[tuple[str, float, bool, float]]:
    """``[(name, kappa, use_graph, patience)]``: the AQM agent at ``kappa`` and ``patience`` (0: the
    fixed budget) first, then the ablations (``'kappa=X'``: the fixed budget at X; ``'stall=P'``:
    the stall rule at patience P, with the AQM row's kappa); for a method without a quasimetric
    (``plans`` False) the flat controller alone."""
    if not plans:
        return [(FLAT, math.inf, False, 0.0)]
    out = [(AQM, float(kappa), True, float(patience))]
    for a in ablations:
        if a == NO_PRUNING:
            out.append((a, math.inf, True, 0.0))
        elif a == FLAT:
            out.append((a, math.inf, False, 0.0))
        elif isinstance(a, str) and a.startswith('kappa='):
            out.append((a, _number(a, 'kappa'), True, 0.0))
        elif isinstance(a, str) and a.startswith('stall='):
            p = _number(a, 'patience', finite=True)
            if p == 0:
                raise ValueError(f'ablation {a!r}: patience must be > 0 (0 is the fixed budget: kappa=X)')
            out.append((a, float(kappa) if math.isfinite(kappa) else 1.0, True, p))
        else:
            raise ValueError(f'unknown ablation {a!r}; expected {NO_PRUNING!r}, {FLAT!r}, kappa=X or stall=P')
    names = [spec[0] for spec in out]
    if len(set(names)) != len(names):
        raise ValueError(f'ablations repeat an agent: {names}')
    return out


class Table(NamedTuple):
    """One row per episode (numpy, host side)."""

    agent: np.ndarray  # int [E] index into the agent specs
    variant: np.ndarray  # int [E] index into the layouts
    task: np.ndarray  # int32 [E] task id (1-based)
    episode: np.ndarray  # int [E] episode number within (layout, task)
    seed_id: np.ndarray  # int32 [E] key id: the same for every agent on one (layout, task, episode)
    kappa: np.ndarray  # float32 [E]
    use_graph: np.ndarray  # bool [E]
    group: np.ndarray  # int32 [E] (agent, layout, task) cell of the rate table, row-major
    patience: np.ndarray  # float32 [E] (0: the fixed budget)


def episode_table(specs, n_variants: int, task_ids, episodes: int) -> Table:
    """Every agent x layout x task x episode, in that order."""
    a, v, t, e = np.meshgrid(np.arange(len(specs)), np.arange(n_variants), np.asarray(task_ids), np.arange(episodes),
                             indexing='ij')
    a, v, t, e = (x.reshape(-1) for x in (a, v, t, e))
    n_tasks = len(task_ids)
    task_pos = np.searchsorted(np.sort(task_ids), t) if n_tasks else t
    seed_id = ((v * n_tasks + task_pos) * episodes + e).astype(np.int32)
    kappa = np.array([specs[i][1] for i in a], np.float32)
    use = np.array([specs[i][2] for i in a], bool)
    patience = np.array([specs[i][3] for i in a], np.float32)
    group = ((a * n_variants + v) * n_tasks + task_pos).astype(np.int32)
    return Table(a, v, t.astype(np.int32), e, seed_id, kappa, use, group, patience)


class Episodes(NamedTuple):
    """Everything the episode table of an evaluation depends on (host side)."""

    variants: dict  # {name: grid [H, W]}
    grids: np.ndarray  # int8 [V, H, W], validated
    task_ids: list  # sorted task ids
    specs: list  # agent_specs(...)
    table: Table
    steps: int  # control steps per episode

    @property
    def agents(self) -> list:
        return [s[0] for s in self.specs]

    @property
    def shape(self) -> tuple[int, int, int]:
        """(agents, layouts, tasks) of the rate table."""
        return len(self.specs), len(self.grids), len(self.task_ids)


def plan_episodes(env, protocol: ProtocolConfig, kappa: float, variants: Optional[dict] = None,
                  plans: bool = True, patience: float = 0.0) -> Episodes:
    """Validate the layouts and task ids of an evaluation and lay out its episode table
    (``kappa``, ``patience``: the AQM agent's budget slack and rule; ``plans`` False: a method
    without a quasimetric, one flat row). The episode keys do not depend on the agents, so every method meets the same episodes."""
    variants = {'base': env.layout} if variants is None else dict(variants)
    grids = np.stack([mazes.validate_grid(g, env.maze) for g in variants.values()])
    valid_ids = {t.task_id for t in mazes.tasks(env.maze)}
    task_ids = sorted(protocol.tasks) if protocol.tasks else sorted(valid_ids)
    bad = [t for t in task_ids if t not in valid_ids]
    if bad:
        raise ValueError(f'task ids {bad} do not exist in maze {env.maze!r} (it has {sorted(valid_ids)})')
    specs = agent_specs(kappa, protocol.ablations, plans, patience)
    table = episode_table(specs, len(grids), task_ids, protocol.episodes)
    return Episodes(variants, grids, task_ids, specs, table, int(protocol.horizon or env.max_episode_steps))


def calibration_protocol(protocol: ProtocolConfig) -> ProtocolConfig:
    """The protocol of the calibration pass before an evaluation (``protocol.calibrate``): the agent
    alone (run it without pruning), ``protocol.calibration_episodes`` per task, the same tasks,
    horizon and backend; run it on ``fold_in(key, CALIBRATION_FOLD)`` of the evaluation's key, so
    that its episodes are not the evaluated ones."""
    return dataclasses.replace(protocol, episodes=protocol.calibration_episodes, ablations=(), calibrate='none')


def calibration_episodes(env, protocol: ProtocolConfig) -> Episodes:
    """The episode table of the calibration pass: :func:`calibration_protocol`, no pruning, on the
    maze's layout (the training layout)."""
    return plan_episodes(env, calibration_protocol(protocol), math.inf)


def table_inputs(episodes: Episodes, key: jax.Array, rows=None) -> EpisodeInputs:
    """The rollout inputs of table ``rows`` (default: all), episode keys from ``key`` and each row's
    ``seed_id``: the one place where the table becomes a batch."""
    t = episodes.table
    rows = np.arange(len(t.task)) if rows is None else np.asarray(rows)
    return episode_inputs(episode_keys(key, t.seed_id[rows]), t.task[rows], episodes.grids[t.variant[rows]],
                          t.kappa[rows], t.use_graph[rows], t.patience[rows])


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
