"""The whole AQM run as one pure function: train -> select keypoints -> graph -> evaluate.

    run = make_run(RunConfig(train=TrainConfig.preset('tiny'), eval=EvalConfig(episodes=2)), env)
    out = jax.jit(run)(key, dataset)                               # one compiled program
    outs = jax.jit(jax.vmap(run, in_axes=(0, None)))(keys, dataset)  # several seeds, the dataset shared

Each stage is the same function the step-by-step path (``aqm-mjx run``: ``train.train`` with its
checkpoints, then ``evaluate.build_map`` and ``evaluate.evaluate``) calls; :func:`stage_keys` splits
one key the same way for both, so the two paths give the same results for the same key.
Nothing in ``run`` leaves the device and no Python control flow depends on data: training is a
``lax.scan`` over chunks of ``updates_per_call`` updates, IWE a ``while_loop`` with a static maximum
K and a mask, the evaluation the episode table of :mod:`aqm_mjx.evaluate` as one batch.
"""

from __future__ import annotations

import dataclasses
from typing import Callable, Optional

import jax
import jax.numpy as jnp
import numpy as np

from aqm_mjx import dataset as ds_io
from aqm_mjx import evaluate as ev
from aqm_mjx import envs, rollout, train


@dataclasses.dataclass(frozen=True)
class RunConfig:
    """A whole experiment: how to train and how to evaluate (saved as JSON with its results)."""

    train: train.TrainConfig = dataclasses.field(default_factory=train.TrainConfig)
    eval: ev.EvalConfig = dataclasses.field(default_factory=ev.EvalConfig)

    def to_dict(self) -> dict:
        return dict(train=self.train.to_dict(), eval=dataclasses.asdict(self.eval))

    @classmethod
    def from_dict(cls, d: dict) -> 'RunConfig':
        e = {k: tuple(v) if isinstance(v, list) else v for k, v in d['eval'].items()}
        return cls(train=train.TrainConfig.from_dict(d['train']), eval=ev.EvalConfig(**e))


