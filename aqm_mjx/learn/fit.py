"""Training: the one chunk scan, the whole training as a pure scan, and the host loop around it
(progress bar, JSON-lines metrics, Orbax checkpoints, resume, skip when complete).

    trained = fit.train('aqm', cfg, data, 'runs/medium/train', resume='auto')
    trained.agent                                 # the Agent with the final parameters

A run folder holds ``config.json`` (method name, config, shapes, dataset path), ``metrics.jsonl``
and ``checkpoints/<step>/``; :func:`aqm_mjx.learn.folder.load` rebuilds a trained method from it alone.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import json
import math
import os
import time
from typing import Any, Callable, NamedTuple, Optional, Union

import jax
import jax.numpy as jnp
import numpy as np

from aqm_mjx import files, processes
from aqm_mjx.data import dataset as ds_io
from aqm_mjx.learn import checkpoint as ckpt
from aqm_mjx.learn import methods
from aqm_mjx.learn.folder import (Trained, check_against_checkpoint, check_resumable,  # noqa: F401 (load: re-exported)
                                  check_same_data, checkpoint_steps, fingerprint, load, meta_of, read_meta, trim_metrics)
from aqm_mjx.learn.learner import Learner

class Curve(NamedTuple):
    """A training run's learning curve, evaluated at every checkpoint (built by a later stage, e.g.
    :func:`aqm_mjx.assess.learning_curve`, so that training imports no evaluation).

    ``point(trained) -> {metric: float}``: the metrics of the method at that checkpoint (e.g.
    ``eval/success``, ``eval/episodes``), appended to the run's ``metrics.jsonl`` as a line of their
    own; ``draw(folders)``: called after each point with the run folders (one per seed), e.g. to
    redraw ``curves.png``."""

    point: Callable[[Trained], dict]
    draw: Optional[Callable[[list], None]] = None


# ------------------------------------------------------------------------------------ pure parts
def chunk_step(update: Callable, length: int) -> Callable:
    """``(state, ds) -> (state, metrics)``: ``length`` updates under ``lax.scan``, each metric
    averaged over them. The host loop jits it; :func:`train_scan` scans it."""

    def run(state, ds):
        state, metrics = jax.lax.scan(lambda st, _: update(st, ds), state, None, length=length)
        return state, jax.tree.map(jnp.mean, metrics)

    return run


def seeds_chunk(update: Callable, length: int) -> Callable:
    """:func:`chunk_step` over ``S`` seeds' stacked states, vmapped with the update index shared.

    Every seed of one program is at the same step (they start from a common checkpoint and update
    in lockstep), so the step goes in unbatched (seed 0's): a branch on it, as GAS's phase, stays one
    ``lax.cond`` instead of vmap's select over both branches (both computed on every update). The
    states come back stacked, the step with them."""
    inner = chunk_step(update, length)
    run = jax.vmap(lambda state, ds, step: inner(state.replace(step=step), ds), in_axes=(0, None, None))
    return lambda state, ds: run(state, ds, state.step[0])


def train_scan(learner: Learner, key: jax.Array, ds: ds_io.Dataset, progress: Optional[Callable] = None):
    """``learner.init(key)``, then the whole run as a ``lax.scan`` over its chunks (pure, jittable).

    ``progress(step)``, if given, is called from the device through ``jax.debug.callback`` after
    each chunk (a host function captured at trace time: it never causes a recompile).
    Returns the final state and each metric's mean over the last chunk.
    """
    cfg = learner.config
    chunk = chunk_step(learner.update, cfg.updates_per_call)

    def body(state, _):
        state, m = chunk(state, ds)
        if progress is not None:
            jax.debug.callback(progress, state.step)
        return state, m

    state, metrics = jax.lax.scan(body, learner.init(key), None, length=cfg.chunks)
    return state, jax.tree.map(lambda x: x[-1], metrics)


# ------------------------------------------------------------------------------------- host loop
def train(method: Union[str, methods.Method], cfg: Any, data: dict, out: str, resume: Union[bool, str] = False,
          steps: Optional[int] = None, dataset_path: Optional[str] = None, progress: bool = True, log=print,
          key: Optional[jax.Array] = None, curve: Optional[Curve] = None) -> Trained:
    """Train, resume or skip a run in folder ``out``: the one place that decides which.

    Args:
        method: a registry name or entry.
        cfg: the run's config (on resume the saved one is used; ``steps`` may extend it).
        data: raw arrays from :func:`aqm_mjx.data.dataset.read_ogbench` or a collector.
        out: run folder (``config.json``, ``metrics.jsonl``, ``checkpoints/``).
        resume: False: a new run (refused when ``out`` holds checkpoints); True: continue from the
            newest readable checkpoint (from the start, with the saved config, when a run was stopped
            before its first one); ``'auto'``: continue when there are checkpoints, else start.
            A run already at its last step is restored and returned without training.
        steps: override the total number of updates.
        key: the initialisation key (default ``PRNGKey(cfg.seed)``; the pipeline passes its train
            key so that both paths of a run start alike). Ignored on resume.
        curve: evaluated at every checkpoint written (:class:`Curve`); None: no learning curve.
    Returns:
        :class:`Trained` with the final state.

    Several processes (:mod:`aqm_mjx.processes`; every process calls this with the same arguments):
    one run, data-parallel. The state and the dataset are replicated on a mesh over every process's
    devices, each update's batch is split over its axis ``'batch'`` (:func:`aqm_mjx.data.goals.spread`;
    ``batch_size`` a multiple of the device count) and XLA sums the gradients across processes, so
    every process holds the same state. Process 0 alone holds the folder's lock and writes its files
    (config, metric lines, checkpoints); on resume it restores the checkpoint and sends the state to
    the others. The numbers are one process's up to float reassociation (the sums run in another
    order). A process that ends makes the others end at the next update with one line.
    """
    # one writer per run folder; with several processes, process 0 (the others only read it)
    with files.run_lock(out) if processes.writer() else contextlib.nullcontext():
        return _train(method, cfg, data, out, resume, steps, dataset_path, progress, log, key, curve)


def _curve_points(curve: Optional[Curve], method, cfgs: list, learner, metas: list) -> Optional[Callable]:
    """``(step, i, state_i) -> metrics`` of seed ``i`` for :func:`_host_loop` (None without a curve)."""
    if curve is None:
        return None
    return lambda step, i, state: curve.point(Trained(method.name, cfgs[i], learner, state, step, metas[i]))


def _train(method, cfg, data, out, resume, steps, dataset_path, progress, log, key, curve) -> Trained:
    method = methods.get(method) if isinstance(method, str) else method
    ds = ds_io.to_device(data)  # validates, and refuses a dataset without transitions
    obs_size, action_size = ds.observations.shape[1], ds.actions.shape[1]
    data_sha = fingerprint(data)
    cfg_path = os.path.join(out, 'config.json')
    metrics_path = os.path.join(out, 'metrics.jsonl')
    saved_meta = None
    done = checkpoint_steps(out)
    if resume == 'auto':
        resume = bool(done)
    if resume and not done:  # killed before its first checkpoint: start over with the saved settings
        if cfg is None:
            if not os.path.exists(cfg_path):
                raise FileNotFoundError(f'{out} holds no run to resume (no config.json, no checkpoint); start a '
                                        'new run without --resume')
            method, cfg, _ = read_meta(out)
        log(f'{out} has no checkpoint yet: starting from the beginning')
        resume = False
    if resume:
        if cfg is not None:  # a caller with a config of its own (aqm-mjx run): the saved run's, steps aside
            check_resumable(out, method.name, cfg, obs_size, action_size)
            steps = cfg.steps if steps is None else steps
        method, cfg, meta = read_meta(out)
        saver = ckpt.Checkpointer(out, keep=None, create=False)
        try:
            check_against_checkpoint(out, meta, saver)
        finally:
            saver.close()
        if (meta['obs_size'], meta['action_size']) != (obs_size, action_size):
            raise ValueError(f'{out} was trained on {meta["obs_size"]}-d observations and {meta["action_size"]}-d '
                             f'actions; this dataset has {obs_size} and {action_size}')
        check_same_data(out, meta, data_sha, dataset_path)
        saved_meta = meta
    elif done:
        raise FileExistsError(f'{out} already holds checkpoints; pass --resume to continue it or choose a new --out')
    if cfg is None:
        raise ValueError('a config is needed for a new run')
    if steps is not None:
        cfg = dataclasses.replace(cfg, steps=int(steps))
    learner = method.make(cfg, obs_size, action_size)
    if saved_meta is not None:  # a resumed run keeps the record of the data it was trained on
        dataset_path, data_sha = saved_meta.get('dataset') or dataset_path, saved_meta.get('data_sha256') or data_sha
    meta = meta_of(method.name, cfg, obs_size, action_size, dataset_path, data_sha)
    state = learner.init(jax.random.PRNGKey(cfg.seed) if key is None else key)
    spread, writes = jax.process_count() > 1, processes.writer()  # several processes: process 0 writes
    if spread:
        _check_batch(cfg.batch_size)
    saver = None
    if resume:
        if writes:
            saver = ckpt.Checkpointer(out, keep=cfg.keep)
            _, state, _ = saver.restore(state, log=log, set_aside=True)
        if spread:  # the writer's restored state, on every process
            state = jax.tree.map(jnp.asarray, processes.from_writer(state, f'the state of {out}'))
        at = int(state.step)
        log(f'resumed {out} at step {at}' if at < cfg.steps else f'{out} is complete at step {at}')
    start = int(state.step)
    if start % cfg.updates_per_call:
        raise ValueError(f'checkpoint step {start} is not a multiple of updates_per_call {cfg.updates_per_call}')
    if writes:
        _check_room([out], state, cfg, start)  # before anything is written to the folder
        saver = saver or ckpt.Checkpointer(out, keep=cfg.keep)
        trim_metrics(metrics_path, start)  # a fresh start drops what a killed run left
        files.write_json(cfg_path, meta)
    step_fn = chunk_step(learner.update, cfg.updates_per_call)
    if spread:
        chunk, state, ds = _data_parallel(step_fn, state, ds)
    else:
        chunk = jax.jit(step_fn, donate_argnums=0)
    save = _saving([saver], [meta], [set()], lambda x, i: x) if writes else (lambda step, state: None)
    try:
        state, step = _host_loop(chunk, state, ds, cfg, start, [out], save, None, f'train {method.name} {cfg.preset}',
                                 progress and writes, method.progress,
                                 _curve_points(curve, method, [cfg], learner, [meta]) if writes else None, curve,
                                 writes=writes)
    finally:
        if saver is not None:
            saver.close()
    if spread:  # this process's replica as ordinary arrays of its first device
        state = jax.tree.map(jnp.asarray, processes.local_copy(state))
    return Trained(method.name, cfg, learner, state, step, meta)


def _check_batch(batch_size: int) -> None:
    """Several processes split each batch over every device: refuse a batch that does not split."""
    n = jax.device_count()
    if batch_size % n:
        raise ValueError(f'batch_size {batch_size} does not split over the {n} devices of {jax.process_count()} '
                         f'processes: give a multiple of {n} (--set batch_size=N) or another number of processes')


def _data_parallel(step_fn: Callable, state, ds):
    """``(chunk, state, ds)`` of one run over every process's devices: the state and the dataset
    replicated on a 1-D mesh named ``'batch'``, each batch split over it (:func:`aqm_mjx.data.goals.spread`
    reads the mesh in context). ``chunk(state, ds)`` returns replicated arrays once they are computed,
    or ends with one line when a partner ended."""
    from jax.sharding import Mesh, NamedSharding, PartitionSpec  # pylint: disable=import-outside-toplevel

    mesh = Mesh(np.array(jax.devices()), ('batch',))
    rep = NamedSharding(mesh, PartitionSpec())
    state, ds = processes.replicate((state, ds), rep)
    jitted = jax.jit(step_fn, in_shardings=(rep, rep), out_shardings=rep, donate_argnums=0)

    def chunk(state, ds):
        try:
            with jax.set_mesh(mesh):
                return jax.block_until_ready(jitted(state, ds))
        except jax.errors.JaxRuntimeError as e:  # a partner ended mid-update (gloo: connection closed)
            if 'RESOURCE_EXHAUSTED' in str(e):  # out of memory: XLA's own message says what
                raise
            raise processes.lost('running the updates', e) from None

    return chunk, state, ds


class DivergedError(RuntimeError):
    """Training produced a non-finite loss or parameter; the message names it, the step and what to try."""


def _strict_json(line: dict) -> str:
    """One metrics line as strict JSON: a non-finite number is written as ``null``."""
    clean = {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in line.items()}
    return json.dumps(clean, allow_nan=False)


def _diverged(cfg, step: int, what: list[str], who: str, saved: list[int], start: int = 0) -> DivergedError:
    shown = ', '.join(what[:3]) + (f' and {len(what) - 3} more' if len(what) > 3 else '')
    lrs = [(f.name, getattr(cfg, f.name)) for f in dataclasses.fields(cfg) if f.name.startswith('lr')]
    hint = ', '.join(f'{n}={v:g}' for n, v in lrs)
    kept = (f'the newest checkpoint, step {max(saved)}, holds finite values (only finite states are saved)'
            if saved else 'no checkpoint was written')
    began = f'this run resumed from checkpoint {start}' if start else 'this run started from the beginning'
    return DivergedError(f'training diverged{who} in updates {step - cfg.updates_per_call + 1}-{step} ({began}): '
                         f'non-finite {shown}; stopped, {kept}. Try lower learning rates (now {hint}; --set NAME=VALUE) or '
                         f'look for extreme values in the dataset')


def _check_room(outs: list[str], state, cfg, start: int) -> None:
    """Room for the checkpoints still to come in each folder (``keep`` of them plus the one being
    written), before training starts rather than at its first save."""
    if start >= cfg.steps:
        return
    size = int(1.1 * sum(x.nbytes for x in jax.tree.leaves(state))) + 2 ** 17  # Orbax's metadata: ~100 KiB each
    for o in outs:
        files.check_writable(o, size * (cfg.keep + 1), f'{cfg.keep} checkpoints of {size / 2 ** 20:.2f} MiB')


def _append(f, line: str) -> None:
    """Append one line to a metrics file opened unbuffered (``'ab', buffering=0``: nothing is left to
    flush at close); a failed write is cut off again (no torn line)."""
    pos = f.tell()
    try:
        data = line.encode()
        while data:
            data = data[f.write(data):]
    except OSError as e:
        try:
            f.truncate(pos)
        except OSError:
            pass
        raise files.OutputError(f'cannot append to {f.name}: {e.strerror or e}') from None


def _saving(savers: list, metas: list[dict], skip: list[set], pick: Callable) -> Callable:
    """``save(step, state)``: each saver's checkpoint of its seed (``pick(state, i)``), except the steps
    in ``skip[i]`` (already on disk)."""
    def save(step, state):
        for i, (saver, done) in enumerate(zip(savers, skip)):
            if step not in done:
                saver.save(step, jax.tree.map(lambda x, i=i: pick(x, i), state), metas[i])
    return save


def _host_loop(chunk: Callable, state, ds, cfg, start: int, outs: list[str], save: Callable,
               seeds: Optional[int], desc: str, progress: bool, shown: dict,
               points: Optional[Callable] = None, curve: Optional[Curve] = None, writes: bool = True):
    """The host side of training, shared by :func:`train` (``seeds=None``: one unvmapped state) and
    :func:`train_seeds` (``seeds=S``: every leaf stacked on a leading axis, one folder per seed).

    Each chunk: run it, check every metric and every floating leaf of the state for finiteness
    (on the first non-finite value: write that chunk's metric line, stop with :class:`DivergedError`;
    no checkpoint of a non-finite state is ever written), append strict-JSON metric lines every
    ``log_every`` updates, move the bar, ``save(step, state)`` every ``checkpoint_every`` updates
    (:func:`_saving`). ``shown``: the metrics on the bar, ``{metric: short name}``
    (the method's ``progress``). ``points(step, i, state_i)``: after each checkpoint, seed ``i``'s
    learning-curve metrics, appended as a line of their own (then ``curve.draw(outs)``). ``writes``
    False (a process other than 0 of a data-parallel run): no metric lines. Returns ``(state, step)``.
    """
    n = 1 if seeds is None else seeds
    pick = (lambda x, i: x) if seeds is None else (lambda x, i: x[i])
    check = jax.jit(functools.partial(ckpt.finite_leaves, seeds=seeds))
    bar = None
    if progress and start < cfg.steps:
        from tqdm.auto import tqdm  # pylint: disable=import-outside-toplevel

        bar = tqdm(total=cfg.steps, initial=start, desc=desc, unit='upd', smoothing=0.1)
        bar.set_postfix_str('compiling the training chunk (first call)', refresh=True)
    t_last, first, step = time.perf_counter(), True, start
    metric_files = [open(os.path.join(o, 'metrics.jsonl'), 'ab', buffering=0)  # pylint: disable=consider-using-with
                    for o in (outs if writes else [])]
    try:
        while step < cfg.steps:
            state, m = chunk(state, ds)
            m, finite = processes.local_copy((m, check(state)))  # (this process's replica when spread)
            step += cfg.updates_per_call
            now = time.perf_counter()
            timing = {'time/updates_per_s': n * cfg.updates_per_call / (now - t_last), 'time/includes_compile': first}
            t_last, first = now, False
            lines = [{'step': step, 'preset': cfg.preset, **{k: float(pick(v, i)) for k, v in m.items()}, **timing}
                     for i in range(n)]
            bad = [[k for k, v in ln.items() if isinstance(v, float) and not math.isfinite(v)]
                   + [f'state{p}' for p, ok in finite.items() if not pick(ok, i)] for i, ln in enumerate(lines)]
            if any(bad) or step % cfg.log_every == 0 or step == cfg.steps:
                for mf, ln in zip(metric_files, lines):
                    _append(mf, _strict_json(ln) + '\n')
            if any(bad):
                i = next(i for i, b in enumerate(bad) if b)
                raise _diverged(cfg, step, bad[i], '' if seeds is None else f' (seed folder {outs[i]})',
                                checkpoint_steps(outs[i]), start)
            if bar is not None:
                # postfix first without a redraw: update() draws once (a refresh here wrote every line twice in logs)
                bar.set_postfix({shown[k]: f'{v:.3g}' for k, v in lines[0].items() if k in shown},
                                refresh=False)
                bar.update(cfg.updates_per_call)
            if step % cfg.checkpoint_every == 0 or step == cfg.steps:
                save(step, state)
                if points is not None:
                    _curve_point(points, state, step, cfg, metric_files, pick, n, bar, curve, outs)
    finally:
        for mf in metric_files:
            mf.close()
        if bar is not None:
            bar.close()
    return state, step


def _curve_point(points, state, step, cfg, metric_files, pick, n, bar, curve, outs) -> None:
    """One point of the learning curve for every seed: a metric line of its own, the bar's postfix."""
    got = [points(step, i, jax.tree.map(lambda x, i=i: pick(x, i), state)) for i in range(n)]
    for mf, g in zip(metric_files, got if got[0] else []):  # a curve of the losses alone adds no line
        _append(mf, _strict_json({'step': step, 'preset': cfg.preset, **{k: float(v) for k, v in g.items()}}) + '\n')
    if bar is not None and 'eval/success' in got[0]:
        bar.write(f'step {step}: success ' + ', '.join(f'{100 * g["eval/success"]:.0f}%' for g in got)
                  + f' ({int(got[0].get("eval/episodes", 0))} development episodes'
                  + (' per seed)' if n > 1 else ')'))
    if curve.draw is not None:
        curve.draw(list(outs))


def train_seeds(method: Union[str, methods.Method], cfgs: list, data: dict, outs: list[str], keys: jax.Array,
                dataset_path: Optional[str] = None, progress: bool = True, log=print,
                curve: Optional[Curve] = None) -> list[Trained]:
    """Train ``S`` seeds of one method as one vmapped program, each into its own run folder.

    Every folder ends up as :func:`train` writes it (``config.json`` with its seed, its own
    ``metrics.jsonl`` and checkpoints), so :func:`load`, ``aqm-mjx evaluate`` and ``--resume`` see
    ordinary runs. The seeds are stacked on a leading axis and ``chunk_step`` runs under
    ``jax.vmap``; the numbers are those of ``S`` separate runs up to float reassociation.

    Resume: folders complete at ``cfgs[0].steps`` are loaded, not trained (a config may ask for more
    steps than the folders were started with, nothing else may differ). Otherwise training
    continues from the newest step that every folder has a checkpoint of (from the start when
    there is none); a checkpoint a folder already holds is not written again (the run is
    deterministic, so it is the same state), and metric lines past the restart step are dropped.

    Several processes (:mod:`aqm_mjx.processes`, ``N`` of them, ``N <= S``): every process passes every
    seed's config, folder and key, and trains its share, seed ``i`` on process ``i mod N``, as its own
    vmapped program; at each checkpoint step
    the processes gather their states and process 0 writes every seed's checkpoint (Orbax writes host
    arrays from process 0 alone); each process writes its own folders' ``config.json`` and metric
    lines. A resume starts every process at the newest step every folder holds.

    Args:
        cfgs: one config per seed, equal except ``seed``.
        outs: ``S`` run folders.
        keys: ``[S, 2]`` initialisation keys (ignored for folders restored from a checkpoint).
        curve: evaluated for every seed at every checkpoint step (:class:`Curve`).
    Returns:
        one :class:`Trained` per seed this process trained.
    """
    method = methods.get(method) if isinstance(method, str) else method
    n = len(outs)
    if len(cfgs) != n or keys.shape[0] != n:
        raise ValueError(f'{n} run folders, {len(cfgs)} configs and {keys.shape[0]} keys: give one of each per seed')
    if len(set(map(os.path.normpath, outs))) != n:
        raise ValueError(f'the run folders repeat: {outs}')
    if any(dataclasses.replace(c, seed=0) != dataclasses.replace(cfgs[0], seed=0) for c in cfgs):
        raise ValueError('train_seeds: the configs differ in more than their seed; train them separately')
    count = jax.process_count()
    if count > n:
        raise ValueError(f'{n} seed(s) over {count} processes: every process trains at least one; give --seeds '
                         f'{count} or more, or fewer processes')
    own = processes.share(n)  # this process's seeds
    with contextlib.ExitStack() as stack:
        for i in own:
            stack.enter_context(files.run_lock(outs[i]))  # one writer per run folder
        return _train_seeds(method, cfgs, data, outs, keys, dataset_path, progress, log, curve, own)


def _train_seeds(method, cfgs, data, outs, keys, dataset_path, progress, log, curve, own) -> list[Trained]:
    n, cfg = len(outs), cfgs[0]
    spread = jax.process_count() > 1  # several processes, each training its share
    ds = ds_io.to_device(data)
    obs_size, action_size = ds.observations.shape[1], ds.actions.shape[1]
    data_sha = fingerprint(data)
    done = [checkpoint_steps(o) for o in outs]
    for i in own:
        o, d, c = outs[i], done[i], cfgs[i]
        if d:  # the checks of a single run's resume: data, every config field named, config.json against the checkpoint
            _, _, meta = read_meta(o)
            check_same_data(o, meta, data_sha, dataset_path)
            check_resumable(o, method.name, dataclasses.replace(c, steps=max(c.steps, max(d))), obs_size, action_size)
            saver = ckpt.Checkpointer(o, keep=None, create=False)
            try:
                check_against_checkpoint(o, meta, saver)
            finally:
                saver.close()
    if all(d and max(d) >= cfg.steps for d in done):
        log(f'{method.name}: {n} seed(s) complete at step {cfg.steps}, not trained again')
        return [load(outs[i], log=log) for i in own]
    learner = method.make(cfg, obs_size, action_size)
    states = [learner.init(keys[i]) for i in own]
    _check_room([outs[i] for i in own], states[0], cfg, 0)  # (the complete case returned above) before any write
    metas = [meta_of(method.name, c, obs_size, action_size, dataset_path, data_sha) for c in cfgs]
    if spread:
        savers = [ckpt.Checkpointer(o, keep=cfg.keep) for o in outs] if jax.process_index() == 0 else []
        start, states = _restore_spread(outs, states, done, own, log)
    else:
        savers = [ckpt.Checkpointer(o, keep=cfg.keep) for o in outs]
        start, states = _restore_common(savers, states, done, log)
    try:
        if start:
            log(f'{method.name}: resuming {len(own)} seed(s) at step {start}')
        for i in own:
            files.write_json(os.path.join(outs[i], 'config.json'), metas[i], makedirs=True)
            trim_metrics(os.path.join(outs[i], 'metrics.jsonl'), start)
        state = jax.tree.map(lambda *x: jnp.stack(x), *states)
        chunk = jax.jit(seeds_chunk(learner.update, cfg.updates_per_call), donate_argnums=0)
        skip = [set(d) for d in done]
        pick = lambda x, i: x[i]  # noqa: E731
        save = _gathered_saving(savers, metas, skip, len(own), n) if spread else _saving(savers, metas, skip, pick)
        mine = [cfgs[i] for i in own]
        state, step = _host_loop(chunk, state, ds, cfg, start, [outs[i] for i in own], save, len(own),
                                 f'train {method.name} {cfg.preset} x{len(own)} seeds', progress, method.progress,
                                 _curve_points(curve, method, mine, learner, [metas[i] for i in own]), curve)
    finally:
        for saver in savers:
            saver.close()
    return [Trained(method.name, cfgs[i], learner, jax.tree.map(lambda x, j=j: x[j], state), step, metas[i])
            for j, i in enumerate(own)]


def _restore_spread(outs: list[str], templates: list, done: list[list[int]], own: list[int], log) -> tuple[int, list]:
    """Several processes: ``own``'s states at the newest step that every folder holds (the same on every
    process, so that they save in step); ``(0, templates)`` when there is none."""
    common = sorted(set.intersection(*map(set, done)) if all(done) else set())
    if not common:
        return 0, templates
    states = []
    for i, template in zip(own, templates):
        reader = ckpt.Checkpointer(outs[i], keep=None, create=False)
        try:
            states.append(reader.restore(template, step=common[-1], log=log)[1])
        finally:
            reader.close()
    return common[-1], states


def _gathered_saving(savers: list, metas: list[dict], skip: list[set], mine: int, n: int) -> Callable:
    """``save(step, state)`` of several processes, each holding ``mine`` seeds stacked (process ``p``
    seeds ``p, p + N, ...``): every process sends its states to every other (``process_allgather``,
    each share padded to the largest), and process 0, holding ``savers`` of all ``n`` folders, writes
    them."""
    count, most = jax.process_count(), -(-n // jax.process_count())

    def save(step, state):
        local = jax.device_get(state)
        if mine < most:  # the same shapes on every process: repeat the first seed
            local = jax.tree.map(lambda x: np.concatenate([x] + [x[:1]] * (most - mine)), local)
        got = processes.gather(local, f'gathering checkpoint {step}')  # [processes, most, ...] on every process
        for i, (saver, done) in enumerate(zip(savers, skip)):
            if step not in done:
                saver.save(step, jax.tree.map(lambda x, i=i: x[i % count, i // count], got), metas[i])

    return save


def _restore_common(savers: list, templates: list, done: list[list[int]], log) -> tuple[int, list]:
    """Restore every folder at the newest step all of them hold (``(0, templates)`` when there is
    none). A checkpoint that cannot be read is moved aside in its folder and the next common step
    is tried, so a resume always makes progress. ``done`` is updated in place."""
    while True:
        common = sorted(set.intersection(*map(set, done)) if all(done) else set())
        if not common:
            return 0, templates
        start, states = common[-1], []
        for saver, template, d in zip(savers, templates, done):
            try:
                states.append(saver.restore(template, step=start, log=log)[1])
            except ckpt.CheckpointError as e:
                log(f'warning: {e}; moved to {saver.set_aside(start)}')
                d.remove(start)
                break
        else:
            return start, states
