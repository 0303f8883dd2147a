"""The protocol run in chunks of ``envs`` environments, sharded over every JAX device.

    res = evaluate(env, agent, graph, AgentConfig(), ProtocolConfig(episodes=50), variants=shifts.suite('medium'))
    res.summary['aqm']['close-3-3']['task_1']

The episode table (:mod:`.protocol`) is cut into chunks of ``envs`` environments, one jitted call
each, padded to a static size (a progress bar counts episodes). The environment axis is sharded
over the process's devices (``jax.sharding``, a 1-D mesh named ``env``; parameters and graph
replicated). With several processes (:mod:`aqm_mjx.processes`) process ``p`` runs chunks ``p, p + N,
...`` on its own devices with the program one process runs, and the outcomes are gathered on every
process: the same episodes as one process at the same chunk size, bit for bit, the ant's included (a
mesh over every process's devices, given as ``mesh``, shards each chunk instead; the ant's contact
physics, partitioned so, rounds differently and its trajectories part: RESULTS.md section 7.7).
Episode keys depend on the episode alone, so the point maze's results do not depend on the chunk
size or the number of devices (tested).
"""

from __future__ import annotations

import dataclasses
import math
import time
from typing import Callable, NamedTuple, Optional

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from aqm_mjx import envs as envs_lib
from aqm_mjx import processes
from aqm_mjx.processes import fetch_global, put_global, replicate
from aqm_mjx.agent.rollout import make_host_rollout, make_rollout
from aqm_mjx.agent.rules import LEG_FIELDS, MAX_LEGS, AgentConfig
from aqm_mjx.evaluation import calibration
from aqm_mjx.evaluation import protocol as proto
from aqm_mjx.interface import Agent
from aqm_mjx.mapping.graph import Graph
from aqm_mjx.progress import BAR_FORMAT, ChunkBar, Hook


def device_mesh(devices=None) -> Mesh:
    """A 1-D mesh named ``'env'`` over ``devices`` (by default this process's: every device when it runs
    alone; with several processes, :func:`evaluate` runs each process's share of the chunks on its own
    devices). ``device_mesh(jax.devices())`` spans every process's devices."""
    devices = jax.local_devices() if devices is None else list(devices)
    return Mesh(np.array(devices), ('env',))


class Results(NamedTuple):
    """Per-episode outcomes and the summary tables."""

    agents: list  # agent names
    variants: list  # layout names
    tasks: list  # task ids
    table: proto.Table
    success: np.ndarray  # bool [E]
    pruned: np.ndarray  # int32 [E]
    summary: dict  # {agent: {layout: {'task_1': rate, ..., 'mean': rate, 'pruned_mean': x}}}
    traces: dict  # {(agent, layout, task): {'xy': [T, 2], 'node': [T], 'cuts': [C, 2], 'goal_xy': [2], ...}}
    timing: dict
    legs: np.ndarray  # float32 [E, MAX_LEGS, LEG_FIELDS] completed legs (d, steps, longest stall, kind), -1 padded
    n_legs: np.ndarray  # int32 [E] legs completed (the first MAX_LEGS are in ``legs``)
    removed: np.ndarray  # int32 [E] keypoint edges cut (``pruned`` counts overruns)


HOOK = Hook()  # the host callback compiled into every evaluation program; evaluate() points it at its bar


class HostProgram:
    """The evaluation of one chunk in OGBench's own environments (``backend='ogbench'``):
    :func:`aqm_mjx.agent.rollout.make_host_rollout` over an
    :class:`~aqm_mjx.envs.ogbench_env.OGBenchEnvs` kept across chunks (and across the checkpoints
    that share this program); ``close()`` ends its worker processes."""

    def __init__(self, env, agent: Agent, cfg: AgentConfig, steps: int, workers: int = 0):
        from aqm_mjx.envs.ogbench_env import OGBenchEnvs  # pylint: disable=import-outside-toplevel

        self.envs = OGBenchEnvs(env.name, max_episode_steps=steps, workers=workers)
        self.run = make_host_rollout(self.envs, agent, cfg, steps, progress=HOOK)

    def __call__(self, aux, graph, inputs) -> dict:
        return self.run(aux, graph, inputs)

    def close(self) -> None:
        self.envs.close()


