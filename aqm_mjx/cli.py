"""Command line: ``aqm-mjx {run,collect,train,evaluate,compare,merge,methods,rollouts,render,envs}``.

``run`` is the whole pipeline (collect -> train -> keypoints -> evaluate); the other commands are
its stages, or tools. This module only parses arguments: the options of the map, agent and protocol
sections are built from the fields of their configs (help, choices and types included), and every
default comes from a preset of :class:`aqm_mjx.pipeline.RunConfig` or a config class.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time

# Loading a cached CPU executable makes XLA log E-level "Target machine feature +prefer-no-gather is
# not supported" lines listing ~150 CPU features (tuning flags differ, the code runs). Quiet XLA's C++
# log unless the user chose a level. XLA reads the level once, when jaxlib loads, and building the
# parser imports the configs (and jax), so it is set here, before anything else. Python-side errors
# are unaffected.
os.environ.setdefault('TF_CPP_MIN_LOG_LEVEL', '3')


def _enable_compile_cache():
    import jax  # pylint: disable=import-outside-toplevel

    jax.config.update('jax_compilation_cache_dir', os.path.expanduser('~/.cache/aqm_mjx/jax'))
    jax.config.update('jax_persistent_cache_min_compile_time_secs', 1.0)


def cmd_envs(a):
    from aqm_mjx import envs  # pylint: disable=import-outside-toplevel

    for name in envs.ENV_NAMES:
        agent, maze = envs.parse_name(name)
        tasks = envs.mazes.tasks(maze)
        print(f'{name:<22} grid {envs.mazes.layout(maze).shape}  tasks: '
              + ', '.join(f'{t.init_ij}->{t.goal_ij}' for t in tasks))
    return 0


def cmd_render(a):
    import numpy as np  # pylint: disable=import-outside-toplevel

    from aqm_mjx import envs  # pylint: disable=import-outside-toplevel
    from aqm_mjx.envs.render import render_maze, render_panels  # pylint: disable=import-outside-toplevel

    _, maze = envs.parse_name(a.env)
    bad = [d for d in a.deltas or () if not (d > 0 and d < float('inf'))]
    if bad:
        raise ValueError(f'--deltas must be finite numbers > 0; got {bad}')
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


def cmd_rollouts(a):
    """Roll a batch of random-action episodes in MJX and draw them (the environments alone)."""
    _enable_compile_cache()
    import jax  # pylint: disable=import-outside-toplevel
    import jax.numpy as jnp  # pylint: disable=import-outside-toplevel
    import numpy as np  # pylint: disable=import-outside-toplevel
    from tqdm.auto import tqdm  # pylint: disable=import-outside-toplevel

    from aqm_mjx import envs, memory  # pylint: disable=import-outside-toplevel
    from aqm_mjx.envs.render import render_maze  # pylint: disable=import-outside-toplevel

    for name in ('envs', 'steps'):
        if getattr(a, name) < 1:
            raise ValueError(f'--{name} must be >= 1; got {getattr(a, name)}')
    env = envs.make(a.env)
    memory.check(a.envs * (memory.env_state_bytes(env) * memory.FACTOR + 8 * a.steps),
                 f'{a.envs:,} environments x {a.steps:,} steps', '--envs (or --steps)')
    os.makedirs(a.out, exist_ok=True)
    print(f'{env}\ndevice: {jax.devices()[0]}; {a.envs} environments x {a.steps} control steps (random actions)')
    n_tasks = env.num_tasks
    keys = jax.random.split(jax.random.PRNGKey(a.seed), a.envs)
    task_ids = jnp.arange(a.envs) % n_tasks + 1
    t0 = time.perf_counter()
    reset = jax.jit(jax.vmap(env.reset))
    state = reset(keys, task_ids)
    jax.block_until_ready(state)
    t_reset = time.perf_counter() - t0

    chunk = 10

    @jax.jit
    def rollout(state, key):
        def body(s, k):
            a_ = jax.random.uniform(k, (a.envs, env.action_size), minval=-1, maxval=1)
            s = jax.vmap(env.step)(s, a_)
            return s, s.data.qpos[:, :2]
        return jax.lax.scan(body, state, jax.random.split(key, chunk))

    xys = [np.asarray(state.data.qpos[:, :2])[None]]
    key = jax.random.PRNGKey(a.seed + 1)
    t0 = time.perf_counter()
    t_first = None
    for _ in tqdm(range(max(1, a.steps // chunk)), desc='control steps', unit=f'x{chunk}'):
        key, k = jax.random.split(key)
        state, xy = rollout(state, k)
        xys.append(np.asarray(xy))
        if t_first is None:
            t_first = time.perf_counter() - t0
    total = time.perf_counter() - t0
    xys = np.concatenate(xys)
    n_chunks = max(1, a.steps // chunk)
    rate = (n_chunks - 1) * chunk * a.envs / max(total - t_first, 1e-9) if n_chunks > 1 else float('nan')
    png = os.path.join(a.out, f'{a.env}_rollouts.png')
    render_maze(env.layout, png, start_xy=xys[0], goal_xy=np.asarray(state.goal_xy), agent_xy=xys[-1],
                trajectories=[xys[:, i] for i in range(min(a.envs, 16))],
                title=f'{a.env}: {a.envs} MJX rollouts, random actions')
    summary = dict(env=a.env, envs=a.envs, steps=int(n_chunks * chunk), reset_compile_and_run_s=round(t_reset, 2),
                   first_chunk_s_incl_compile=round(t_first, 2), control_steps_per_s=round(rate, 1),
                   successes=int(np.asarray(state.success).sum()), picture=png)
    with open(os.path.join(a.out, 'summary.json'), 'w') as f:
        json.dump(summary, f, indent=1)
    print(json.dumps(summary, indent=1))
    return 0


def cmd_collect(a):
    """Collect an OGBench-format dataset in MJX with the scripted expert."""
    _enable_compile_cache()
    from aqm_mjx import files  # pylint: disable=import-outside-toplevel
    from aqm_mjx.data import collect  # pylint: disable=import-outside-toplevel

    cfg = collect.CollectConfig(env=a.env, style=a.style, episodes=a.episodes, steps=a.steps, noise=a.noise,
                                batch=a.batch, seed=a.seed, layout=a.layout).resolved()
    collect.check_output(a.out, a.overwrite, cfg)  # name, folder and free space before minutes of collection
    collect.check_memory(cfg)
    import jax  # pylint: disable=import-outside-toplevel

    print(f'collecting {cfg.episodes} + {cfg.val_episodes} (val) {cfg.style} episodes x {cfg.steps} states in '
          f'{cfg.env} ({cfg.layout} layout), noise {cfg.noise}, {cfg.batch} at a time on {jax.devices()[0]}')
    physics = {k: v for k, v in (('iterations', a.iterations), ('ls_iterations', a.ls_iterations)) if v is not None}
    res = collect.collect(cfg, physics=physics)
    train, val = collect.write(res, a.out, overwrite=a.overwrite)
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
    del a
    from aqm_mjx.learn import methods  # pylint: disable=import-outside-toplevel

    for m in methods.METHODS.values():
        print(f'{m.name:<10} {m.summary}')
    return 0


def cmd_train(a):
    """Train a method on an OGBench-format dataset."""
    _enable_compile_cache()
    from aqm_mjx import envs  # pylint: disable=import-outside-toplevel
    from aqm_mjx.data import dataset  # pylint: disable=import-outside-toplevel
    from aqm_mjx import memory  # pylint: disable=import-outside-toplevel
    from aqm_mjx.learn import fit, methods  # pylint: disable=import-outside-toplevel

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
        cfg = method.preset(a.preset or 'cpu', style=style, env=env_name, seed=a.seed or 0).with_overrides(sets)
        if cfg.env != env_name:
            raise ValueError(f'--set env={cfg.env}: the environment is {env_name} (from --env or the dataset\'s '
                             'name), which sets the observation size; give --env instead')
        if a.steps is not None:
            cfg = dataclasses.replace(cfg, steps=int(a.steps))
        memory.check(memory.training_bytes(cfg, obs_size, action_size), f'an update of batch {cfg.batch_size:,}',
                     '--set batch_size')
    elif a.method or a.preset or a.seed is not None or sets or a.env:
        # every option given with --resume is checked against the saved run (the same values pass)
        if not os.path.exists(os.path.join(a.out, 'config.json')):
            raise FileNotFoundError(f'{a.out} holds no run to resume (no config.json); start a new run without --resume')
        _, saved, _ = fit.read_meta(a.out)
        fit.check_resume_request(a.out, a.method, None)  # another method first: its fields are not comparable
        base = method.preset(a.preset, style=style, env=saved.env, seed=saved.seed) if a.preset else saved
        changes = ([f'env={a.env}'] if a.env else []) + ([f'seed={a.seed}'] if a.seed is not None else []) + sets
        fit.check_resume_request(a.out, None, base.with_overrides(changes))
    data = dataset.read_ogbench(a.dataset, obs_size=obs_size, action_size=action_size, add_info=False)
    print(f'dataset {a.dataset}: {len(data["terminals"])} states, {int(data["terminals"].sum())} trajectories')
    if cfg is not None:
        print(f'{method.name}, preset {cfg.preset}: {cfg.steps} updates of batch {cfg.batch_size}')
    fit.train(method, cfg, data, a.out, resume=a.resume, steps=a.steps, dataset_path=os.path.abspath(a.dataset))
    print(f'wrote {a.out} (config.json, metrics.jsonl, checkpoints/)')
    return 0


def _section_options(p: argparse.ArgumentParser) -> None:
    """One option per field of the map, agent and protocol configs (``--max-keypoints``), taken as
    text and parsed by the config: unset options keep the preset's value."""
    from aqm_mjx import pipeline  # pylint: disable=import-outside-toplevel

    classes = {s: type(getattr(pipeline.RunConfig(), s)) for s in pipeline.SECTIONS}
    for section, cls in classes.items():
        g = p.add_argument_group(f'{section} ({cls.__name__}; default: the preset\'s)')
        for f in dataclasses.fields(cls):
            kw = dict(dest=f'{section}.{f.name}', default=None, help=f.metadata.get('help', ''))
            if f.metadata.get('choices'):
                kw['choices'] = list(f.metadata['choices'])
            if isinstance(f.default, tuple):
                kw['nargs'] = '*'
            g.add_argument('--' + f.name.replace('_', '-'), **kw)


