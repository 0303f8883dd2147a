"""A trained checkpoint, mapped and evaluated: ``aqm-mjx evaluate`` (one checkpoint, or several on the
same episodes), and the map-then-evaluate step that a run takes after training (:func:`map_and_evaluate`:
keypoints, a calibration pass where the protocol asks for one, the episode table, the report).

    res, rep = assess.evaluate_checkpoint('runs/antmaze-medium/train', shift='closures', seed=5)

Evaluation is the same code whichever path trained the model: the step-by-step run
(:mod:`aqm_mjx.run`) calls :func:`map_and_evaluate` with its trained state in memory.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import shutil
import time
from typing import Callable, Optional

import jax
import numpy as np

from aqm_mjx import envs, files, presets, processes
from aqm_mjx.agent import planners
from aqm_mjx.data import dataset as ds_io
from aqm_mjx.envs import shifts
from aqm_mjx.evaluation import plots, report
from aqm_mjx.evaluation.evaluate import calibrate_then_evaluate, device_mesh, evaluate, make_program
from aqm_mjx.evaluation.protocol import plan_episodes
from aqm_mjx.learn import fit, methods
from aqm_mjx.interface import Agent
from aqm_mjx.mapping.build import CHECK_OFFSET, candidate_rows, distance_check, method_map
from aqm_mjx.pipeline import RunConfig, stage_keys


def read_data(path: str, env) -> dict:
    """An OGBench file's arrays, checked against ``env``'s observation and action sizes (and its
    name, when the file's OGBench name says a maze)."""
    ds_io.check_env_name(path, env.name)
    return ds_io.read_ogbench(path, obs_size=env.obs_size, action_size=env.action_size, add_info=False)


def variants_for(maze: str, shift: str) -> dict:
    """``{name: grid}`` of ``--shift``: 'base', 'all' (the maze's suite), 'closures' (the training layout
    and the suite's closed corridors), one variant, or several joined by commas ('base,close-3-3')."""
    if shift == 'all':
        return shifts.suite(maze)
    if shift == 'closures':
        return {k: g for k, g in shifts.suite(maze).items() if k == 'base' or k.startswith('close')}
    names = [n.strip() for n in shift.split(',')]
    repeated = sorted({n for n in names if names.count(n) > 1})
    if '' in names or repeated:
        raise ValueError(f'--shift {shift!r}: ' + (f'layout(s) {repeated} named twice' if repeated else 'an empty name')
                         + "; give layout names joined by commas, e.g. 'base,close-3-3'")
    return {n: shifts.variant(maze, n) for n in names}


def preset_for_name(train_preset: str) -> str:
    """The run preset whose map, agent and protocol defaults match a training preset (runs trained
    before the presets were renamed say 'tiny' for 'ci'; an unknown name gets the default preset)."""
    return train_preset if train_preset in presets.RUN else 'ci' if train_preset == 'tiny' else presets.DEFAULT


def preset_for(trained: fit.Trained) -> str:
    """:func:`preset_for_name` of a trained method's training preset."""
    return preset_for_name(trained.config.preset)


# ------------------------------------------------------------------------------ map + evaluation
# room an evaluation's outputs need, reserved before its episodes (results.json and three pictures are
# about 0.1 MiB; 20x that): a disk too full for them is refused up front, not after every episode ran
EVAL_OUTPUT_BYTES = 2 * 2 ** 20

def agent_for(trained: fit.Trained, agent_cfg) -> Agent:
    """The agent ``trained`` is evaluated as: its own, or with the planner ``agent_cfg.planner`` around it
    (:func:`aqm_mjx.agent.planners.around`: ``flat``, ``aqm`` or ``ttgs`` on the method's distance)."""
    return planners.around(trained.agent, trained.learner.distance, agent_cfg.planner, trained.method,
                           ttgs=agent_cfg.ttgs)


def checked_distance(agent: Agent, trained: fit.Trained, data: dict, agent_cfg, key, log=print) -> None:
    """Before a map of planner ``aqm`` or ``ttgs`` is built on a method's distance: the check of
    :func:`aqm_mjx.mapping.build.distance_check` (unless ``agent_cfg.distance_check`` is off), its
    medians logged in one line."""
    if agent_cfg.planner not in ('aqm', 'ttgs') or not agent_cfg.distance_check:
        return
    c = distance_check(agent, data['observations'], data['terminals'], key, name=trained.method)
    if c is None:
        log(f'note: the data hold no trajectory of {CHECK_OFFSET + 1} states: {trained.method}\'s distance is not '
            f'checked before planner {agent_cfg.planner} maps on it')
        return
    log(f'{trained.method}\'s distance along the data: median {c["d1"]:.3g} steps over 1 step, {c["d25"]:.3g} over '
        f'{CHECK_OFFSET} (d(s, s) {c["d0"]:.3g}): planner {agent_cfg.planner} on it')


def _program(programs: Optional[dict], trained: fit.Trained, env, cfg: RunConfig, variants: dict):
    """The compiled evaluation chunk for ``trained`` from ``programs`` (filled on first use), shared by
    checkpoints whose method and configs agree up to the seed, and by the calibration pass and the
    evaluation: parameters, kappa, patience, layouts and episodes are arguments, not constants, so
    seeds of one method compile once, whatever their calibrated budgets."""
    if programs is None:
        return None
    run_cfg = cfg.to_dict()
    agent_cfg = {k: v for k, v in run_cfg['agent'].items() if k not in ('kappa', 'patience')}
    chunk = {k: run_cfg['protocol'][k] for k in ('horizon', 'backend', 'workers', 'physics_preset')}
    sig = json.dumps([trained.method, dataclasses.replace(trained.config, seed=0).to_dict(), run_cfg['map'],
                      agent_cfg, chunk], sort_keys=True)
    if sig not in programs:
        agent = agent_for(trained, cfg.agent)
        steps = plan_episodes(env, cfg.protocol, cfg.agent.kappa, variants, plans=agent.plans,
                              patience=cfg.agent.patience, own_rule=agent.rule is not None).steps
        programs[sig] = make_program(env, agent, cfg.agent, steps, device_mesh(), cfg.protocol.backend,
                                     cfg.protocol.workers, cfg.protocol.physics_preset)
    return programs[sig]


def map_and_evaluate(trained: fit.Trained, env, data: dict, cfg: RunConfig, variants: dict, k_map, k_eval,
                     out: str, info: dict, log=print, programs: Optional[dict] = None, train_layout=None):
    """The map from the dataset's arrays ``data`` (``observations``, ``terminals``) and the protocol for a
    trained method, then the report in
    ``out`` (``results.json`` and pictures). With ``cfg.protocol.calibrate`` ('fixed' or 'stall')
    a calibration pass on the training layout (``train_layout``, default the maze's) sets the AQM
    row's budget first (:func:`~aqm_mjx.evaluation.evaluate.calibrate_then_evaluate`; recorded as
    ``calibration`` in ``results.json``). ``programs``: a dict that keeps compiled evaluation
    chunks across calls (several seeds of a method). Returns ``(Results, report dict)``."""
    agent = agent_for(trained, cfg.agent)
    checked_distance(agent, trained, data, cfg.agent, k_map, log)
    if agent.plans:
        graph, m = method_map(agent, data, cfg.map, k_map)
    else:  # a flat method: no quasimetric, no map
        graph, m = None, dict(keypoints=0, overflow=False, seconds=0.0)
        why = ('' if cfg.agent.planner == 'flat' else ' (it has no distance to plan on)'
               if trained.learner.distance is None else ' (its own rule; --planner aqm|ttgs plans on its distance)')
        log(f'{trained.method} runs flat: no map, its controller aimed at the goal{why}')
    if m['overflow'] and agent.mapper is not None:
        log(f'warning: {trained.method} needed more map nodes than its max_nodes; some states joined their nearest')
    elif m['overflow']:
        log(f'warning: {cfg.map.max_keypoints} keypoints did not cover the candidates at delta {cfg.map.delta}: '
            f'{m["uncovered"]:,} of {m["candidates"]:,} were left outside every keypoint\'s delta; '
            'raise --max-keypoints or --delta')
    what = 'nodes of its own map' if agent.mapper is not None else f'keypoints at delta {cfg.map.delta}'
    mapped = 'no map' if graph is None else f'{m["keypoints"]} {what} ({m["seconds"]:.1f} s)'
    n_agents = 1 + len(cfg.protocol.ablations) if agent.prunes else 1
    if cfg.protocol.ablations and not agent.prunes:
        who = trained.method if cfg.agent.planner == 'own' else f'{trained.method} under planner {cfg.agent.planner}'
        log(f'note: {who} does not prune, so its own agent runs alone; the ablations '
            f'({", ".join(cfg.protocol.ablations)}) are rows of pruning agents (AQM, and QRL under its planner)')
    log(f'{env.name}, {trained.method} {trained.config.preset} preset at step {trained.step}: {mapped}; '
        f'{n_agents} agents x {len(variants)} layouts x '
        f'{len(cfg.protocol.tasks) or env.num_tasks} tasks x {cfg.protocol.episodes} episodes on '
        f'{jax.device_count()} device(s)')
    owned = programs is None  # the calibration pass and the evaluation share one compiled chunk
    programs = {} if owned else programs
    program = _program(programs, trained, env, cfg, variants)
    try:
        res, cal = calibrate_then_evaluate(env, agent, graph, cfg.agent, cfg.protocol, variants, k_eval,
                                           layout=train_layout, program=program,
                                           on_calibrated=lambda c: log(calibration_line(c, cfg.agent)))
    finally:
        if owned:
            for p in programs.values():
                if hasattr(p, 'close'):
                    p.close()
    report.print_summary(res, log, cfg.protocol.false_alarm)
    info = dict(info, method=trained.method, step=trained.step, train_preset=trained.config.preset,
                keypoints=m['keypoints'], keypoint_overflow=m['overflow'],
                **({'keypoint_uncovered': m['uncovered']} if 'uncovered' in m else {}), map_s=round(m['seconds'], 2),
                config=cfg.to_dict(), **({} if cal is None else dict(calibration=cal)))
    if not processes.writer():  # several processes: each holds every result; process 0 writes them
        return res, info
    rep = report.write(res, graph, env.layout, variants, out, env.name, cfg.protocol.episodes, info,
                       name=os.path.basename(os.path.normpath(info.get('checkpoint', out))),
                       false_alarm=cfg.protocol.false_alarm)
    log(f'wrote {out}/results.json and pictures')
    return res, rep


def calibration_line(cal: dict, agent_cfg) -> str:
    """One line on what a calibration pass set (or why it set nothing)."""
    where = (f'calibration pass: {cal["episodes"]} episodes without pruning between cells no task uses, '
             f'{cal["legs"]} legs completed')
    if not cal['calibrated']:
        return (f'warning: {where}: nothing to calibrate from; AQM keeps kappa {agent_cfg.kappa:g}, '
                f'patience {agent_cfg.patience:g}')
    q = f'{cal["false_alarm"]:.1%} false alarms'
    paper = f'; the paper\'s rule on keypoint edges: kappa {cal["kappa_edges"]:g}'
    if cal['rule'] == 'stall':
        how = (f'{cal["stall_scale"]:g} x the 90th percentile of the longest stall, {cal["stall_q"][1]:g} steps'
               if cal.get('stall_scale', 0) > 0 else q)
        return f'{where}: AQM row on the stall rule, patience {cal["patience"]:g} steps ({how}){paper}'
    if cal['rule'] == 'fixed':
        return f'{where}: AQM row on the fixed rule, kappa {cal["kappa"]:g} ({q}){paper}'
    return f'{where} ({q}){paper}'


def curve_setup(cfg: RunConfig, key: jax.Array, episodes: Optional[int] = None) -> tuple:
    """How a learning-curve point evaluates: ``(protocol, agent_cfg, k_map, k_eval)``, the protocol on
    the development split with ``episodes`` a task (default ``cfg.protocol.curve_episodes``), no
    ablations, no calibration, in ``curve_backend``'s physics; the agent without pruning (``kappa``
    infinite, ``patience`` 0); ``key`` (``stage_keys(...)[2]`` in a comparison) split into the map's key
    and the episodes' key."""
    protocol = dataclasses.replace(cfg.protocol, episodes=cfg.protocol.curve_episodes if episodes is None else episodes,
                                   ablations=(), calibrate='none', split='dev',
                                   backend=cfg.protocol.curve_backend or cfg.protocol.backend)
    agent_cfg = dataclasses.replace(cfg.agent, kappa=math.inf, patience=0.0)
    k_map, k_eval = jax.random.split(key)
    return protocol, agent_cfg, k_map, k_eval


def learning_curve(env, data: dict, cfg: RunConfig, key: jax.Array, label: str = '') -> Optional[fit.Curve]:
    """The learning curve of a training run (:class:`~aqm_mjx.learn.fit.Curve`; None when
    ``cfg.protocol.curve_episodes`` is 0): at every checkpoint, the method's agent without pruning
    (its planner, or its flat controller) on ``curve_episodes`` development episodes per task of the
    training layout (in ``curve_backend``'s physics, default the protocol's), mapped from ``data``'s states with every map slot kept, so one compiled chunk
    serves every point; the same episodes at every point (``key``). Each point is
    ``{'eval/success', 'eval/episodes', 'eval/seconds'}``; ``draw`` redraws ``FOLDER/curves.png``
    (the method's progress metrics and success, a line per seed)."""
    n = cfg.protocol.curve_episodes
    if not n:
        return None
    protocol, agent_cfg, k_map, k_eval = curve_setup(cfg, key)
    variants = {'base': env.layout}
    programs, drawers = {}, {}

    def point(trained: fit.Trained) -> dict:
        t0 = time.perf_counter()
        agent = agent_for(trained, agent_cfg)
        graph = method_map(agent, data, cfg.map, k_map, static=True)[0] if agent.plans else None
        if trained.method not in programs:  # seeds and checkpoints share one compiled chunk
            steps = plan_episodes(env, protocol, agent_cfg.kappa, variants, plans=agent.plans,
                                  own_rule=agent.rule is not None).steps
            programs[trained.method] = make_program(env, agent, agent_cfg, steps, device_mesh(), protocol.backend,
                                                    protocol.workers, protocol.physics_preset)
            drawers[trained.method] = curve_drawer(
                trained.method, f'{env.name}: {label or trained.method}, {cfg.train.preset} preset, {{seeds}} seed(s)',
                label)
        res = evaluate(env, agent, graph, agent_cfg, protocol, variants, k_eval, program=programs[trained.method],
                       progress=False)
        if protocol.workers and hasattr(programs[trained.method], 'close'):  # worker processes do not outlive a point
            programs.pop(trained.method).close()
        return {'eval/success': res.summary[res.agents[0]]['base']['mean'], 'eval/episodes': n * len(res.tasks),
                'eval/seconds': time.perf_counter() - t0}

    def draw(folders: list) -> None:  # a curve serves one method: its one drawer
        next(iter(drawers.values()))(folders)

    return fit.Curve(point, draw)


def curve_drawer(method: str, title: str, label: str = '') -> Callable[[list], None]:
    """``draw(folders)``: ``curves.png`` of a run's seeds (the method's progress metrics, GAS's phase
    flag aside, and its learning-curve points), drawn once and written into every folder; ``{seeds}`` in
    ``title`` is the number of folders."""
    keys = [k for k in methods.get(method).progress if k != 'phase']

    def draw(folders: list) -> None:
        first = os.path.join(folders[0], 'curves.png')
        plots.curves({label or method: [os.path.join(f, 'metrics.jsonl') for f in folders]}, keys, first,
                     title=title.replace('{seeds}', str(len(folders))))
        for folder in folders[1:]:
            shutil.copyfile(first, os.path.join(folder, 'curves.png'))

    return draw


def dataset_of(checkpoint: str, meta: dict) -> Optional[str]:
    """The dataset a run folder records (``config.json``'s ``dataset``); a relative path is read from
    the folder (a shipped checkpoint's ``map_states.npz``)."""
    path = meta.get('dataset')
    return os.path.join(checkpoint, path) if path and not os.path.isabs(path) else path


MAP_STATES = 'map_states.npz'


def learned_map_panels(checkpoint: str, deltas=(), dataset: Optional[str] = None, seed: int = 0):
    """``aqm-mjx render --checkpoint``: the map a trained run plans on, built as its evaluation builds
    it (the map key of ``PRNGKey(seed)``, candidates from its dataset or map states), one panel per
    ``delta`` (default the preset's). Returns ``(grid, panels)`` for
    :func:`aqm_mjx.envs.render.render_panels`."""
    from aqm_mjx.mapping.graph import components, edge_list  # pylint: disable=import-outside-toplevel

    env, _, cfg, path = prepare_evaluation(checkpoint, None, dataset, 'base', ())
    trained = fit.load(checkpoint, log=lambda *_: None)
    if not trained.agent.plans:
        raise ValueError(f'{checkpoint}: {trained.method} has no quasimetric and plans on no map')
    data = read_data(path, env)
    _, k_map, _ = stage_keys(jax.random.PRNGKey(seed))
    panels = []
    for delta in list(deltas) or [cfg.map.delta]:
        graph, info = method_map(trained.agent, data, dataclasses.replace(cfg.map, delta=float(delta)), k_map)
        mask = np.asarray(graph.mask)
        n_comp = int(components(graph.w, graph.mask)[1])
        panels.append(dict(nodes_xy=np.asarray(graph.obs)[mask, :2], edges=edge_list(np.asarray(graph.w)[mask][:, mask]),
                           title=f'{trained.method} step {trained.step}, delta {delta:g}: {info["keypoints"]} '
                                 f'keypoints, {n_comp} component(s)'))
    return env.layout, panels


def export_checkpoint(checkpoint: str, out: str, dataset: Optional[str] = None, seed: int = 0, log=print) -> dict:
    """``aqm-mjx export``: a run folder small enough to ship. ``out`` gets the newest checkpoint,
    ``config.json`` (its dataset: :data:`MAP_STATES`, in the folder), ``metrics.jsonl`` and
    ``curves.png``, and :data:`MAP_STATES`: the ``map.candidates`` training states that the map of
    ``aqm-mjx evaluate --seed seed`` draws, in its order (:func:`~aqm_mjx.mapping.build.candidate_rows`),
    so that the shipped folder builds the map the full data gives, without the data. ``data.json``
    keeps the training data's fingerprint (``config.json`` too, so a resume on the map states is
    refused). Returns ``data.json``'s record."""
    env, _, cfg, path = prepare_evaluation(checkpoint, None, dataset, 'base', ())
    if fit.load(checkpoint, log=lambda *_: None).agent.mapper is not None:
        raise ValueError(f'{checkpoint}: {cfg.method} builds its map from whole trajectories; only a keypoint '
                         'map is rebuilt from map states: ship it with its dataset')
    if os.path.exists(out) and os.listdir(out):
        raise FileExistsError(f'{out} is not empty; export into a new folder')
    steps = fit.checkpoint_steps(checkpoint)
    if not steps:
        raise files.MissingFileError(f'{checkpoint} holds no checkpoint to export')
    _, _, meta = fit.read_meta(checkpoint)
    data = read_data(path, env)
    _, k_map, _ = stage_keys(jax.random.PRNGKey(seed))
    rows = jax.device_get(candidate_rows(len(data['observations']), cfg.map, k_map))
    states = dict(observations=data['observations'][rows], actions=data['actions'][rows],
                  terminals=np.ones(len(rows), bool))  # each state on its own: no transitions to train on
    os.makedirs(os.path.join(out, 'checkpoints'), exist_ok=True)
    shutil.copytree(os.path.join(checkpoint, 'checkpoints', str(steps[-1])),
                    os.path.join(out, 'checkpoints', str(steps[-1])))
    for name in ('metrics.jsonl', 'curves.png'):
        if os.path.exists(os.path.join(checkpoint, name)):
            shutil.copy2(os.path.join(checkpoint, name), os.path.join(out, name))
    ds_io.write_ogbench(os.path.join(out, MAP_STATES), states)
    files.write_json(os.path.join(out, 'config.json'), dict(meta, dataset=MAP_STATES))
    record = dict(source=os.path.basename(path), data_sha256=meta.get('data_sha256') or ds_io.fingerprint(data),
                  states=len(data['observations']),
                  map_states=len(rows), map_seed=seed, map_candidates=cfg.map.candidates, step=steps[-1],
                  map_states_sha256=ds_io.fingerprint(states), provenance=files.provenance())
    files.write_json(os.path.join(out, 'data.json'), record)
    log(f'wrote {out}: step {steps[-1]}, {len(rows):,} map states of {len(data["observations"]):,} '
        f'({sum(os.path.getsize(os.path.join(d, f)) for d, _, fs in os.walk(out) for f in fs) / 2 ** 20:.1f} MiB)')
    return record


def prepare_evaluation(checkpoint: str, cfg: Optional[RunConfig], dataset: Optional[str], shift: str, overrides):
    """Everything an evaluation of ``checkpoint`` needs, checked before anything is loaded or built:
    ``(env, variants, RunConfig, dataset path)``."""
    method, train_cfg, meta = fit.read_meta(checkpoint)
    if train_cfg.env is None:
        raise ValueError(f'{checkpoint} does not record its environment (config.env); it cannot be evaluated')
    env = envs.make(train_cfg.env)
    variants = variants_for(env.maze, shift)
    if dataset and not os.path.exists(dataset):
        raise FileNotFoundError(f'--dataset {dataset}: no such file')
    path = dataset or dataset_of(checkpoint, meta)
    if not path or not os.path.exists(path):
        raise FileNotFoundError(f'dataset {path!r} of {checkpoint} not found (keypoints are selected from its '
                                'states); pass --dataset')
    if cfg is None:
        cfg = RunConfig.preset(preset_for_name(train_cfg.preset), method=method.name, env=train_cfg.env)
    cfg = RunConfig(method=method.name, train=train_cfg, map=cfg.map, agent=cfg.agent,
                    protocol=cfg.protocol).with_overrides(list(overrides))
    check_evaluation_memory(env, cfg, len(variants))  # before the episode table is allocated
    plan_episodes(env, cfg.protocol, cfg.agent.kappa, variants)  # bad task ids fail before any work
    return env, variants, cfg, path


def check_evaluation_memory(env, cfg: RunConfig, n_layouts: int) -> None:
    """Refuse an evaluation whose episode table (host: the leg log and outcome of every episode) or
    chunk of environments (device: ``protocol.envs`` states) cannot fit, naming the option."""
    from aqm_mjx import memory  # pylint: disable=import-outside-toplevel
    from aqm_mjx.agent.rules import LEG_FIELDS, MAX_LEGS  # pylint: disable=import-outside-toplevel
    from aqm_mjx.evaluation.protocol import agent_specs  # pylint: disable=import-outside-toplevel

    p = cfg.protocol
    rows = len(agent_specs(1.0, p.ablations)) * n_layouts * len(p.tasks or range(env.num_tasks)) * p.episodes
    memory.check(rows * (MAX_LEGS * LEG_FIELDS * 4 + 256), f'the episode table ({rows:,} episodes)',
                 '--episodes (or the layouts and ablations)', (memory.host_available(), 'host'))
    if p.backend == 'mjx' and p.envs:  # (0: the chunk is chosen to fit)
        memory.check(p.envs * memory.env_state_bytes(env) * memory.FACTOR,
                     f'a chunk of {p.envs:,} environments', '--envs')


def default_out(checkpoints) -> str:
    """Where an evaluation of ``checkpoints`` writes when no folder is named: ``CHECKPOINT/eval`` for
    one, the first one's parent's ``comparison/`` for several; ``runs/eval/NAME`` (or
    ``runs/eval/comparison``) where that lies in a shipped or exported checkpoint, which is only read."""
    first = os.path.normpath(checkpoints[0])
    one = len(checkpoints) == 1
    out = os.path.join(first, 'eval') if one else os.path.join(os.path.dirname(first), 'comparison')
    if files.shipped_above(out) is not None:
        out = os.path.join('runs', 'eval', os.path.basename(first) if one else 'comparison')
    return out


def evaluate_checkpoint(checkpoint: str, cfg: Optional[RunConfig] = None, dataset: Optional[str] = None,
                        shift: str = 'base', out: Optional[str] = None, seed: int = 0, overrides=(), log=print):
    """``aqm-mjx evaluate``: load a run folder, map, evaluate, write ``results.json`` and pictures.

    ``cfg`` defaults to the run preset of the checkpoint's training preset, with ``overrides``
    (``section.field=value``) applied; its ``train`` section is the checkpoint's. The map and
    episode keys are :func:`~aqm_mjx.pipeline.stage_keys` of ``PRNGKey(seed)``, as in ``aqm-mjx run``.
    Layouts, tasks and the dataset are checked before anything is loaded or built.
    """
    env, variants, cfg, path = prepare_evaluation(checkpoint, cfg, dataset, shift, overrides)
    out = out or default_out([checkpoint])
    files.check_writable(out, EVAL_OUTPUT_BYTES, 'the evaluation\'s results and pictures')  # before the episodes
    trained = fit.load(checkpoint, log=log)
    data = read_data(path, env)
    _, k_map, k_eval = stage_keys(jax.random.PRNGKey(seed))
    info = dict(checkpoint=os.path.abspath(checkpoint), dataset=os.path.abspath(path), seed=seed)
    return map_and_evaluate(trained, env, data, cfg, variants, k_map, k_eval, out, info, log)


def checkpoint_labels(checkpoints, names) -> list[str]:
    """Row labels of several checkpoints of methods ``names``: the method's name, or with the run
    folder's where methods repeat."""
    folders = [os.path.basename(os.path.normpath(c)) or c for c in checkpoints]
    labels = [n if names.count(n) == 1 else f'{n}:{f}' for n, f in zip(names, folders)]
    if len(set(labels)) != len(labels):
        labels = [f'{n}:{i}' for i, n in enumerate(names)]
    return labels


def evaluate_checkpoints(checkpoints, out: str, cfg: Optional[RunConfig] = None, dataset: Optional[str] = None,
                         shift: str = 'base', seed: int = 0, overrides=(), log=print) -> dict:
    """``aqm-mjx evaluate --checkpoint A --checkpoint B ...``: several checkpoints (any methods, one
    environment) on the same episodes: the same protocol, layouts, tasks and episode keys
    (:func:`~aqm_mjx.pipeline.stage_keys` of ``PRNGKey(seed)``). Each is written to ``out/LABEL``;
    ``out/results.json`` holds the table ``{LABEL/agent: {layout: {'task_T': rate, 'mean': rate}}}``
    and ``out/success.png`` its bars. Every checkpoint is checked before any is evaluated."""
    checkpoints = list(checkpoints)
    if not checkpoints:
        raise ValueError('give at least one --checkpoint')
    prepared = [prepare_evaluation(c, cfg, dataset, shift, overrides) for c in checkpoints]
    env_names = sorted({p[0].name for p in prepared})
    if len(env_names) > 1:
        raise ValueError(f'the checkpoints were trained on different environments ({", ".join(env_names)}); '
                         'compare checkpoints of one environment')
    labels = checkpoint_labels(checkpoints, [p[2].method for p in prepared])  # config.json read once, above
    files.check_writable(out, EVAL_OUTPUT_BYTES * (len(checkpoints) + 1),  # before any map or episode
                         'the evaluation\'s results and pictures')
    _, k_map, k_eval = stage_keys(jax.random.PRNGKey(seed))
    table, per, programs, datasets = {}, {}, {}, {}
    for label, ckpt, (env, variants, c, path) in zip(labels, checkpoints, prepared):
        log(f'== {label} ({ckpt})')
        trained = fit.load(ckpt, log=log)
        if path not in datasets:  # checkpoints of one dataset (seeds of a method) read it once
            datasets[path] = read_data(path, env)
        info = dict(checkpoint=os.path.abspath(ckpt), dataset=os.path.abspath(path), seed=seed)
        res, rep = map_and_evaluate(trained, env, datasets[path], c, variants, k_map, k_eval,
                                    os.path.join(out, label), info, log, programs)
        per[label] = dict(checkpoint=os.path.abspath(ckpt), method=trained.method, step=trained.step,
                          keypoints=rep['keypoints'])
        for agent_name in res.agents:
            table[f'{label}/{agent_name}'] = res.summary[agent_name]
    env, variants = prepared[0][0], prepared[0][1]
    first = list(variants)[0]
    combined = dict(env=env.name, seed=seed, episodes=prepared[0][2].protocol.episodes,
                    split=prepared[0][2].protocol.split, checkpoints=per, tasks=res.tasks, variants=list(variants),
                    summary=table, config=prepared[0][2].to_dict(), provenance=files.provenance())
    if not processes.writer():  # process 0 writes the table
        return combined
    files.write_json(os.path.join(out, 'results.json'), combined, makedirs=True)
    plots.success_bars(table, first, res.tasks, os.path.join(out, 'success.png'),
                       title=f'{env.name} ({first}): every checkpoint on the same episodes',
                       episodes=prepared[0][2].protocol.episodes)
    width = max(len(k) for k in table)
    log(f'{"checkpoint/agent":<{width}}  mean success ({first})')
    for k, row in table.items():
        log(f'{k:<{width}}  {100 * row[first]["mean"]:5.1f}%')
    log(f'wrote {out}/results.json and {out}/success.png')
    return combined