def stage_keys(key: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
    """(train, map, evaluation) keys of a run; both paths split the run key this way."""
    k_train, k_map, k_eval = jax.random.split(key, 3)
    return k_train, k_map, k_eval


def train_stage(learner: train.Learner, key: jax.Array, ds: ds_io.Dataset,
                progress: Optional[Callable] = None) -> tuple[train.TrainState, dict]:
    """``learner.init(key)`` then ``steps`` updates (``lax.scan`` over chunks of ``updates_per_call``).

    ``progress(step)``, if given, is called from the device through ``jax.debug.callback`` after
    each chunk (a host function captured at trace time: it never causes a recompile).
    Returns the final state and each metric's mean over the last chunk.
    """
    cfg = learner.config

    def chunk(state, _):
        state, m = jax.lax.scan(lambda st, __: learner.update(st, ds), state, None, length=cfg.updates_per_call)
        if progress is not None:
            jax.debug.callback(progress, state.step)
        return state, jax.tree.map(jnp.mean, m)

    state, metrics = jax.lax.scan(chunk, learner.init(key), None, length=cfg.steps // cfg.updates_per_call)
    return state, jax.tree.map(lambda x: x[-1], metrics)


def make_run(cfg: RunConfig, env, variants: Optional[dict] = None, progress: Optional[Callable] = None):
    """Build ``run(key, dataset) -> dict`` for ``env`` (a :class:`aqm_mjx.envs.MazeEnv`).

    Args:
        variants: ``{name: grid}`` layouts to evaluate on (default: the maze's layout).
        progress: optional host callback ``progress(step)`` during training.
    Returns:
        ``run(key [2], dataset: Dataset) -> dict`` with ``success [agents, layouts, tasks]`` (rates),
        ``episode_success [E]`` and ``pruned [E]`` in the order of ``run.table``, ``keypoints``
        (count), ``overflow``, ``metrics`` (last chunk's means) and ``params`` (``{'q', 'pi'}``).
        ``run.table``, ``run.agents``, ``run.variants``, ``run.tasks`` describe the episodes.
    """
    tcfg, ecfg = cfg.train, cfg.eval
    learner = train.make_learner(tcfg, env.obs_size, env.action_size)
    agent = ev.learner_agent(learner)  # parameters come from training, inside run
    variants, grids, task_ids, specs, table, steps = ev.plan_episodes(env, ecfg, variants)
    program = rollout.make_evaluate(env, agent.encode, agent.dist, agent.controller, ecfg.agent_config(), steps)
    group = ((table.agent * len(grids) + table.variant) * len(task_ids)
             + np.searchsorted(np.asarray(task_ids), table.task)).astype(np.int32)
    n_groups = len(specs) * len(grids) * len(task_ids)

    def run(key, ds: ds_io.Dataset) -> dict:
        k_train, k_map, k_eval = stage_keys(key)
        # TRAIN
        state, metrics = train_stage(learner, k_train, ds, progress)
        aux = {'q': state.q_params, 'pi': state.pi_params}
        # MAP: keypoints and graph from dataset states
        graph, kp = ev.build_map(agent, ds.observations, ecfg, k_map, aux)
        # EVALUATE: every agent x layout x task x episode in one batch
        keys = ev.episode_keys(k_eval, table.seed_id)
        out = program(aux, graph, keys, jnp.asarray(table.task), jnp.asarray(grids[table.variant], jnp.int8),
                      jnp.asarray(table.kappa), jnp.asarray(table.use_graph))
        success = out['success'] > 0
        rate = jax.ops.segment_sum(success.astype(jnp.float32), jnp.asarray(group), n_groups) / ecfg.episodes
        return dict(success=rate.reshape(len(specs), len(grids), len(task_ids)), episode_success=success,
                    pruned=out['pruned'], keypoints=kp.count, overflow=kp.overflow, metrics=metrics, params=aux)

    run.table, run.agents, run.variants, run.tasks = table, [s[0] for s in specs], list(variants), task_ids
    run.learner = learner
    return run


def shard_seeds(keys: jax.Array, mesh=None) -> jax.Array:
    """Place ``keys [S, 2]`` with the seed axis sharded over ``mesh`` (default: every device, the
    same 1-D ``'env'`` mesh as the evaluation batch); ``jax.jit(jax.vmap(run, in_axes=(0, None)))``
    then runs each device's seeds there, the dataset replicated. ``S`` must be a multiple of the
    number of devices."""
    from jax.sharding import NamedSharding, PartitionSpec  # pylint: disable=import-outside-toplevel

    mesh = ev.device_mesh() if mesh is None else mesh
    n = mesh.devices.size
    if keys.shape[0] % n:
        raise ValueError(f'{keys.shape[0]} seeds cannot be split evenly over {n} devices')
    return ev._put(np.asarray(keys), NamedSharding(mesh, PartitionSpec('env')))  # pylint: disable=protected-access


def summary(run, out: dict) -> dict:
    """``{agent: {layout: {'task_T': rate, 'mean': rate}}}`` from one seed's ``out`` (host side)."""
    return ev.format_summary(out['success'], run.agents, run.variants, run.tasks)


# ------------------------------------------------------------------------ the two paths, host side
def data_stage(env_name: str, out: str, dataset: Optional[str], episodes: int, batch: int, log=print,
               style: str = 'navigate') -> str:
    """The dataset file of a run: ``dataset`` if given, else ``OUT/data/ENV-STYLE.npz``, collected
    in MJX (``episodes`` + a tenth for validation) unless it is already there."""
    import os  # pylint: disable=import-outside-toplevel

    from aqm_mjx import collect  # pylint: disable=import-outside-toplevel

    if dataset:
        if not os.path.exists(dataset):
            raise FileNotFoundError(f'dataset {dataset!r} not found')
        return dataset
    path = os.path.join(out, 'data', f'{env_name}-{style}.npz')
    if os.path.exists(path):
        log(f'[1/4 data] found {path}, not collecting again')
        return path
    os.makedirs(os.path.dirname(path), exist_ok=True)
    ccfg = collect.CollectConfig(env=env_name, style=style, episodes=episodes, batch=batch).resolved()
    log(f'[1/4 data] collecting {ccfg.episodes} + {ccfg.val_episodes} {style} episodes x {ccfg.steps} states')
    res = collect.collect(ccfg)
    collect.write(res, path)
    collect.plot(res, path[:-4] + '.png')
    return path


def run_stepwise(cfg: RunConfig, env_name: str, out: str, dataset: Optional[str] = None, episodes: int = 100,
                 collect_batch: int = 64, seed: int = 0, shift: str = 'base', log=print) -> dict:
    """``aqm-mjx run``: data -> train (Orbax checkpoints, resumed when interrupted) -> map -> evaluate,
    one progress display per stage; writes ``OUT/summary.json`` and returns it."""
    import os  # pylint: disable=import-outside-toplevel
    import time  # pylint: disable=import-outside-toplevel

    from aqm_mjx import checkpoint as ckpt  # pylint: disable=import-outside-toplevel

    times = {}
    k_train, k_map, k_eval = stage_keys(jax.random.PRNGKey(seed))
    t0 = time.perf_counter()
    path = data_stage(env_name, out, dataset, episodes, collect_batch, log)
    times['data_s'] = time.perf_counter() - t0
    # TRAIN (resume when checkpoints exist; skip when the run is complete)
    tdir = os.path.join(out, 'train')
    done = []
    if os.path.isdir(os.path.join(tdir, 'checkpoints')):
        saver = ckpt.Checkpointer(tdir, keep=None, create=False)
        done = saver.steps()
        saver.close()
    env = envs.make(env_name)
    data = ds_io.read_ogbench(path, obs_size=env.obs_size, action_size=env.action_size, add_info=False)
    t0 = time.perf_counter()
    if done and max(done) >= cfg.train.steps:
        log(f'[2/4 train] {tdir} is complete at step {max(done)}')
    else:
        log(f'[2/4 train] {"resuming" if done else "training"} {cfg.train.preset} preset, {cfg.train.steps} updates')
        train.train(cfg.train, data, tdir, resume=bool(done), dataset_path=os.path.abspath(path), key=k_train, log=log)
    times['train_s'] = time.perf_counter() - t0
    # MAP + EVALUATE
    t0 = time.perf_counter()
    log('[3/4 map] and [4/4 evaluate]')
    res, report = ev.run_cli(tdir, cfg.eval, dataset=path, shift=shift, out=os.path.join(out, 'eval'),
                             map_key=k_map, eval_key=k_eval, data=data)
    times['map_and_evaluate_s'] = time.perf_counter() - t0
    summary_ = dict(env=env_name, seed=seed, config=cfg.to_dict(), dataset=os.path.abspath(path),
                    keypoints=report['keypoints'], success=res.summary,
                    times_s={k: round(v, 1) for k, v in times.items()},
                    pictures=[os.path.join(out, 'eval', p) for p in ('trajectories.png', 'success.png')])
    ckpt.write_json(os.path.join(out, 'summary.json'), summary_)
    aqm = res.summary['aqm'][res.variants[0]]
    log(f'AQM on {env_name} ({res.variants[0]}): {100 * aqm["mean"]:.0f}% mean success ('
        + ', '.join(f'task {t}: {100 * aqm[f"task_{t}"]:.0f}%' for t in res.tasks) + f'); {report["keypoints"]} keypoints; '
        + ', '.join(f'{k[:-2]} {v:.0f} s' for k, v in times.items()))
    log(f'wrote {out}/summary.json; map and trajectories: {out}/eval/trajectories.png')
    return summary_


def run_one_program(cfg: RunConfig, env_name: str, data: dict, seeds: int, seed: int = 0, log=print) -> dict:
    """``aqm-mjx run --one-program --seeds N``: the whole run for N seeds as one jitted, vmapped call
    (keys ``PRNGKey(seed + i)``, the same as ``run_stepwise`` with ``seed + i``)."""
    import time  # pylint: disable=import-outside-toplevel

    env = envs.make(env_name)
    ds = ds_io.to_device(data)
    total = seeds * cfg.train.steps

    def progress(step):  # called from the device with [seeds] steps (or a scalar for one seed)
        log(f'  train step {int(np.max(np.asarray(step)))} / {cfg.train.steps} ({seeds} seeds, {total} updates)')

    run = make_run(cfg, env, progress=progress)
    keys = jnp.stack([jax.random.PRNGKey(seed + i) for i in range(seeds)])
    if seeds % jax.device_count() == 0:
        keys = shard_seeds(keys)  # one device's share of the seeds on each device
    program = jax.jit(jax.vmap(run, in_axes=(0, None)))
    t0 = time.perf_counter()
    compiled = program.lower(keys, ds).compile()
    t_compile = time.perf_counter() - t0
    t0 = time.perf_counter()
    out = jax.device_get(compiled(keys, ds))
    t_run = time.perf_counter() - t0
    per_seed = [summary(run, jax.tree.map(lambda x: x[i], out)) for i in range(seeds)]
    for i, s in enumerate(per_seed):
        log(f'seed {seed + i}: AQM mean success {100 * s["aqm"][run.variants[0]]["mean"]:.0f}%, '
            f'{int(out["keypoints"][i])} keypoints')
    log(f'one program, {seeds} seeds: compile {t_compile:.1f} s, run {t_run:.1f} s')
    return dict(env=env_name, seeds=[seed + i for i in range(seeds)], config=cfg.to_dict(), success=per_seed,
                keypoints=[int(k) for k in out['keypoints']], compile_s=round(t_compile, 2), run_s=round(t_run, 2))