def _overrides(a) -> list:
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
                                     style=style).with_overrides(_overrides(a))


def cmd_run(a):
    """The whole pipeline: data -> train -> keypoints -> evaluate (step by step, or as one program)."""
    _enable_compile_cache()
    import jax  # pylint: disable=import-outside-toplevel

    from aqm_mjx import envs, files, run  # pylint: disable=import-outside-toplevel

    cfg = run_config(a)
    out = a.out or os.path.join('runs', a.env)
    print(f'aqm-mjx run: {a.env}, {cfg.method} {cfg.train.preset} preset ({cfg.train.steps} updates of batch '
          f'{cfg.train.batch_size}), {cfg.protocol.episodes} evaluation episodes per task, on {jax.devices()[0]}; '
          f'output in {out}')
    if not a.one_program:
        run.run_stepwise(cfg, out, dataset=a.dataset, collect_episodes=_collect_episodes(a),
                         collect_batch=a.collect_batch, shift=a.shift)
        return 0
    if a.shift != 'base':
        raise ValueError('--one-program evaluates the base layout; drop --shift')
    with files.run_lock(out):  # one writer per run folder
        path = run.data_stage(a.env, out, a.dataset, _collect_episodes(a), a.collect_batch)
        data = run.read_data(path, envs.make(a.env))
        res = run.run_one_program(cfg, data, a.seeds)
        files.write_json(os.path.join(out, 'one_program.json'), res, makedirs=True)
    print(f'wrote {out}/one_program.json')
    return 0