def chunking(n: int, envs: int, n_dev: int = 1) -> tuple:
    """How :func:`evaluate` cuts ``n`` episodes at ``envs`` environments per chunk over ``n_dev``
    devices: (environments per chunk, number of chunks). A chunk holds at most ``n`` and ``envs``
    environments, rounded up to a multiple of the device count."""
    chunk = -(-min(int(envs), int(n)) // n_dev) * n_dev
    return chunk, -(-int(n) // chunk)


def make_program(env, agent: Agent, cfg: AgentConfig, steps: int, mesh: Optional[Mesh] = None,
                 backend: str = 'mjx', workers: int = 0, physics: Optional[str] = None):
    """The evaluation of one chunk: ``(aux, graph, inputs) -> dict`` of
    :func:`aqm_mjx.agent.rollout.make_rollout`. ``backend='mjx'``: one jitted program, the
    environment axis sharded over ``mesh`` (``aux`` and ``graph`` replicated); ``'ogbench'``: a
    :class:`HostProgram` (OGBench's environments on the host, ``workers`` processes). Either reports
    its steps to :data:`HOOK` every :data:`aqm_mjx.progress.EVERY` control steps, so the bar moves
    during a chunk. ``physics``: the MJX physics preset (:mod:`aqm_mjx.envs.physics`; None: ``env``'s own)."""
    if backend == 'ogbench':
        return HostProgram(env, agent, cfg, steps, workers)
    if backend != 'mjx':
        raise ValueError(f"unknown backend {backend!r}; expected 'mjx' or 'ogbench'")
    if physics is not None:
        env = envs_lib.with_physics(env, physics)
    run = make_rollout(env, agent, cfg, steps, progress=HOOK)
    if mesh is None:
        return jax.jit(run)
    rep, shard = NamedSharding(mesh, PartitionSpec()), NamedSharding(mesh, PartitionSpec('env'))
    time_env = NamedSharding(mesh, PartitionSpec(None, 'env'))
    out = dict(success=shard, pruned=shard, removed=shard, cuts=shard, legs=shard, n_legs=shard, xy=time_env,
               node=time_env, goal_xy=shard)
    return jax.jit(run, in_shardings=(rep, rep, shard), out_shardings=out)


def evaluate(env, agent: Agent, graph: Graph, cfg: AgentConfig, protocol: proto.ProtocolConfig,
             variants: Optional[dict] = None, key: Optional[jax.Array] = None, mesh: Optional[Mesh] = None,
             progress: bool = True, program=None, budgets: Optional[dict] = None,
             episodes: Optional[proto.Episodes] = None, label: str = 'evaluate') -> Results:
    """Run the protocol: every agent x layout x task x episode, in chunks of ``protocol.envs``.

    Args:
        env: a :class:`aqm_mjx.envs.MazeEnv`.
        agent: any :class:`~aqm_mjx.interface.Agent` with its parameters bound.
        graph: from :func:`aqm_mjx.mapping.build.build_map` (or trimmed); None for an agent that
            does not plan (then only its flat row is run).
        cfg: the agent's rules (its ``kappa``, ``patience`` and ``cut_slack`` are the AQM row's).
        variants: ``{name: grid [H, W]}``; default ``{'base': the maze's layout}``.
        key: the evaluation key (default ``PRNGKey(0)``); the episodes are its ``protocol.split``'s.
        mesh: devices to shard the environments over (default: all devices).
        program: a compiled chunk from :func:`make_program` to reuse (its ``steps``, ``mesh`` and
            backend); by default one is made for ``protocol.backend`` (and closed at the end).
        budgets: ``{kind: (kappa, patience)}`` of the rows that take a calibrated budget (e.g.
            ``'paper=cal'``), from :func:`calibration_pass`.
        episodes: an episode table to run instead of the protocol's (the calibration pass's).
        label: what the progress bar says this pass is (``'calibration pass'`` for that pass).
    """
    eps = episodes if episodes is not None else proto.plan_episodes(
        env, protocol, cfg.kappa, variants, plans=agent.plans, patience=cfg.patience, cut_slack=cfg.cut_slack,
        own_rule=agent.rule is not None)
    table = eps.table
    # several processes: each runs every N-th chunk on its own devices, with the program one process runs,
    # and the outcomes are gathered: the same episodes as one process at the same chunk size, bit for bit
    mesh = device_mesh() if mesh is None else mesh
    spread = jax.process_count() > 1 and all(d.process_index == jax.process_index() for d in mesh.devices.flat)
    n_dev = mesh.devices.size
    envs = int(protocol.envs)
    if envs == 0 and protocol.backend == 'mjx':  # chosen from the memory estimate
        from aqm_mjx import memory  # pylint: disable=import-outside-toplevel

        envs = memory.fitting_envs(envs_lib.with_physics(env, protocol.physics_preset)) * n_dev
    chunk, n_chunks = chunking(len(table.task), envs or len(table.task), n_dev)
    owned = program is None
    if owned:
        program = make_program(env, agent, cfg, eps.steps, mesh, protocol.backend, protocol.workers,
                               protocol.physics_preset)
    key = jax.random.PRNGKey(0) if key is None else key
    rep, shard = NamedSharding(mesh, PartitionSpec()), NamedSharding(mesh, PartitionSpec('env'))
    aux, graph = replicate((agent.aux, graph), rep)
    n = len(table.task)
    success, pruned, removed = np.zeros(n, bool), np.zeros(n, np.int32), np.zeros(n, np.int32)
    legs, n_legs = np.full((n, MAX_LEGS, LEG_FIELDS), -1.0, np.float32), np.zeros(n, np.int32)
    first = {}  # (agent, layout, task) -> row of its first episode, whose trajectory is kept
    for r in range(n):
        first.setdefault((table.agent[r], table.variant[r], table.task[r]), r)
    keep = {r: k for k, r in first.items()}
    mine = processes.share(n_chunks) if spread else range(n_chunks)
    fetch = (lambda x: np.asarray(jax.device_get(x))) if spread else fetch_global
    kept = {}  # row -> its trace's arrays (gathered from every process when spread)
    traces, timing = {}, {'chunks': n_chunks, 'envs_per_chunk': chunk, 'devices': int(n_dev), 'steps': eps.steps}
    bar = None
    if progress:
        from tqdm.auto import tqdm  # pylint: disable=import-outside-toplevel

        bar = tqdm(total=min(n, len(mine) * chunk) if spread else n, desc=f'{label} {env.name}', unit='ep',
                   bar_format=BAR_FORMAT)
    ticks = ChunkBar(bar)
    HOOK.target = ticks
    t0 = time.perf_counter()
    try:
        for c in mine:
            rows = np.arange(c * chunk, (c + 1) * chunk)
            real = rows < n
            rows = np.where(real, rows, 0)  # padding repeats row 0; its results are dropped
            inputs = jax.tree.map(lambda x: put_global(x, shard), proto.table_inputs(eps, key, rows, budgets))
            t_c = time.perf_counter()
            ticks.start(int(real.sum()), eps.steps)
            out = program(aux, graph, inputs)
            success_c, pruned_c = fetch(out['success']) > 0, fetch(out['pruned'])
            ticks.finish()
            timing.setdefault('first_chunk_s', time.perf_counter() - t_c)
            success[rows[real]] = success_c[real]
            pruned[rows[real]] = pruned_c[real]
            removed[rows[real]] = fetch(out['removed'])[real]
            legs[rows[real]], n_legs[rows[real]] = fetch(out['legs'])[real], fetch(out['n_legs'])[real]
            wanted = [(i, rows[i]) for i in np.flatnonzero(real) if rows[i] in keep]
            if wanted:
                xy, node, cuts, goal = (fetch(out[k]) for k in ('xy', 'node', 'cuts', 'goal_xy'))
                for i, r in wanted:
                    kept[r] = dict(xy=xy[:, i], node=node[:, i], cuts=cuts[i], goal_xy=goal[i])
        if spread:
            success, pruned, removed, legs, n_legs, kept = _gathered(
                (success, pruned, removed, legs, n_legs), kept, sorted(keep), chunk,
                jax.eval_shape(program, aux, graph, jax.tree.map(lambda x: put_global(x, shard), proto.table_inputs(
                    eps, key, np.arange(chunk) % n, budgets))))
        for r, tr in kept.items():
            a, v, t = keep[r]
            traces[(eps.specs[a][0], list(eps.variants)[v], int(t))] = dict(
                xy=tr['xy'], node=tr['node'], cuts=tr['cuts'][tr['cuts'][:, 0] >= 0], goal_xy=tr['goal_xy'],
                success=bool(success[r]), pruned=int(pruned[r]))
    finally:
        HOOK.target = None  # a later program (or a failed chunk) never drives this bar
        if owned and hasattr(program, 'close'):
            program.close()
    if bar is not None:
        bar.close()
    timing['total_s'] = time.perf_counter() - t0
    timing['backend'] = 'ogbench' if isinstance(program, HostProgram) else 'mjx'
    timing['physics'] = ('ogbench (OGBench\'s environments)' if timing['backend'] == 'ogbench'
                         else envs_lib.physics_presets.describe(protocol.physics_preset))
    timing['progress_callbacks'] = ticks.calls
    timing['env_steps_per_s_after_first_chunk'] = (
        (n_chunks - 1) * chunk * eps.steps / (timing['total_s'] - timing['first_chunk_s']) if n_chunks > 1 else None)
    timing['env_steps_per_s_all_chunks'] = steps_per_s(timing)
    rates, prunes = jax.device_get(proto.success_rates(eps, success, pruned))
    names = list(eps.variants)
    summary = proto.format_summary(rates, eps.agents, names, eps.task_ids, prunes)
    return Results(eps.agents, names, eps.task_ids, table, success, pruned, summary, traces, timing, legs, n_legs,
                   removed)


def _gathered(rows: tuple, kept: dict, keep_rows: list, chunk: int, shapes) -> tuple:
    """Several processes, each holding the outcomes of its chunks (row ``r`` ran on process
    ``(r // chunk) mod N``): every per-episode array (``rows``, each ``[E, ...]``) and the kept traces
    (``{row: {'xy', 'node', 'cuts', 'goal_xy'}}`` of ``keep_rows``) as if one process had run them all,
    on every process. ``shapes``: the chunk program's output shapes and dtypes."""
    count = jax.process_count()
    n = len(rows[0])
    owner = (np.arange(n) // chunk) % count

    def pick(x, who, at):  # x [processes, len(at), ...] -> each row from its owner
        return x[who, np.arange(len(at))]

    got = processes.gather(rows, 'gathering the episodes\' outcomes')
    out = [pick(x, owner, np.arange(n)) for x in got]
    if not keep_rows:
        return (*out, {})
    k = len(keep_rows)  # each trace as the program gives one episode's: xy [T, 2], node [T], cuts [C, 2], goal [2]
    over_time = lambda name: shapes[name].shape[:1] + shapes[name].shape[2:]  # noqa: E731  ([T, B, ...] -> [T, ...])
    one = dict(xy=over_time('xy'), node=over_time('node'), cuts=shapes['cuts'].shape[1:],
               goal_xy=shapes['goal_xy'].shape[1:])
    mine = {name: np.zeros((k,) + dims, shapes[name].dtype) for name, dims in one.items()}
    for j, r in enumerate(keep_rows):
        for name, arr in kept.get(r, {}).items():
            mine[name][j] = arr
    allk = processes.gather(mine, 'gathering the drawn episodes')
    who = owner[np.asarray(keep_rows)]
    traces = {name: pick(x, who, keep_rows) for name, x in allk.items()}
    return (*out, {r: {name: traces[name][j] for name in traces} for j, r in enumerate(keep_rows)})


def steps_per_s(timing: dict) -> float:
    """Control steps/s over a whole evaluation (:func:`evaluate`'s ``timing``), the first, compiling
    chunk included: every chunk's environments x the episode's steps over the wall time. MJX's
    program runs every step; OGBench's loop ends a chunk early when all its episodes have ended, and
    then this overstates the steps run."""
    return timing['chunks'] * timing['envs_per_chunk'] * timing['steps'] / timing['total_s']


def calibration_pass(env, agent: Agent, graph: Graph, cfg: AgentConfig, protocol: proto.ProtocolConfig,
                     key: jax.Array, layout=None, mesh: Optional[Mesh] = None, progress: bool = True,
                     program=None) -> dict:
    """The budget calibration that ``protocol.calibrate`` (or a calibrated row such as
    ``'paper=cal'``) asks for before an evaluation.

    The agent without pruning on ``layout`` (default the maze's: the training layout),
    ``protocol.calibration_episodes`` episodes between start and goal cells that no evaluation task
    uses (:func:`~aqm_mjx.evaluation.protocol.calibration_episodes`), on ``fold_in(key,
    CALIBRATION_FOLD)`` (``key``: the evaluation's, whose episodes these are not); its completed
    legs give the budgets at ``protocol.false_alarm``
    (:func:`~aqm_mjx.evaluation.calibration.calibrate`, then
    :func:`~aqm_mjx.evaluation.calibration.budget` and :func:`~aqm_mjx.evaluation.calibration.row_budgets`).

    Returns:
        ``{'rule', 'false_alarm', 'stall_scale', 'episodes', 'legs', 'edges', 'calibrated', 'kappa', 'patience',
        'kappa_edges', 'budgets', 'ratio_q', 'stall_q'}``: ``kappa`` and ``patience`` are the AQM
        row's under ``protocol.calibrate`` (``cfg``'s when it is 'none' or ``calibrated`` is False: no
        leg was completed); ``kappa_edges`` the paper's rule's; ``budgets`` ``{kind: (kappa,
        patience)}`` for :func:`evaluate`; ``ratio_q`` and ``stall_q`` the quantiles
        :data:`~aqm_mjx.evaluation.calibration.QUANTILES` of steps / d and of the longest stall;
        plain Python values.
    Raises:
        ValueError: nothing asks for a calibration, or the agent has no quasimetric (no budgets).
    """
    rule = protocol.calibrate
    if not proto.needs_calibration(protocol) or not agent.prunes:
        raise ValueError('calibration_pass: nothing to calibrate ' + (
            "(protocol.calibrate is 'none' and no row is calibrated)" if agent.prunes
            else '(the agent runs no budgets: no quasimetric, or a rule of its own)'))
    eps = proto.calibration_episodes(env, protocol, layout)
    res = evaluate(env, agent, graph, dataclasses.replace(cfg, kappa=math.inf, patience=0.0),
                   proto.calibration_protocol(protocol), key=jax.random.fold_in(key, proto.CALIBRATION_FOLD),
                   mesh=mesh, progress=progress, program=program, episodes=eps, label='calibration pass')
    c = calibration.calibrate(res.legs, protocol.false_alarm, stall_scale=protocol.stall_scale)
    kappa, patience = calibration.budget(c, rule, cfg.kappa, cfg.patience)
    budgets = {k: (float(a), float(b)) for k, (a, b) in calibration.row_budgets(c, cfg.kappa, cfg.patience).items()}
    return dict(rule=rule, false_alarm=protocol.false_alarm, stall_scale=protocol.stall_scale,
                episodes=len(res.table.task), legs=int(c['legs']), edges=int(c['edges']),
                calibrated=bool(int(c['legs']) > 0), kappa=float(kappa), patience=float(patience),
                kappa_edges=budgets['paper'][0], budgets=budgets,
                ratio_q=np.asarray(c['ratio_q']).tolist(), stall_q=np.asarray(c['stall_q']).tolist())


def calibrate_then_evaluate(env, agent: Agent, graph: Graph, cfg: AgentConfig, protocol: proto.ProtocolConfig,
                            variants: Optional[dict], key: jax.Array, layout=None, program=None,
                            mesh: Optional[Mesh] = None, progress: bool = True,
                            on_calibrated: Optional[Callable] = None) -> tuple[Results, Optional[dict]]:
    """The protocol as every host path runs it: the :func:`calibration_pass` first where the protocol
    asks for one (an agent that plans; ``layout``: the training layout), its budgets then given to
    the AQM row (``kappa``, ``patience``) and to the calibrated rows (``budgets``) of
    :func:`evaluate` on ``variants``, on the same compiled ``program``. ``on_calibrated(cal)`` is
    called between the two (a log line). Returns ``(Results, calibration dict or None)``; the one
    program (:func:`aqm_mjx.pipeline.make_run`) does the same inside its jitted run."""
    cal, budgets = None, None
    if agent.prunes and proto.needs_calibration(protocol):
        cal = calibration_pass(env, agent, graph, cfg, protocol, key, layout=layout, mesh=mesh, progress=progress,
                               program=program)
        cfg, budgets = dataclasses.replace(cfg, kappa=cal['kappa'], patience=cal['patience']), cal['budgets']
        if on_calibrated is not None:
            on_calibrated(cal)
    res = evaluate(env, agent, graph, cfg, protocol, variants, key=key, mesh=mesh, progress=progress,
                   program=program, budgets=budgets)
    return res, cal
