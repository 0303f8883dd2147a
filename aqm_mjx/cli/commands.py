"""What each ``aqm-mjx`` subcommand does with its parsed options: build the config, call the package
(:mod:`aqm_mjx.run`, :mod:`aqm_mjx.compare`, :mod:`aqm_mjx.learn.fit`, :mod:`aqm_mjx.data.collect`) and
print where the results went. Nothing here computes: the commands only connect options to stages.
"""

from __future__ import annotations

import dataclasses
import json
import os
import sys

from aqm_mjx import presets


#: where every command caches its compiled programs (README: "Compiled programs are cached")
CACHE_DIR = '~/.cache/aqm_mjx/jax'


def enable_compile_cache():
    """JAX's persistent compilation cache for the commands: :data:`CACHE_DIR`, unless a cache folder
    is already configured (``JAX_COMPILATION_CACHE_DIR``, or a caller's ``jax.config``), which wins."""
    import jax  # pylint: disable=import-outside-toplevel

    if not jax.config.jax_compilation_cache_dir:
        jax.config.update('jax_compilation_cache_dir', os.path.expanduser(CACHE_DIR))
        jax.config.update('jax_persistent_cache_min_compile_time_secs', 1.0)


def cmd_envs(a):
    """The environments and their tasks (from the catalog: no JAX imported)."""
    del a
    from aqm_mjx.cli import catalog  # pylint: disable=import-outside-toplevel

    print('\n'.join(catalog.load()['envs']))
    return 0


PICTURE_TYPES = ('.png', '.pdf', '.svg', '.jpg', '.jpeg')


def picture_path(out: str, name: str) -> str:
    """Where a picture asked for as ``out`` is written: ``out/name`` for a folder (an existing one, or
    a path ending in a separator), ``out + '.png'`` without a suffix, ``out`` itself with a picture
    suffix; any other suffix is refused, naming the types."""
    if os.path.isdir(out) or out.endswith(os.sep):
        return os.path.join(out, name)
    suffix = os.path.splitext(out)[1].lower()
    if not suffix:
        return out + '.png'
    if suffix not in PICTURE_TYPES:
        raise ValueError(f'--out {out}: a picture is written as {", ".join(PICTURE_TYPES)} (or into a folder); '
                         f'not {suffix}')
    return out


def cmd_render(a):
    import numpy as np  # pylint: disable=import-outside-toplevel

    from aqm_mjx import envs  # pylint: disable=import-outside-toplevel
    from aqm_mjx.envs.render import render_maze, render_panels  # pylint: disable=import-outside-toplevel

    _, maze = envs.parse_name(a.env)
    bad = [d for d in a.deltas or () if not (d > 0 and d < float('inf'))]
    if bad:
        raise ValueError(f'--deltas must be finite numbers > 0; got {bad}')
    a.out = picture_path(a.out, f'{a.env}.png')
    if a.checkpoint:
        from aqm_mjx import assess  # pylint: disable=import-outside-toplevel

        grid, panels = assess.learned_map_panels(a.checkpoint, a.deltas or (), dataset=a.dataset)
        render_panels(grid, panels, a.out)
        for p in panels:
            print(p['title'])
        print(f'wrote {a.out}')
        return 0
    if a.deltas:
        from aqm_mjx.agent.oracle import keypoint_map_panels  # pylint: disable=import-outside-toplevel

        grid, panels = keypoint_map_panels(maze, a.deltas)
        render_panels(grid, panels, a.out)
        for p in panels:
            print(p['title'])
        print(f'wrote {a.out}')
        return 0
    tasks = envs.mazes.tasks(maze)
    render_maze(envs.mazes.layout(maze), a.out, start_xy=np.array([t.init_xy for t in tasks]),
                goal_xy=np.array([t.goal_xy for t in tasks]), title=f'{a.env}: evaluation tasks')
    print(f'wrote {a.out}')
    return 0