def _collect_episodes(a) -> int:
    """--collect-episodes, or the preset's data size when it is not given."""
    from aqm_mjx import pipeline  # pylint: disable=import-outside-toplevel

    return pipeline.collect_episodes(a.preset) if a.collect_episodes is None else a.collect_episodes


def cmd_evaluate(a):
    """OGBench's protocol for a trained model, with ablations and test-time shifts in one batch."""
    if a.distributed:
        import jax  # pylint: disable=import-outside-toplevel

        jax.distributed.initialize()  # before any other JAX call: every host runs this same command
    _enable_compile_cache()
    from aqm_mjx import pipeline, run  # pylint: disable=import-outside-toplevel

    overrides = _overrides(a)
    if any(o.startswith('train.') for o in overrides):
        raise ValueError('evaluate: the train settings are the checkpoint\'s; --set takes map., agent. and '
                         'protocol. fields here')
    cfg = None if a.preset is None else pipeline.RunConfig.preset(a.preset)
    if len(a.checkpoint) == 1:
        run.evaluate_checkpoint(a.checkpoint[0], cfg, dataset=a.dataset, shift=a.shift, out=a.out, seed=a.seed,
                                overrides=overrides)
    else:
        out = a.out or os.path.join(os.path.dirname(os.path.normpath(a.checkpoint[0])), 'comparison')
        run.evaluate_checkpoints(a.checkpoint, out, cfg, dataset=a.dataset, shift=a.shift, seed=a.seed,
                                 overrides=overrides)
    return 0


