"""The host side of a run: the data stage, then training with checkpoints, the map and the
evaluation, step by step with progress and resume (:func:`run_stepwise`), and the same stages as one
jitted program (:func:`run_one_program`). The trained state goes from training to the map and the
evaluation (:func:`aqm_mjx.assess.map_and_evaluate`, as for a saved checkpoint) in memory; keys come
from :func:`aqm_mjx.pipeline.stage_keys` on every path.
"""

from __future__ import annotations

import contextlib
import os
import time
from typing import Optional

import jax
import jax.numpy as jnp
import numpy as np

from aqm_mjx import envs, files, memory, processes
from aqm_mjx.assess import learning_curve, map_and_evaluate, read_data, variants_for
from aqm_mjx.data import collect
from aqm_mjx.data import dataset as ds_io
from aqm_mjx.envs import shifts
from aqm_mjx.evaluation.protocol import plan_episodes
from aqm_mjx.learn import fit, methods
from aqm_mjx.pipeline import RunConfig, make_run, stage_keys, summary
from aqm_mjx.processes import put_global


# ------------------------------------------------------------------------------------------- data
def data_stage(env_name: str, out: str, dataset: Optional[str], episodes: int, batch: int, log=print,
               style: str = 'navigate', layout: str = 'base', physics: str = 'mjx',
               physics_preset: str = 'ogbench') -> str:
    """The dataset file of a run: ``dataset`` if given, else ``OUT/data/ENV-STYLE.npz`` (on a shifted
    ``layout``: ``OUT/data/ENV-STYLE-LAYOUT.npz``), collected in ``physics`` (``'mjx'``, or ``'mujoco'``
    on the host; ``episodes`` + a tenth for validation) with the settings of ``physics_preset``
    (:mod:`aqm_mjx.envs.physics`) unless it is already there.

    Several processes (every one calling this at the same point): process 0 decides whether the file
    is there, every process collects its share of the chunks (:func:`aqm_mjx.data.collect.collect`),
    process 0 writes the file and the others return once it is written (the run's folder is one
    folder that every process reads: a shared file system across hosts)."""
    if dataset:
        if not os.path.exists(dataset):
            raise FileNotFoundError(f'dataset {dataset!r} not found')
        return dataset
    ccfg = collect.CollectConfig(env=env_name, style=style, episodes=episodes, batch=batch, layout=layout,
                                 physics=physics, physics_preset=physics_preset).resolved()
    name = f'{env_name}-{style}' + ('' if layout == shifts.BASE else f'-{layout}')
    path = os.path.join(out, 'data', f'{name}.npz')
    writer = processes.writer()
    if bool(processes.from_writer(np.asarray(os.path.exists(path)), f'whether {path} exists')):
        log(f'[1/4 data] found {path}, not collecting again')
        return path
    if writer:
        os.makedirs(os.path.dirname(path), exist_ok=True)
        collect.check_output(path, cfg=ccfg)  # room for it, before minutes of collection
    where = '' if layout == shifts.BASE else f' on layout {layout}'
    log(f'[1/4 data] collecting {ccfg.episodes} + {ccfg.val_episodes} {style} episodes x {ccfg.steps} states{where} '
        + ('in MJX' if physics == 'mjx' else 'in MuJoCo on the host') + f', physics {physics_preset}'
        + (f', over {processes.count()} processes' if processes.count() > 1 else ''))
    res = collect.collect(ccfg)
    if writer:
        collect.write(res, path)
        collect.plot(res, path[:-4] + '.png')
    processes.barrier(f'{path} written')
    return path