def cmd_collect(a):
    """Collect an OGBench-format dataset with the scripted expert (MJX, or MuJoCo on the host); with
    several processes each collects its share of the chunks and process 0 writes the files."""
    start_processes(a)  # before any other JAX call: every process runs this same command
    enable_compile_cache()
    from aqm_mjx import files, processes  # pylint: disable=import-outside-toplevel
    from aqm_mjx.data import collect  # pylint: disable=import-outside-toplevel

    cfg = collect.CollectConfig(env=a.env, style=a.style, episodes=a.episodes, steps=a.steps, noise=a.noise,
                                batch=a.batch, seed=a.seed, layout=a.layout, physics=a.physics,
                                physics_preset=a.physics_preset).resolved()
    writer = processes.writer()
    if writer:
        collect.check_output(a.out, a.overwrite, cfg)  # name, folder and free space before minutes of collection
    collect.check_memory(cfg)
    import jax  # pylint: disable=import-outside-toplevel

    where = jax.devices()[0] if cfg.physics == 'mjx' else 'the host (MuJoCo)'
    if processes.count() > 1:
        where = f'{where} and the devices of {processes.count() - 1} more processes' if cfg.physics == 'mjx' else \
            f'the hosts of {processes.count()} processes (MuJoCo)'
    if writer:
        print(f'collecting {cfg.episodes} + {cfg.val_episodes} (val) {cfg.style} episodes x {cfg.steps} states in '
              f'{cfg.env} ({cfg.layout} layout), noise {cfg.noise}, {cfg.batch} at a time on {where}, physics '
              f'{cfg.physics_preset}')
    physics = {k: v for k, v in (('iterations', a.iterations), ('ls_iterations', a.ls_iterations)) if v is not None}
    res = collect.collect(cfg, physics=physics)
    if not writer:  # process 0 writes the files; the others end once it has
        processes.barrier('collect: written')
        return 0
    try:
        train, val = collect.write(res, a.out, overwrite=a.overwrite)
    finally:  # the others wait here, written or not (an error here is process 0's to show)
        processes.barrier('collect: written')
    # the data are complete from here on: a picture or summary the disk has no room for is a warning
    png, summary = a.out[:-4] + '.png', a.out[:-4] + '.json'
    try:
        collect.plot(res, png)
    except OSError as e:
        if os.path.exists(png):
            os.remove(png)
        print(f'warning: {png} could not be written ({e.strerror or e}); the data in {train} are complete',
              file=sys.stderr)
        png = None
    res.stats.update(train=train, val=val if cfg.val_episodes else None, picture=png)
    try:
        files.write_json(summary, res.stats)
    except files.OutputError as e:
        print(f'warning: {e}; the data in {train} are complete', file=sys.stderr)
    print(json.dumps(res.stats, indent=1))
    return 0


def cmd_methods(a):
    """The registered methods (from the catalog: no JAX imported)."""
    del a
    from aqm_mjx.cli import catalog  # pylint: disable=import-outside-toplevel

    for name, summary in catalog.load()['summaries'].items():
        print(f'{name:<10} {summary}')
    return 0


def cmd_train(a):
    """Train a method on an OGBench-format dataset (with several processes: one run, data-parallel)."""
    start_processes(a)  # before any other JAX call: every process runs this same command
    enable_compile_cache()
    from aqm_mjx import envs  # pylint: disable=import-outside-toplevel
    from aqm_mjx.data import dataset  # pylint: disable=import-outside-toplevel
    from aqm_mjx import memory  # pylint: disable=import-outside-toplevel
    from aqm_mjx.learn import fit, folder, methods  # pylint: disable=import-outside-toplevel

    from aqm_mjx import files  # pylint: disable=import-outside-toplevel

    files.check_output(a.out, 'config.json')
    method = methods.get(a.method or 'aqm')
    try:
        inferred, style = dataset.infer_env(a.dataset)
    except ValueError:
        if a.env is None and not a.resume:
            raise
        inferred, style = None, None
    env_name = a.env or inferred
    if a.env and inferred:
        dataset.check_env_name(a.dataset, a.env)
    cfg = None
    obs_size = action_size = None
    sets = [s[len('train.'):] if s.startswith('train.') else s for s in a.set or []]
    if not a.resume:
        env = envs.make(env_name)
        obs_size, action_size = env.obs_size, env.action_size
        cfg = method.preset(a.preset or presets.DEFAULT, style=style, env=env_name, seed=a.seed or 0).with_overrides(sets)
        if cfg.env != env_name:
            raise ValueError(f'--set env={cfg.env}: the environment is {env_name} (from --env or the dataset\'s '
                             'name), which sets the observation size; give --env instead')
        if a.steps is not None:
            cfg = dataclasses.replace(cfg, steps=int(a.steps))
        memory.check_training(method, cfg, obs_size, action_size)
    elif a.method or a.preset or a.seed is not None or sets or a.env:
        # every option given with --resume is checked against the saved run (the same values pass)
        if not os.path.exists(os.path.join(a.out, 'config.json')):
            raise FileNotFoundError(f'{a.out} holds no run to resume (no config.json); start a new run without --resume')
        _, saved, _ = fit.read_meta(a.out)
        folder.check_resume_request(a.out, a.method, None)  # another method first: its fields are not comparable
        base = method.preset(a.preset, style=style, env=saved.env, seed=saved.seed) if a.preset else saved
        changes = ([f'env={a.env}'] if a.env else []) + ([f'seed={a.seed}'] if a.seed is not None else []) + sets
        folder.check_resume_request(a.out, None, base.with_overrides(changes))
    data = dataset.read_ogbench(a.dataset, obs_size=obs_size, action_size=action_size, add_info=False)
    print(f'dataset {a.dataset}: {len(data["terminals"])} states, {int(data["terminals"].sum())} trajectories')
    if cfg is not None:
        print(f'{method.name}, preset {cfg.preset}: {cfg.steps} updates of batch {cfg.batch_size}')
    from aqm_mjx.assess import curve_drawer  # pylint: disable=import-outside-toplevel

    shown = fit.read_meta(a.out)[0] if a.resume and os.path.exists(os.path.join(a.out, 'config.json')) else method
    losses = fit.Curve(lambda trained: {},  # the losses at every checkpoint, no evaluation
                       curve_drawer(shown.name, f'{shown.name} on {os.path.basename(a.dataset)}'))
    fit.train(method, cfg, data, a.out, resume=a.resume, steps=a.steps, dataset_path=os.path.abspath(a.dataset),
              curve=losses)
    from aqm_mjx import processes  # pylint: disable=import-outside-toplevel

    if processes.writer():
        print(f'wrote {a.out} (config.json, metrics.jsonl, checkpoints/, curves.png)')
    return 0


