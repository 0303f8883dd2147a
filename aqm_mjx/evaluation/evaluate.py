"""Evaluation of a trained AQM model with OGBench's protocol, vectorised over every episode.

    trained = train.load('runs/medium')
    agent = learned_agent(trained)
    graph, kp = build_map(agent, observations, EvalConfig(), jax.random.PRNGKey(0))
    res = evaluate(env, agent, graph, EvalConfig(episodes=50), variants={'base': layout})

Protocol (OGBench): every task of the maze, ``episodes`` episodes each, deterministic actions
(the main policy's mean) clipped to [-1, 1], an episode succeeds when it is at the goal at its
last step. Ablations (other kappas, no pruning, the flat policy without a graph) and test-time
shifts (:mod:`aqm_mjx.envs.shifts`) are rows of the same episode table: each environment of the
batch carries its own task, walls, kappa and use_graph, so they all run in one compiled program.
Episode ``(variant, task, e)`` gets the same start, goal and noise key for every agent, so the
agents are compared on identical episodes.

The table is cut into chunks of ``envs`` environments (one jitted call each, padded to a static
size; a progress bar counts them). The environment axis is sharded over every JAX device
(``jax.sharding``); with ``jax.distributed.initialize()`` that is every device of every host.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Callable, NamedTuple, Optional

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from aqm_mjx import graph as graphs
from aqm_mjx import rollout
from aqm_mjx.envs import mazes
from aqm_mjx.quasimetric import IQE

FLAT, NO_PRUNING = 'flat', 'no-pruning'


@dataclasses.dataclass(frozen=True)
class EvalConfig:
    """Evaluation settings; saved in the results JSON."""

    episodes: int = 50  # episodes per task (and per variant, per agent); OGBench: 50
    tasks: tuple = ()  # task ids to run; () = all of the maze's (1..5)
    steps: int = 0  # control steps per episode; 0 = the environment's limit (1000 for the ant)
    envs: int = 1024  # environments per jitted call; the episode table is cut into chunks of this size
    # the AQM agent's budget slack (B = (1 + kappa) d(z_i, z_j)). 1.0, not the rollout's 0.25: at the cpu
    # preset the learned policy walks slower than the data's expert that d measures (RESULTS.md, kappa sweep)
    kappa: float = 1.0
    ablations: tuple = (NO_PRUNING, FLAT)  # extra agents in the same batch: 'no-pruning', 'flat', 'kappa=X'
    delta: float = 8.0  # IWE repel radius, quasimetric units (control steps); paper: 10-25; 8 measured best at the cpu preset
    tau: float = 0.0  # edge and attachment radius; 0 = 2 delta
    switch_radius: float = 10.0  # a keypoint counts as reached when d(s, z) <= switch_radius (RESULTS.md)
    max_keypoints: int = 256  # static K
    candidates: int = 10_000  # dataset states encoded as IWE candidates (a uniform subsample)
    selector: str = 'iwe'  # 'iwe', 'fps' or 'random' (random picks max_keypoints)
    replan_slots: int = 0  # pruning environments replanned per Floyd-Warshall pass; 0: 8 on CPU, 256 elsewhere
    seed: int = 0

    def __post_init__(self):
        for name in ('episodes', 'envs', 'max_keypoints', 'candidates'):
            if int(getattr(self, name)) < 1:
                raise ValueError(f'{name} must be >= 1; got {getattr(self, name)}')
        if self.steps < 0 or self.replan_slots < 0:
            raise ValueError(f'steps and replan_slots must be >= 0 (0: the default); got {self.steps}, '
                             f'{self.replan_slots}')
        if not (self.delta > 0 and self.tau >= 0 and self.switch_radius > 0 and self.kappa >= 0):
            raise ValueError('delta and switch_radius must be > 0, tau and kappa >= 0')
        if self.selector not in graphs.SELECTORS:
            raise ValueError(f'unknown selector {self.selector!r}; expected one of {", ".join(graphs.SELECTORS)}')
        agent_specs(self)  # validates the ablation names

    @property
    def edge_radius(self) -> float:
        return self.tau if self.tau > 0 else 2.0 * self.delta

    def agent_config(self) -> rollout.AgentConfig:
        slots = self.replan_slots or (8 if jax.default_backend() == 'cpu' else 256)
        return rollout.AgentConfig(kappa=self.kappa, switch_radius=self.switch_radius, tau=self.edge_radius,
                                   replan_slots=slots)


def agent_specs(cfg: EvalConfig) -> list[tuple[str, float, bool]]:
    """``[(name, kappa, use_graph)]``: the AQM agent first, then the ablations."""
    out = [('aqm', float(cfg.kappa), True)]
    for a in cfg.ablations:
        if a == NO_PRUNING:
            out.append((a, math.inf, True))
        elif a == FLAT:
            out.append((a, math.inf, False))
        elif isinstance(a, str) and a.startswith('kappa='):
            try:
                k = float(a.split('=', 1)[1])
            except ValueError:
                raise ValueError(f'ablation {a!r}: kappa must be a number') from None
            if not k >= 0:
                raise ValueError(f'ablation {a!r}: kappa must be >= 0')
            out.append((a, k, True))
        else:
            raise ValueError(f'unknown ablation {a!r}; expected {NO_PRUNING!r}, {FLAT!r} or kappa=X')
    names = [n for n, _, _ in out]
    if len(set(names)) != len(names):
        raise ValueError(f'ablations repeat an agent: {names}')
    return out


# ------------------------------------------------------------------------------- the learned agent
class Agent(NamedTuple):
    """What the rollout needs from a model: pure functions of ``aux`` and ``aux`` itself."""

    encode: Callable  # (aux, obs [D]) -> latent [L]
    dist: Callable  # (aux, latent, latent) -> scalar
    controller: Callable  # (aux, obs [D], subgoal_obs [D], t, key) -> action [A]
    aux: Any


def learner_agent(learner, aux: Any = None) -> Agent:
    """The learner's IQE as the quasimetric and its main (Q-SAW) policy's mean as the controller;
    ``aux`` is ``{'q': q_params, 'pi': pi_params}`` (or None when it is passed at call time)."""
    iqe = learner.quasimetric

    def encode(aux, obs):
        return iqe.apply(aux['q'], obs, method=IQE.encode)

    def dist(aux, x, y):
        return iqe.apply(aux['q'], x, y, method=IQE.distance)

    def controller(aux, obs, sub, t, key):
        del t, key  # deterministic: the Gaussian's mean
        return learner.act(aux['pi'], obs, sub)

    return Agent(encode, dist, controller, aux)


def learned_agent(trained) -> Agent:
    """:func:`learner_agent` with a trained model's parameters (from :func:`aqm_mjx.train.load`)."""
    return learner_agent(trained.learner, {'q': trained.state.q_params, 'pi': trained.state.pi_params})