def cmd_compare(a):
    """Several methods, seeds vmapped, on the same data and episodes: a table and a bar chart."""
    _enable_compile_cache()
    from aqm_mjx import compare  # pylint: disable=import-outside-toplevel

    out = a.out or os.path.join('runs', f'compare-{a.env}-{a.style}')
    compare.compare(a.env, a.methods, a.seeds, out, preset=a.preset, dataset=a.dataset, style=a.style,
                    collect_episodes=_collect_episodes(a), collect_batch=a.collect_batch,
                    overrides=(a.set or []) + ([f'protocol.backend={a.backend}'] if a.backend else [])
                    + ([f'protocol.workers={a.workers}'] if a.workers is not None else []),
                    shift=a.shift, first_seed=a.seed, eval_seed=a.eval_seed)
    return 0


def cmd_merge(a):
    """Finished comparisons on the same data and episodes as one table."""
    from aqm_mjx import compare  # pylint: disable=import-outside-toplevel

    compare.merge(a.folders, a.out)
    return 0


def _one_line(err: BaseException) -> str:
    """An error as the one line the user reads: an OS error as ``path: reason``."""
    if isinstance(err, OSError) and err.strerror and err.filename:
        return f'{err.filename}: {err.strerror}'
    text = ' '.join(str(err).split())
    return text or type(err).__name__