def overrides_of(a) -> list:
    """``--set`` pairs, then the section options the user gave, as ``section.field=text``."""
    out = list(a.set or [])
    for k, v in vars(a).items():
        if '.' in k and v is not None:
            out.append(f'{k}={",".join(v) if isinstance(v, list) else v}')
    return out


def run_config(a):
    """The RunConfig of ``aqm-mjx run`` (both paths): the preset for the method, environment, seed and
    data style, then the overrides."""
    from aqm_mjx import envs, pipeline  # pylint: disable=import-outside-toplevel

    envs.parse_name(a.env)
    style = 'navigate'  # what the run collects; a --dataset says its own in its OGBench name
    if a.dataset:
        from aqm_mjx.data import dataset  # pylint: disable=import-outside-toplevel

        try:
            style = dataset.infer_env(a.dataset)[1]
        except ValueError:
            style = None  # not an OGBench name: no style rule
    return pipeline.RunConfig.preset(a.preset, method=a.method, env=a.env, seed=a.seed,
                                     style=style).with_overrides(overrides_of(a))


def named_physics(overrides) -> str:
    """The physics preset the overrides name for every method (``--physics-preset`` or ``--set
    [protocol.]physics_preset=NAME``, the last one given), else ``'ogbench'``: what the data are
    collected in, as the evaluation steps it."""
    found = 'ogbench'
    for o in overrides:
        key, _, value = o.partition('=')
        if ':' not in key and key.strip().split('.')[-1] == 'physics_preset':
            found = value.strip()
    return found


def start_processes(a) -> int:
    """Join the run's processes when the command names them (``--coordinator``, ``--num-processes``,
    ``--process-id``, or ``--distributed``); returns the process count (1: this process alone)."""
    from aqm_mjx import processes  # pylint: disable=import-outside-toplevel

    named = (getattr(a, 'coordinator', None), getattr(a, 'num_processes', None), getattr(a, 'process_id', None))
    if not getattr(a, 'distributed', False) and named == (None, None, None):
        return 1
    pid, n = processes.start(*named, detect=getattr(a, 'distributed', False) and named == (None, None, None))
    print(f'process {pid} of {n}: {n} processes joined', file=sys.stderr)
    return n


def host_backend(preset_names, overrides) -> list:
    """``['protocol.backend=ogbench']`` where an evaluation of these presets runs in OGBench's own
    environments on this host, else ``[]``: the ``cpu`` rows (:func:`aqm_mjx.presets.host_evaluation`)
    on a host without an accelerator, when ``overrides`` name no backend and no MJX physics (a
    ``physics_preset`` other than ``ogbench`` asks for MJX). On a 2-core CPU OGBench's environments
    evaluate 8x faster than MJX (RESULTS 7.4); with an accelerator MJX is the default."""
    import jax  # pylint: disable=import-outside-toplevel

    from aqm_mjx import presets  # pylint: disable=import-outside-toplevel

    named = dict(o.split('=', 1) for o in overrides if '=' in o)
    named = {k.strip().split('.')[-1]: v.strip() for k, v in named.items()}
    if 'backend' in named or named.get('physics_preset', 'ogbench') != 'ogbench':
        return []
    if not all(presets.host_evaluation(p) for p in preset_names) or jax.default_backend() != 'cpu':
        return []
    return ['protocol.backend=ogbench']