# ------------------------------------------------------------------------------------- the run
def run_stepwise(cfg: RunConfig, out: str, dataset: Optional[str] = None, collect_episodes: int = 100,
                 collect_batch: int = 55, shift: str = 'base', log=print, collect_physics: str = 'mjx',
                 collect_preset: str = 'ogbench') -> dict:
    """``aqm-mjx run``: data -> train (Orbax checkpoints; resumed when interrupted, skipped when
    complete) -> map -> evaluate, one progress display per stage. The run key is
    ``PRNGKey(cfg.train.seed)``. Writes ``OUT/run.json`` (the config), ``OUT/summary.json`` and
    returns the summary.

    Several processes (:mod:`aqm_mjx.processes`, every process running this with the same
    arguments): process 0 holds the folder's lock, collects the data (the others then read the file)
    and writes every file; training is one data-parallel run (:func:`aqm_mjx.learn.fit.train`), without
    the learning curve; the evaluation runs each process's share of the episodes in MJX."""
    several, writer = jax.process_count() > 1, processes.writer()
    if several:
        processes.check_backend(cfg.protocol.backend)
    env_name = cfg.train.env
    env = envs.make(env_name)
    variants = variants_for(env.maze, shift)  # a bad --shift or task id fails here, not after training
    plan_episodes(env, cfg.protocol, cfg.agent.kappa, variants)
    memory.check_training(methods.get(cfg.method), cfg.train, env.obs_size, env.action_size)
    t0 = time.perf_counter()
    given = read_data(dataset, env) if dataset else None  # a damaged file is named before anything is written
    with files.run_lock(out) if writer else contextlib.nullcontext():  # one writer per run folder
        # a folder trained with other settings is refused here, before run.json or data change
        fit.check_resumable(os.path.join(out, 'train'), cfg.method, cfg.train, env.obs_size, env.action_size)
        processes.barrier('run: request checked')  # every process read the folder before it changes
        if writer:
            files.write_json(os.path.join(out, 'run.json'), cfg.to_dict(), makedirs=True)
        times = {}
        seed = cfg.train.seed
        k_train, k_map, k_eval = stage_keys(jax.random.PRNGKey(seed))

        path = data_stage(env_name, out, dataset, collect_episodes, collect_batch, log, physics=collect_physics,
                          physics_preset=collect_preset)
        data = given if given is not None else read_data(path, env)
        times['data_s'] = time.perf_counter() - t0
        # TRAIN (resumed when checkpoints exist; skipped when the run is complete)
        tdir = os.path.join(out, 'train')
        t0 = time.perf_counter()
        done = fit.checkpoint_steps(tdir)
        log('[2/4 train] ' + (f'{tdir} is complete at step {max(done)}' if done and max(done) >= cfg.train.steps else
                               f'{"resuming" if done else "training"} {cfg.method} {cfg.train.preset} preset, '
                               f'{cfg.train.steps} updates'))
        trained = fit.train(cfg.method, cfg.train, data, tdir, resume='auto', dataset_path=os.path.abspath(path),
                            key=k_train, log=log, curve=None if several else learning_curve(env, data, cfg, k_eval))
        times['train_s'] = time.perf_counter() - t0
        # MAP + EVALUATE, with the trained state in memory
        t0 = time.perf_counter()
        log('[3/4 map] and [4/4 evaluate]')
        info = dict(checkpoint=os.path.abspath(tdir), dataset=os.path.abspath(path), seed=seed)
        res, rep = map_and_evaluate(trained, env, data, cfg, variants, k_map, k_eval,
                                    os.path.join(out, 'eval'), info, log)
        times['map_and_evaluate_s'] = time.perf_counter() - t0
        summary_ = dict(env=env_name, seed=seed, config=cfg.to_dict(), dataset=os.path.abspath(path),
                        keypoints=rep['keypoints'], success=res.summary,
                        times_s={k: round(v, 1) for k, v in times.items()},
                        pictures=[os.path.join(out, 'eval', p) for p in ('trajectories.png', 'success.png')]
                        + [p for p in [os.path.join(tdir, 'curves.png')] if os.path.exists(p)],
                        provenance=files.provenance())
        if writer:
            files.write_json(os.path.join(out, 'summary.json'), summary_)
        head = res.agents[0]  # 'aqm', or 'flat' for a method without a quasimetric
        row = res.summary[head][res.variants[0]]
        log(f'{cfg.method} ({head}) on {env_name} ({res.variants[0]}): {100 * row["mean"]:.0f}% mean success ('
            + ', '.join(f'task {t}: {100 * row[f"task_{t}"]:.0f}%' for t in res.tasks) + f'); {rep["keypoints"]} '
            'keypoints; ' + ', '.join(f'{k[:-2]} {v:.0f} s' for k, v in times.items()))
        if writer:
            log(f'wrote {out}/summary.json; map and trajectories: {out}/eval/trajectories.png')
        if cfg.train.preset == 'ci':
            log(f'note: the ci preset checks the wiring ({cfg.train.steps} updates, {cfg.protocol.episodes} episodes '
                'per task): its success rates say nothing about the method; --preset cpu is the smallest that does')
        return summary_