def oracle_agent(env, grid=None, delta: float = 4.0, speed: float = 0.12) -> tuple[Agent, graphs.Graph, dict]:
    """An agent without learning, for checking the planner, the pruning and the protocol.

    The quasimetric is the exact BFS maze distance of ``grid`` (default: the maze's layout) as a
    time-to-reach at ``speed`` m per control step, the keypoints are IWE's at ``delta`` m
    (:func:`aqm_mjx.rollout.maze_graph`), and the controller steers along ``grid``'s BFS toward the
    current target: the scripted trot for the ant, a unit displacement for the point. On any other
    layout both the map and the controller are out of date, as a learned agent's would be.

    Returns:
        (agent, graph, ``EvalConfig`` keywords that match it: ``switch_radius`` 1.5 m and ``tau`` 2
        ``delta``, in steps, and ``kappa`` 0.25: its distance is exact, so the slack can be small).
    """
    from aqm_mjx import expert  # pylint: disable=import-outside-toplevel

    grid = np.asarray(env.layout if grid is None else grid)
    aux, graph = rollout.maze_graph(grid, delta=delta, speed=speed, obs_size=env.obs_size)
    aux['bfs'] = jnp.asarray(expert.bfs_next_cell(grid))

    def controller(aux, o, g, t, key):
        del key
        cmd = expert.waypoint_command(o[:2], g[:2], aux['bfs'], grid.shape)
        if env.agent == 'ant':
            return expert.gait_action(o[:15], o[15:], cmd, t)
        return cmd / (jnp.linalg.norm(cmd) + 1e-6)

    agent = Agent(rollout.maze_encode, rollout.maze_dist, controller, aux)
    return agent, graph, dict(switch_radius=1.5 / speed, tau=2 * delta / speed, kappa=0.25)