def build_parser() -> argparse.ArgumentParser:
    """The ``aqm-mjx`` command line: one subcommand per job, each with its ``fn``."""
    from aqm_mjx import pipeline  # pylint: disable=import-outside-toplevel
    from aqm_mjx.learn import methods  # pylint: disable=import-outside-toplevel

    presets = list(pipeline.PRESETS)
    import aqm_mjx  # pylint: disable=import-outside-toplevel

    p = argparse.ArgumentParser(prog='aqm-mjx', description='Adaptive Quasimetric Mapping on MuJoCo MJX.')
    p.add_argument('--version', action='version', version=f'aqm-mjx {aqm_mjx.__version__}')
    sub = p.add_subparsers(dest='cmd', required=True)
    r = sub.add_parser(
        'run', help='the whole pipeline: collect (or --dataset) -> train -> keypoints -> evaluate',
        description='Collect a navigate dataset in MJX (or use --dataset), train a method, select keypoints, and '
                    'evaluate AQM and its ablations with OGBench\'s protocol. Each stage shows its progress; '
                    'training checkpoints, so re-running the same command after an interrupt resumes. Writes '
                    'OUT/run.json, OUT/summary.json and OUT/eval/*.png. --one-program runs training, keypoints '
                    'and evaluation as one jitted program, vmapped over --seeds.')
    r.add_argument('--env', default='antmaze-medium', help='environment name (see `aqm-mjx envs`)')
    r.add_argument('--method', default='aqm', choices=methods.names(), help='registered method (aqm-mjx methods)')
    r.add_argument('--preset', default='cpu', choices=presets,
                   help='every default of the run: cpu (minutes on a 2-core CPU), cpu-long (about an hour: 400 '
                        'episodes, 50,000 updates), paper (the paper\'s sizes; for a GPU), ci (seconds; tests)')
    r.add_argument('--set', action='append', metavar='SECTION.FIELD=VALUE',
                   help='override any config field, e.g. --set train.batch_size=512 --set map.delta=10 (a field '
                        'name alone where it is unique: --set steps=400); repeatable')
    r.add_argument('--out', default=None, help='run folder (default runs/ENV)')
    r.add_argument('--dataset', default=None, help='an OGBench-format .npz to train on instead of collecting')
    r.add_argument('--collect-episodes', type=int, default=None,
                   help="navigate episodes to collect (1001 states each; default: the preset's, 100 or 400 for cpu-long)")
    r.add_argument('--collect-batch', type=int, default=55,
                   help='episodes collected side by side (default: the 100 + 10 of the default run in 2 calls)')
    r.add_argument('--shift', default='base', help="evaluation layout: base, all, closures, a variant (close-I-J), or several joined by commas")
    r.add_argument('--seed', type=int, default=0, help='run seed: PRNGKey(seed) is split into train, map, evaluation')
    r.add_argument('--one-program', action='store_true',
                   help='train, select keypoints and evaluate as one jitted program (no checkpoints)')
    r.add_argument('--seeds', type=int, default=1, help='with --one-program: seeds vmapped in the one program')
    _section_options(r)
    r.set_defaults(fn=cmd_run)
    o = sub.add_parser('rollouts', help='random-action MJX rollouts and a picture (the environments alone)')
    o.add_argument('--env', default='antmaze-medium', help='environment name (see `aqm-mjx envs`)')
    o.add_argument('--envs', type=int, default=16, help='parallel environments')
    o.add_argument('--steps', type=int, default=100, help='control steps per environment')
    o.add_argument('--seed', type=int, default=0, help='random seed')
    o.add_argument('--out', default='runs/rollouts', help='output folder (picture and summary.json)')
    o.set_defaults(fn=cmd_rollouts)
    e = sub.add_parser('envs', help='list the environments and their evaluation tasks')
    e.set_defaults(fn=cmd_envs)
    m = sub.add_parser('methods', help='list the registered methods')
    m.set_defaults(fn=cmd_methods)
    d = sub.add_parser('render', help='draw a maze with its evaluation tasks (or keypoint maps) as a PNG')
    d.add_argument('--env', default='antmaze-medium')
    d.add_argument('--out', default='maze.png')
    d.add_argument('--deltas', type=float, nargs='*', default=None,
                   help='draw IWE keypoint maps for these delta values (m), with the exact maze distance')
    d.set_defaults(fn=cmd_render)
    c = sub.add_parser(
        'collect', help='collect an OGBench-format dataset in MJX with the scripted expert',
        description='Collect a dataset with OGBench\'s recipe: the scripted ant trot (or the point agent\'s '
                    'direct move) steered along BFS waypoints, run in MJX, written as OGBench .npz plus the '
                    '-val twin (a tenth as many episodes), a PNG of some trajectories and a JSON summary.')
    c.add_argument('--env', default='antmaze-medium', help='environment, e.g. antmaze-medium, antmaze-large, pointmaze-medium')
    c.add_argument('--style', default='navigate', choices=['navigate', 'stitch', 'explore'],
                   help='navigate: a new junction-cell goal each time one is reached (noise 0.2); stitch: a goal '
                        'exactly 4 BFS cells away, 201-state episodes; explore: a random direction redrawn '
                        'every 10 steps (noise 1.0)')
    c.add_argument('--episodes', type=int, default=None,
                   help="training episodes (default OGBench's: 1000 navigate, 500 giant navigate, 5000 stitch, "
                        '10000 explore); validation adds a tenth')
    c.add_argument('--steps', type=int, default=None,
                   help="states per episode (default OGBench's: 1001 navigate, 2001 giant, 201 stitch, 501 explore)")
    c.add_argument('--noise', type=float, default=None, help='Gaussian action noise (default 0.2, explore 1.0)')
    c.add_argument('--batch', type=int, default=64,
                   help='episodes simulated side by side (CPU: 64 to 256; GPU: thousands)')
    c.add_argument('--seed', type=int, default=0, help='random seed (episode e uses fold_in(seed, e))')
    c.add_argument('--layout', default='base',
                   help="walls of the data: 'base' or a shifted layout (close-I-J, open-I-J: the names of evaluate --shift)")
    c.add_argument('--iterations', type=int, default=None,
                   help="MJX solver iterations (default MuJoCo's: 100); fewer trade fidelity for speed")
    c.add_argument('--ls-iterations', type=int, default=None, help="MJX line-search iterations (default MuJoCo's: 50)")
    c.add_argument('--out', required=True, help='output .npz (the -val twin, .png and .json go beside it)')
    c.add_argument('--overwrite', action='store_true', help='replace existing output files')
    c.set_defaults(fn=cmd_collect)
    t = sub.add_parser('train', help='train a method on a dataset (Orbax checkpoints)',
                       description='Train a registered method (default AQM: quasimetric IQE + QRL, Q-AWR target and '
                                   'Q-SAW main policies) on an OGBench-format .npz. Writes OUT/config.json, '
                                   'OUT/metrics.jsonl (JSON lines) and Orbax checkpoints in OUT/checkpoints.')
    t.add_argument('--dataset', required=True, help='OGBench .npz (e.g. antmaze-large-navigate-v0.npz)')
    t.add_argument('--env', default=None,
                   help='environment; inferred from a file name such as antmaze-large-navigate-v0.npz when omitted')
    t.add_argument('--method', default=None, choices=methods.names(),
                   help='registered method (aqm-mjx methods; default aqm)')
    t.add_argument('--preset', default=None, choices=presets,
                   help='cpu: minutes on a 2-core CPU; cpu-long: 50,000 updates; paper: Appendix 10 sizes (3x512, batch 1024, 1e6 updates); '
                        'ci: smoke tests (default cpu)')
    t.add_argument('--set', action='append', metavar='FIELD=VALUE',
                   help='override a training config field, e.g. --set batch_size=512 --set q_hidden=512,512 (repeatable)')
    t.add_argument('--steps', type=int, default=None, help='total updates (overrides the preset; extends a resumed run)')
    t.add_argument('--seed', type=int, default=None, help='initialisation seed (default 0)')
    t.add_argument('--out', required=True, help='run folder')
    t.add_argument('--resume', action='store_true',
                   help='continue the run in --out from its newest readable checkpoint with its saved config: '
                        'other options must agree with it (--steps may extend it), and the dataset must be the '
                        'one it was trained on (by fingerprint)')
    t.set_defaults(fn=cmd_train)
    v = sub.add_parser(
        'evaluate', help='evaluate a trained model: OGBench protocol, ablations and shifts in one batch',
        description='OGBench protocol: every task, --episodes each, deterministic actions clipped to [-1, 1], '
                    'success at the last step. The AQM agent, its ablations and every shifted layout run as rows '
                    'of one batch, --envs environments per jitted call, sharded over all devices. Defaults: the '
                    'run preset of the checkpoint\'s training preset (--preset to choose another). Writes '
                    'OUT/results.json, success.png, trajectories.png and, with several layouts, heatmap.png.')
    v.add_argument('--checkpoint', required=True, action='append',
                   help='run folder written by `aqm-mjx train` (or RUN/train); repeat it to put several checkpoints '
                        '(any methods, one environment) on the same episodes')
    v.add_argument('--dataset', default=None, help='states to select keypoints from (default: the training dataset)')
    v.add_argument('--shift', default='base',
                   help="layout: 'base', 'all' (the maze's shift suite), 'closures' (base and the suite's closed "
                        "corridors), one variant such as close-3-3, or several joined by commas")
    v.add_argument('--preset', default=None, choices=presets,
                   help="map, agent and protocol defaults (default: the checkpoint's training preset)")
    v.add_argument('--set', action='append', metavar='SECTION.FIELD=VALUE',
                   help='override a map, agent or protocol field, e.g. --set agent.kappa=0.5 (repeatable)')
    v.add_argument('--seed', type=int, default=0,
                   help='PRNGKey(seed) split as in `aqm-mjx run`: the same seed gives the same map and episodes')
    v.add_argument('--out', default=None, help='output folder (default CHECKPOINT/eval; with several checkpoints '
                                               "the first one's parent/comparison)")
    v.add_argument('--distributed', action='store_true',
                   help='multi-host: call jax.distributed.initialize() first (run the same command on every host)')
    _section_options(v)
    v.set_defaults(fn=cmd_evaluate)
    k = sub.add_parser(
        'compare', help='several methods x seeds on the same data and episodes: table and bar chart',
        description='Collect (or --dataset) once, train every method with --seeds seeds (vmapped in one program '
                    'per method), evaluate every checkpoint on the same episodes, and write OUT/results.json, '
                    'OUT/table.md and OUT/success.png: per-method mean success with 95% intervals over seeds '
                    'and over episodes. Re-running the same command after an interrupt resumes: finished methods '
                    'are not trained or evaluated again.')
    k.add_argument('--env', default='antmaze-medium', help='environment name (see `aqm-mjx envs`)')
    from aqm_mjx import compare  # pylint: disable=import-outside-toplevel

    k.add_argument('--methods', nargs='+', default=list(compare.DEFAULT_METHODS), choices=methods.names(),
                   metavar='METHOD', help=f'registered methods (default: {" ".join(compare.DEFAULT_METHODS)})')
    k.add_argument('--seeds', type=int, default=2, help='training seeds per method (vmapped)')
    k.add_argument('--seed', type=int, default=0, help='the first seed: seeds are SEED, SEED+1, ...')
    k.add_argument('--eval-seed', type=int, default=0, help='PRNGKey of the map and the episodes, shared by all')
    k.add_argument('--preset', default='cpu', choices=presets, help='every default of each method\'s run')
    k.add_argument('--set', action='append', metavar='[METHOD:]SECTION.FIELD=VALUE',
                   help='override a field for every method (--set steps=4000 --set protocol.episodes=10), or '
                        'for one (--set gciql:alpha=0.1); repeatable')
    k.add_argument('--dataset', default=None, help='an OGBench-format .npz instead of collecting')
    k.add_argument('--style', default='navigate', choices=['navigate', 'stitch', 'explore'],
                   help='the dataset to collect (taken from the file name with --dataset)')
    k.add_argument('--collect-episodes', type=int, default=None,
                   help="episodes to collect (default: the preset's, 100 or 400 for cpu-long)")
    k.add_argument('--collect-batch', type=int, default=55, help='episodes collected side by side')
    k.add_argument('--shift', default='base', help="evaluation layout: base, all, closures, a variant (close-I-J), or several joined by commas")
    k.add_argument('--backend', default=None, choices=['mjx', 'ogbench'],
                   help="physics of the evaluation: 'mjx' (default) or 'ogbench' (OGBench's own environments on "
                        'the host; same as --set protocol.backend=ogbench)')
    k.add_argument('--workers', type=int, default=None, help="with --backend ogbench: processes stepping the "
                                                             'environments (default 0: this process)')
    k.add_argument('--out', default=None, help='comparison folder (default runs/compare-ENV-STYLE)')
    k.set_defaults(fn=cmd_compare)
    g = sub.add_parser(
        'merge', help='one table from several compare folders on the same data and episodes',
        description='Put the rows of finished `aqm-mjx compare` folders into one table (OUT/results.json, '
                    'OUT/table.md, OUT/success.png), after checking that they share the data (SHA-256), seeds, '
                    'episode key, layout, tasks, episodes and the overrides given to every method. Each method '
                    'comes from one folder; the folders are only read.')
    g.add_argument('folders', nargs='+', metavar='FOLDER', help='comparison folders (aqm-mjx compare --out)')
    g.add_argument('--out', required=True, help='folder of the merged table (not one of the comparisons)')
    g.set_defaults(fn=cmd_merge)
    return p


def main(argv=None):
    a = build_parser().parse_args(argv)
    from aqm_mjx import files  # pylint: disable=import-outside-toplevel

    files.COMMAND[:] = ['aqm-mjx'] + list(sys.argv[1:] if argv is None else argv)  # provenance and lock files
    try:
        return a.fn(a)
    except (ValueError, TypeError, OSError, RuntimeError) as err:
        print(f'aqm-mjx: error: {_one_line(err)}', file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        # files are written atomically and checkpoints are complete or absent: nothing half-written
        again = ('the same command with --resume' if a.cmd == 'train' and not getattr(a, 'resume', False)
                 else 'the same command again')
        print(f'\naqm-mjx {a.cmd}: interrupted. Run {again} to resume (training continues from its last '
              'checkpoint; finished stages are not redone).', file=sys.stderr)
        return 130


if __name__ == '__main__':
    raise SystemExit(main())