def shard_seeds(keys: jax.Array, mesh=None) -> jax.Array:
    """Place ``keys [S, 2]`` with the seed axis sharded over ``mesh`` (default: every device, the
    same 1-D ``'env'`` mesh as the evaluation batch); ``jax.jit(jax.vmap(run, in_axes=(0, None)))``
    then runs each device's seeds there, the dataset replicated. ``S`` must be a multiple of the
    number of devices."""
    from jax.sharding import NamedSharding, PartitionSpec  # pylint: disable=import-outside-toplevel

    mesh = device_mesh() if mesh is None else mesh
    n = mesh.devices.size
    if keys.shape[0] % n:
        raise ValueError(f'{keys.shape[0]} seeds cannot be split evenly over {n} devices')
    return put_global(np.asarray(keys), NamedSharding(mesh, PartitionSpec('env')))


def run_one_program(cfg: RunConfig, data: dict, seeds: int, log=print) -> dict:
    """``aqm-mjx run --one-program --seeds N``: the whole run for N seeds as one jitted, vmapped call
    (keys ``PRNGKey(seed + i)`` with ``seed = cfg.train.seed``, the same as ``run_stepwise`` with
    that seed)."""
    env = envs.make(cfg.train.env)
    ds = ds_io.to_device(data)
    seed = cfg.train.seed
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
    first = list(run.episodes.variants)[0]
    for i, s in enumerate(per_seed):
        head = run.episodes.agents[0]
        cal = out.get('calibration')
        budget = '' if cal is None else (f', calibrated patience {float(cal["patience"][i]):g}'
                                         if cfg.protocol.calibrate == 'stall' else
                                         f', calibrated kappa {float(cal["kappa"][i]):g}')
        log(f'seed {seed + i}: {cfg.method} ({head}) mean success {100 * s[head][first]["mean"]:.0f}%, '
            f'{int(out["keypoints"][i])} keypoints{budget}')
    log(f'one program, {seeds} seeds: compile {t_compile:.1f} s, run {t_run:.1f} s')
    return dict(env=env.name, seeds=[seed + i for i in range(seeds)], config=cfg.to_dict(), success=per_seed,
                keypoints=[int(k) for k in out['keypoints']], compile_s=round(t_compile, 2), run_s=round(t_run, 2))


def demo_run(out: str, steps: int = 200, seed: int = 0) -> tuple[str, str]:
    """A tiny trained point-maze model for notebooks and smoke tests (seconds on a CPU).

    Writes ``OUT/pointmaze-medium-navigate.npz`` (:func:`aqm_mjx.data.synthetic.point_walks`, 200
    walks of 100 states) and trains the ``ci`` preset for ``steps`` updates into ``OUT/train``. The
    walks ignore walls, so the model shows the wiring, not a skill. Returns (run folder, dataset path).
    """
    from aqm_mjx.data import synthetic  # pylint: disable=import-outside-toplevel
    from aqm_mjx.learn import methods  # pylint: disable=import-outside-toplevel

    os.makedirs(out, exist_ok=True)
    data = synthetic.point_walks(n_traj=200, t_len=100, seed=seed)
    path = os.path.join(out, 'pointmaze-medium-navigate.npz')
    np.savez(path, **data)
    run = os.path.join(out, 'train')
    cfg = methods.get('aqm').preset('ci', env='pointmaze-medium', steps=steps, seed=seed)
    fit.train('aqm', cfg, data, run, dataset_path=path, progress=False, log=lambda *_: None)
    return run, path