def build_map(agent: Agent, observations: jax.Array, cfg: EvalConfig, key: jax.Array,
              aux: Any = None) -> tuple[graphs.Graph, Any]:
    """Keypoints and graph from dataset states (pure and jittable; ``aux`` defaults to the agent's).

    Args:
        observations: ``[N, D]`` dataset states; ``min(N, cfg.candidates)`` of them, drawn uniformly
            without replacement, are encoded as candidates.
    Returns:
        (:class:`aqm_mjx.graph.Graph`, :class:`aqm_mjx.keypoints.Keypoints` with indices into the
        candidates).
    """
    aux = agent.aux if aux is None else aux
    k_sub, k_sel = jax.random.split(key)
    n = observations.shape[0]
    m = min(n, int(cfg.candidates))
    idx = jax.random.permutation(k_sub, n)[:m] if m < n else jnp.arange(n)
    cand = observations[idx]
    lat = jax.vmap(lambda o: agent.encode(aux, o))(cand)
    d = lambda x, y: agent.dist(aux, x, y)  # noqa: E731
    return graphs.keypoint_graph(d, lat, cand, k_sel, cfg.delta, cfg.max_keypoints, cfg.edge_radius, cfg.selector)


def map_for_evaluation(agent: Agent, observations, cfg: EvalConfig, key: jax.Array) -> tuple[graphs.Graph, dict]:
    """:func:`build_map` jitted, then trimmed to the keypoint count rounded up to 8 (host side).

    What ``aqm-mjx evaluate`` and the notebooks do before :func:`evaluate`: the rollout program's
    cost grows with K, so the padded ``cfg.max_keypoints`` slots are cut to the ones used.

    Returns:
        (trimmed graph, ``{'keypoints': count, 'overflow': bool, 'seconds': float}``).
    """
    import time  # pylint: disable=import-outside-toplevel

    t0 = time.perf_counter()
    graph, kp = jax.jit(lambda aux, o, k: build_map(agent, o, cfg, k, aux))(agent.aux, jnp.asarray(observations), key)
    n_kp = int(kp.count)
    graph = graphs.trim(graph, min(cfg.max_keypoints, -(-n_kp // 8) * 8))
    return graph, dict(keypoints=n_kp, overflow=bool(kp.overflow), seconds=time.perf_counter() - t0)


# ------------------------------------------------------------------------------ the episode table
class Table(NamedTuple):
    """One row per episode (numpy, host side)."""

    agent: np.ndarray  # int [E] index into the agent specs
    variant: np.ndarray  # int [E] index into the variants
    task: np.ndarray  # int32 [E] task id (1-based)
    episode: np.ndarray  # int [E] episode number within (variant, task)
    seed_id: np.ndarray  # int32 [E] key id: the same for every agent on one (variant, task, episode)
    kappa: np.ndarray  # float32 [E]
    use_graph: np.ndarray  # bool [E]


def episode_table(specs, n_variants: int, task_ids, episodes: int) -> Table:
    a, v, t, e = np.meshgrid(np.arange(len(specs)), np.arange(n_variants), np.asarray(task_ids), np.arange(episodes),
                             indexing='ij')
    a, v, t, e = (x.reshape(-1) for x in (a, v, t, e))
    n_tasks = len(task_ids)
    task_pos = np.searchsorted(np.sort(task_ids), t) if n_tasks else t
    seed_id = ((v * n_tasks + task_pos) * episodes + e).astype(np.int32)
    kappa = np.array([specs[i][1] for i in a], np.float32)
    use = np.array([specs[i][2] for i in a], bool)
    return Table(a, v, t.astype(np.int32), e, seed_id, kappa, use)


class Episodes(NamedTuple):
    """Everything the episode table of an evaluation depends on (host side)."""

    variants: dict  # {name: grid [H, W]}
    grids: np.ndarray  # int8 [V, H, W], validated
    task_ids: list  # sorted task ids
    specs: list  # agent_specs(cfg)
    table: Table
    steps: int  # control steps per episode


def plan_episodes(env, cfg: EvalConfig, variants: Optional[dict] = None) -> Episodes:
    """Validate the layouts and task ids of an evaluation and lay out its episode table."""
    variants = {'base': env.layout} if variants is None else dict(variants)
    grids = np.stack([mazes.validate_grid(g, env.maze) for g in variants.values()])
    task_ids = sorted(cfg.tasks) if cfg.tasks else [t.task_id for t in mazes.tasks(env.maze)]
    valid_ids = {t.task_id for t in mazes.tasks(env.maze)}
    bad = [t for t in task_ids if t not in valid_ids]
    if bad:
        raise ValueError(f'task ids {bad} do not exist in maze {env.maze!r} (it has {sorted(valid_ids)})')
    specs = agent_specs(cfg)
    table = episode_table(specs, len(grids), task_ids, cfg.episodes)
    return Episodes(variants, grids, task_ids, specs, table, int(cfg.steps or env.max_episode_steps))


def episode_keys(key: jax.Array, seed_id) -> jax.Array:
    """``[E, 2, 2]`` (reset, action) keys: episode keys depend only on ``seed_id``, not on the
    chunking or the number of devices."""
    return jax.vmap(lambda i: jax.random.split(jax.random.fold_in(key, i), 2))(jnp.asarray(seed_id, jnp.int32))


# -------------------------------------------------------------------------------------- sharding
def device_mesh(devices=None) -> Mesh:
    """A 1-D mesh named ``'env'`` over ``devices`` (all of them, on every host, by default)."""
    devices = jax.devices() if devices is None else list(devices)
    return Mesh(np.array(devices), ('env',))


def _put(x, sharding):
    """A global array from one host array that every process holds (single- and multi-host)."""
    x = np.asarray(x)
    return jax.make_array_from_callback(x.shape, sharding, lambda index: x[index])


def _fetch(x) -> np.ndarray:
    if jax.process_count() > 1:
        from jax.experimental import multihost_utils  # pylint: disable=import-outside-toplevel

        return np.asarray(multihost_utils.process_allgather(x, tiled=True))
    return np.asarray(jax.device_get(x))


# ------------------------------------------------------------------------------------ evaluation
class Results(NamedTuple):
    """Per-episode outcomes and the summary tables."""

    agents: list  # agent names
    variants: list  # variant names
    tasks: list  # task ids
    table: Table
    success: np.ndarray  # bool [E]
    pruned: np.ndarray  # int32 [E]
    summary: dict  # {agent: {variant: {'task_1': rate, ..., 'mean': rate, 'pruned_mean': x}}}
    traces: dict  # {(agent, variant, task): {'xy': [T, 2], 'node': [T], 'cuts': [C, 2], 'goal_xy': [2]}}
    timing: dict


def format_summary(rates, agents, variants, tasks, pruned=None) -> dict:
    """``rates [agents, variants, tasks]`` (and optional mean prunes ``[agents, variants]``) ->
    ``{agent: {variant: {'task_T': rate, ..., 'mean': rate(, 'pruned_mean': x)}}}``."""
    rates = np.asarray(rates)
    out = {}
    for ai, a in enumerate(agents):
        out[a] = {}
        for vi, v in enumerate(variants):
            row = {f'task_{t}': float(rates[ai, vi, ti]) for ti, t in enumerate(tasks)}
            row['mean'] = float(rates[ai, vi].mean())
            if pruned is not None:
                row['pruned_mean'] = float(pruned[ai, vi])
            out[a][v] = row
    return out


def summarise(table: Table, success, pruned, agents, variants, tasks) -> dict:
    """Per-episode outcomes -> :func:`format_summary` (success rates per task, mean prunes)."""
    rates = np.zeros((len(agents), len(variants), len(tasks)))
    prunes = np.zeros((len(agents), len(variants)))
    for ai in range(len(agents)):
        for vi in range(len(variants)):
            sel = (table.agent == ai) & (table.variant == vi)
            prunes[ai, vi] = pruned[sel].mean()
            for ti, t in enumerate(tasks):
                rates[ai, vi, ti] = success[sel & (table.task == t)].mean()
    return format_summary(rates, agents, variants, tasks, prunes)


def make_program(env, agent: Agent, cfg: EvalConfig, steps: int, mesh: Optional[Mesh] = None):
    """The jitted evaluation of one chunk: ``(aux, graph, keys, task_ids, grids, kappa, use_graph)
    -> dict`` of :func:`aqm_mjx.rollout.make_evaluate`, with the environment axis sharded over
    ``mesh`` (inputs replicated: ``aux``, ``graph``; sharded: the rest)."""
    run = rollout.make_evaluate(env, agent.encode, agent.dist, agent.controller, cfg.agent_config(), steps)
    if mesh is None:
        return jax.jit(run)
    rep, shard = NamedSharding(mesh, PartitionSpec()), NamedSharding(mesh, PartitionSpec('env'))
    out = dict(success=shard, pruned=shard, cuts=shard, xy=NamedSharding(mesh, PartitionSpec(None, 'env')),
               node=NamedSharding(mesh, PartitionSpec(None, 'env')), goal_xy=shard)
    return jax.jit(run, in_shardings=(rep, rep, shard, shard, shard, shard, shard), out_shardings=out)


def evaluate(env, agent: Agent, graph: graphs.Graph, cfg: EvalConfig, variants: Optional[dict] = None,
             mesh: Optional[Mesh] = None, progress: bool = True, program=None,
             key: Optional[jax.Array] = None) -> Results:
    """Run the protocol: every agent x variant x task x episode, in chunks of ``cfg.envs``.

    Args:
        env: a :class:`aqm_mjx.envs.MazeEnv`.
        agent: from :func:`learned_agent` (or any :class:`Agent`).
        graph: from :func:`build_map`.
        variants: ``{name: grid [H, W]}``; default ``{'base': the maze's layout}``.
        mesh: devices to shard the environments over (default: all devices).
        program: a compiled chunk from :func:`make_program` to reuse (its ``steps`` and ``mesh``).
        key: base of the episode keys (default ``PRNGKey(cfg.seed)``).
    """
    import time  # pylint: disable=import-outside-toplevel

    variants, grids, task_ids, specs, table, steps = plan_episodes(env, cfg, variants)
    mesh = device_mesh() if mesh is None else mesh
    n_dev = mesh.devices.size
    chunk = min(int(cfg.envs), len(table.task))
    chunk = -(-chunk // n_dev) * n_dev  # a multiple of the device count
    program = make_program(env, agent, cfg, steps, mesh) if program is None else program
    key = jax.random.PRNGKey(cfg.seed) if key is None else key
    keys = np.asarray(episode_keys(key, table.seed_id))
    rep = NamedSharding(mesh, PartitionSpec())
    aux, graph = jax.device_put((agent.aux, graph), rep)
    shard = NamedSharding(mesh, PartitionSpec('env'))
    n = len(table.task)
    n_chunks = -(-n // chunk)
    success, pruned = np.zeros(n, bool), np.zeros(n, np.int32)
    first = {}  # (agent, variant, task) -> row of its first episode, whose trajectory is kept
    for r in range(n):
        first.setdefault((table.agent[r], table.variant[r], table.task[r]), r)
    keep = {r: k for k, r in first.items()}
    traces, timing = {}, {'chunks': n_chunks, 'envs_per_chunk': chunk, 'devices': int(n_dev), 'steps': steps}
    bar = None
    if progress:
        from tqdm.auto import tqdm  # pylint: disable=import-outside-toplevel

        bar = tqdm(total=n, desc=f'evaluate {env.name}', unit='ep')
    t0 = time.perf_counter()
    for c in range(n_chunks):
        rows = np.arange(c * chunk, (c + 1) * chunk)
        real = rows < n
        rows = np.where(real, rows, 0)  # padding repeats row 0; its results are dropped
        inputs = (keys[rows], table.task[rows], grids[table.variant[rows]], table.kappa[rows], table.use_graph[rows])
        inputs = tuple(_put(x, shard) for x in inputs)
        t_c = time.perf_counter()
        out = program(aux, graph, *inputs)
        success_c, pruned_c = _fetch(out['success']) > 0, _fetch(out['pruned'])
        timing.setdefault('first_chunk_s', time.perf_counter() - t_c)
        success[rows[real]] = success_c[real]
        pruned[rows[real]] = pruned_c[real]
        wanted = [(i, rows[i]) for i in np.flatnonzero(real) if rows[i] in keep]
        if wanted:
            xy, node, cuts, goal = (_fetch(out[k]) for k in ('xy', 'node', 'cuts', 'goal_xy'))
            for i, r in wanted:
                a, v, t = keep[r]
                traces[(specs[a][0], list(variants)[v], int(t))] = dict(
                    xy=xy[:, i], node=node[:, i], cuts=cuts[i][cuts[i, :, 0] >= 0], goal_xy=goal[i],
                    success=bool(success_c[i]), pruned=int(pruned_c[i]))
        if bar is not None:
            bar.update(int(real.sum()))
    if bar is not None:
        bar.close()
    timing['total_s'] = time.perf_counter() - t0
    timing['env_steps_per_s_after_first_chunk'] = (
        (n_chunks - 1) * chunk * steps / (timing['total_s'] - timing['first_chunk_s']) if n_chunks > 1 else None)
    agents, names = [s[0] for s in specs], list(variants)
    summary = summarise(table, success, pruned, agents, names, task_ids)
    return Results(agents, names, task_ids, table, success, pruned, summary, traces, timing)


# ----------------------------------------------------------------------------------- command line
def print_summary(res: Results) -> None:
    cols = [f'task_{t}' for t in res.tasks] + ['mean', 'pruned_mean']
    width = max(len(a) for a in res.agents) + max(len(v) for v in res.variants) + 3
    print(f'{"agent / layout":<{width}}' + ''.join(f'{c.replace("_mean", ""):>9}' for c in cols))
    for a in res.agents:
        for v in res.variants:
            row = res.summary[a][v]
            cells = [f'{100 * row[c]:8.0f}%' for c in cols[:-1]] + [f'{row["pruned_mean"]:9.2f}']
            print(f'{a + " / " + v:<{width}}' + ''.join(cells))


def run_cli(checkpoint: str, cfg: EvalConfig, dataset: Optional[str] = None, shift: str = 'base',
            out: Optional[str] = None, map_key: Optional[jax.Array] = None,
            eval_key: Optional[jax.Array] = None, data: Optional[dict] = None) -> tuple[Results, dict]:
    """``aqm-mjx evaluate``: load, map, evaluate, write ``results.json`` and the pictures.

    ``map_key`` and ``eval_key`` default to ``PRNGKey(cfg.seed)``. ``data``: the arrays of
    ``dataset`` when the caller has already read them. Returns the results and the report written
    to ``results.json``.
    """
    import json  # pylint: disable=import-outside-toplevel
    import os  # pylint: disable=import-outside-toplevel

    from aqm_mjx import dataset as ds_io  # pylint: disable=import-outside-toplevel
    from aqm_mjx import envs, plots, train  # pylint: disable=import-outside-toplevel
    from aqm_mjx.envs import shifts  # pylint: disable=import-outside-toplevel

    trained = train.load(checkpoint)
    env_name = trained.config.env
    if env_name is None:
        raise ValueError(f'{checkpoint} does not record its environment (config.env); it cannot be evaluated')
    env = envs.make(env_name)
    variants = shifts.suite(env.maze) if shift == 'all' else {shift: shifts.variant(env.maze, shift)}
    path = dataset or trained.meta.get('dataset')
    if not path or not os.path.exists(path):
        raise FileNotFoundError(f'keypoints are selected from dataset states: {path!r} not found; pass --dataset')
    if data is None:
        data = ds_io.read_ogbench(path, obs_size=env.obs_size, action_size=env.action_size, add_info=False)
    out = out or os.path.join(checkpoint, 'eval')
    os.makedirs(out, exist_ok=True)
    agent = learned_agent(trained)
    graph, info = map_for_evaluation(agent, data['observations'], cfg,
                                     jax.random.PRNGKey(cfg.seed) if map_key is None else map_key)
    n_kp, t_map = info['keypoints'], info['seconds']
    if info['overflow']:
        print(f'warning: {cfg.max_keypoints} keypoints did not cover the candidates at delta {cfg.delta}; '
              'raise --max-keypoints or --delta')
    print(f'{env_name}, {trained.config.preset} preset at step {trained.step}: {n_kp} keypoints at delta {cfg.delta} '
          f'({t_map:.1f} s); {len(agent_specs(cfg))} agents x {len(variants)} layouts x '
          f'{len(cfg.tasks) or env.num_tasks} tasks x {cfg.episodes} episodes on {jax.device_count()} device(s)')
    res = evaluate(env, agent, graph, cfg, variants, key=eval_key)
    print_summary(res)
    mask = np.asarray(graph.mask)
    nodes_xy = np.asarray(graph.obs)[:, :2]
    edges = graphs.edge_list(graph.w, mask)
    report = dict(env=env_name, checkpoint=os.path.abspath(checkpoint), step=trained.step,
                  train_preset=trained.config.preset, dataset=os.path.abspath(path), keypoints=n_kp,
                  keypoint_overflow=info['overflow'], edges=int(len(edges)), map_s=round(t_map, 2),
                  config=dataclasses.asdict(cfg), agents=res.agents, variants=res.variants, tasks=res.tasks,
                  summary=res.summary, timing=res.timing, backend=jax.default_backend(),
                  device=str(jax.devices()[0]), device_count=jax.device_count())
    with open(os.path.join(out, 'results.json'), 'w') as f:
        json.dump(report, f, indent=1)
    first = res.variants[0]
    plots.success_bars(res.summary, first, res.tasks, os.path.join(out, 'success.png'),
                       title=f'{env_name} ({first}): success per task, {cfg.episodes} episodes each')
    plots.trajectory_panels(env.layout, variants, res.traces, nodes_xy, edges, 'aqm', res.tasks[0],
                            os.path.join(out, 'trajectories.png'))
    if len(variants) > 1:
        vals = np.array([[res.summary[a][v]['mean'] for v in res.variants] for a in res.agents])
        name = os.path.basename(os.path.normpath(checkpoint))
        plots.heatmap([f'{name}: {a}' for a in res.agents], res.variants, vals, os.path.join(out, 'heatmap.png'),
                      title=f'{env_name}: trained on base, evaluated on each layout (mean success)')
    print(f'wrote {out}/results.json and pictures')
    return res, report