def cmd_run(a):
    """The whole pipeline: data -> train -> keypoints -> evaluate (step by step, or as one program)."""
    n_processes = start_processes(a)  # before any other JAX call: every process runs this same command
    enable_compile_cache()
    import jax  # pylint: disable=import-outside-toplevel

    from aqm_mjx import assess, envs, files, run  # pylint: disable=import-outside-toplevel

    if a.one_program and n_processes > 1:
        raise ValueError('--one-program runs in one process (its seeds vmapped over its devices); drop it to run '
                         'over several processes')
    cfg = run_config(a)
    # several processes evaluate in MJX, each its share of the episodes
    host = [] if a.one_program or n_processes > 1 else host_backend([a.preset], overrides_of(a))
    if host:
        cfg = cfg.with_overrides(host)
    out = a.out or os.path.join('runs', a.env)
    files.check_output(out, 'run.json')
    where = {'mjx': ' in MJX', 'ogbench': " in OGBench's environments"}[cfg.protocol.backend]
    if host:
        where += ' on the host (no accelerator; --backend mjx for MJX)'
    print(f'aqm-mjx run: {a.env}, {cfg.method} {cfg.train.preset} preset ({cfg.train.steps} updates of batch '
          f'{cfg.train.batch_size}), {cfg.protocol.episodes} evaluation episodes per task{where}, on '
          f'{jax.devices()[0]}; output in {out}')
    if not a.one_program:
        run.run_stepwise(cfg, out, dataset=a.dataset, collect_episodes=collect_episodes_of(a),
                         collect_batch=a.collect_batch, shift=a.shift, collect_physics=collect_physics_of(a),
                         collect_preset=cfg.protocol.physics_preset)
        return 0
    if a.shift != 'base':
        raise ValueError('--one-program evaluates the base layout; drop --shift')
    from aqm_mjx import memory  # pylint: disable=import-outside-toplevel
    from aqm_mjx.learn import methods  # pylint: disable=import-outside-toplevel

    if isinstance(a.seeds, bool) or a.seeds < 1:
        raise ValueError(f'--seeds must be an integer >= 1; got {a.seeds}')
    env = envs.make(a.env)
    memory.check_training(methods.get(cfg.method), cfg.train, env.obs_size, env.action_size, a.seeds)
    given = assess.read_data(a.dataset, env) if a.dataset else None  # a damaged file is named before any write
    with files.run_lock(out):  # one writer per run folder
        path = run.data_stage(a.env, out, a.dataset, collect_episodes_of(a), a.collect_batch,
                              physics=collect_physics_of(a), physics_preset=cfg.protocol.physics_preset)
        data = given if given is not None else assess.read_data(path, env)
        res = run.run_one_program(cfg, data, a.seeds)
        files.write_json(os.path.join(out, 'one_program.json'), res, makedirs=True)
    print(f'wrote {out}/one_program.json')
    return 0


def collect_episodes_of(a) -> int:
    """--collect-episodes, or the preset's data size when it is not given."""
    from aqm_mjx import pipeline  # pylint: disable=import-outside-toplevel

    return pipeline.collect_episodes(a.preset) if a.collect_episodes is None else a.collect_episodes


def collect_physics_of(a) -> str:
    """--collect-physics, or the preset's (MJX where the host cannot model the maze: the teleport portals)."""
    from aqm_mjx import envs, pipeline  # pylint: disable=import-outside-toplevel

    if a.collect_physics is not None:
        return a.collect_physics
    return 'mjx' if envs.parse_name(a.env)[1] == 'teleport' else pipeline.collect_physics(a.preset)


def cmd_evaluate(a):
    """OGBench's protocol for a trained model, with ablations and test-time shifts in one batch."""
    n_processes = start_processes(a)  # before any other JAX call: every process runs this same command
    enable_compile_cache()
    from aqm_mjx import assess, pipeline  # pylint: disable=import-outside-toplevel

    overrides = overrides_of(a)
    if any(o.startswith('train.') for o in overrides):
        raise ValueError('evaluate: the train settings are the checkpoint\'s; --set takes map., agent. and '
                         'protocol. fields here')
    cfg = None if a.preset is None else pipeline.RunConfig.preset(a.preset)
    from aqm_mjx.assess import preset_for_name  # pylint: disable=import-outside-toplevel
    from aqm_mjx.learn import fit  # pylint: disable=import-outside-toplevel

    named = [a.preset] if a.preset else [preset_for_name(fit.read_meta(c)[1].preset) for c in a.checkpoint]
    host = host_backend(named, overrides) if n_processes == 1 else []
    if host:
        overrides += host
        print("evaluation in OGBench's environments on the host (no accelerator; --backend mjx for MJX)")
    elif any(o.replace(' ', '').split('.')[-1] == 'backend=ogbench' for o in overrides):
        from aqm_mjx import processes  # pylint: disable=import-outside-toplevel

        processes.check_backend('ogbench')
    out = evaluation_out(a.checkpoint, a.out)
    if len(a.checkpoint) == 1:
        assess.evaluate_checkpoint(a.checkpoint[0], cfg, dataset=a.dataset, shift=a.shift, out=out, seed=a.seed,
                                   overrides=overrides)
    else:
        assess.evaluate_checkpoints(a.checkpoint, out, cfg, dataset=a.dataset, shift=a.shift, seed=a.seed,
                                    overrides=overrides)
    return 0


def evaluation_out(checkpoints, out=None) -> str:
    """``evaluate``'s output folder, checked by :func:`aqm_mjx.files.check_output`: ``out``, else
    ``CHECKPOINT/eval`` (several checkpoints: the first one's parent's ``comparison/``); for a shipped
    or exported checkpoint, which is only read, ``runs/eval/NAME`` instead. An output inside a
    checkpoint is allowed beside its ``checkpoints/`` (its ``eval/``), never in them."""
    from aqm_mjx import assess, files  # pylint: disable=import-outside-toplevel

    if out is None:
        out = assess.default_out(checkpoints)
        if files.shipped_above(checkpoints[0]) is not None:
            print(f'{checkpoints[0]} is a shipped checkpoint, only read: the evaluation goes to {out}')
    beside = []  # the checkpoint's own sub-folder that the output lies in, unless it is its checkpoints/
    for c in checkpoints:
        if files.inside(out, c) and not files.inside(out, os.path.join(c, 'checkpoints')):
            rel = os.path.relpath(os.path.realpath(out), os.path.realpath(c))
            if rel != '.':
                beside.append(os.path.join(c, rel.split(os.sep)[0]))
    files.check_output(out, 'results.json', inputs=list(checkpoints), inside_ok=beside)
    return out


def cmd_compare(a):
    """Several methods, seeds vmapped, on the same data and episodes: a table and a bar chart (with
    several processes: each trains its share of the seeds, all evaluate together, process 0 writes)."""
    start_processes(a)  # before any other JAX call: every process runs this same command
    enable_compile_cache()
    from aqm_mjx import compare  # pylint: disable=import-outside-toplevel

    from aqm_mjx import files  # pylint: disable=import-outside-toplevel

    out = a.out or os.path.join('runs', f'compare-{a.env}-{a.style}')
    files.check_output(out, 'compare.json')
    overrides = ((a.set or []) + ([f'protocol.backend={a.backend}'] if a.backend else [])
                 + ([f'protocol.physics_preset={a.physics_preset}'] if a.physics_preset else [])
                 + ([f'protocol.workers={a.workers}'] if a.workers is not None else []))
    compare.compare(a.env, a.methods, a.seeds, out, preset=a.preset, dataset=a.dataset, style=a.style,
                    collect_episodes=collect_episodes_of(a), collect_batch=a.collect_batch,
                    collect_physics=collect_physics_of(a), overrides=overrides,
                    shift=a.shift, first_seed=a.seed, eval_seed=a.eval_seed,
                    collect_preset=named_physics(overrides), planners=a.planners)
    return 0


def cmd_merge(a):
    """Finished comparisons on the same data and episodes as one table."""
    from aqm_mjx import compare  # pylint: disable=import-outside-toplevel

    compare.merge(a.folders, a.out)
    return 0


def cmd_export(a):
    """A run folder made small enough to ship: newest checkpoint and the map's candidate states."""
    enable_compile_cache()
    from aqm_mjx import assess  # pylint: disable=import-outside-toplevel

    from aqm_mjx import files  # pylint: disable=import-outside-toplevel

    files.check_output(a.out, 'map_states.npz', inputs=[a.checkpoint])
    assess.export_checkpoint(a.checkpoint, a.out, dataset=a.dataset, seed=a.seed)
    return 0
