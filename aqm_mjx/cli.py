"""Command line: ``aqm-mjx {run,collect,train,evaluate,rollouts,render,envs}``.

``run`` is the whole pipeline (collect -> train -> keypoints -> evaluate); the other commands are
its stages, or tools.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time


def _enable_compile_cache():
    # Loading a cached CPU executable makes XLA log an E-level "machine type ... doesn't match" line
    # listing ~150 CPU features (tuning flags differ, the code runs). Quiet XLA's C++ log unless the
    # user chose a level; Python-side errors are unaffected.
    os.environ.setdefault('TF_CPP_MIN_LOG_LEVEL', '3')
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


def keypoint_map_panels(maze: str, deltas, n_candidates: int = 20000, sub: int = 4, seed: int = 0):
    """IWE keypoints and tau = 2 delta edges with the exact maze distance as the quasimetric, one
    panel per delta (the paper's Figures 11-13, with a stand-in for a trained quasimetric)."""
    import jax  # pylint: disable=import-outside-toplevel
    import jax.numpy as jnp  # pylint: disable=import-outside-toplevel
    import numpy as np  # pylint: disable=import-outside-toplevel

    from aqm_mjx import graph, keypoints  # pylint: disable=import-outside-toplevel
    from aqm_mjx.envs import mazes  # pylint: disable=import-outside-toplevel

    grid = mazes.layout(maze)
    table = jnp.asarray(mazes.geodesic_table(grid, sub))
    rng = np.random.default_rng(seed)
    free = np.argwhere(grid == 0)
    xy = mazes.ij_to_xy(free[rng.integers(len(free), size=n_candidates)]) + rng.uniform(-1.9, 1.9, (n_candidates, 2))
    cand = jnp.asarray(mazes.xy_to_subcell(xy, grid.shape, sub))[:, None]

    def lookup(table):
        return lambda x, y: table[x[0], y[0]]

    # The table and candidates are arguments: captured as constants XLA would constant-fold them.
    select = jax.jit(lambda table, cand, key, delta: keypoints.iwe(lookup(table), cand, key, delta, 512))
    dist = lookup(table)
    panels = []
    for delta in deltas:
        kp = select(table, cand, jax.random.PRNGKey(seed), float(delta))
        idx = np.asarray(kp.index)[np.asarray(kp.mask)]
        w = graph.build_graph(dist, cand[jnp.asarray(idx)], jnp.ones(len(idx), bool), float(delta))
        _, ncomp = graph.components(w, jnp.ones(len(idx), bool))
        panels.append(dict(nodes_xy=xy[idx], edges=graph.edge_list(w),
                           title=f'delta {delta:g} m: {len(idx)} keypoints, {int(ncomp)} component(s)'))
    return grid, panels


def cmd_render(a):
    import numpy as np  # pylint: disable=import-outside-toplevel

    from aqm_mjx import envs  # pylint: disable=import-outside-toplevel
    from aqm_mjx.envs.render import render_maze, render_panels  # pylint: disable=import-outside-toplevel

    _, maze = envs.parse_name(a.env)
    if a.deltas:
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

    from aqm_mjx import envs  # pylint: disable=import-outside-toplevel
    from aqm_mjx.envs.render import render_maze  # pylint: disable=import-outside-toplevel

    os.makedirs(a.out, exist_ok=True)
    env = envs.make(a.env)
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
    from aqm_mjx import collect  # pylint: disable=import-outside-toplevel

    collect.check_output(a.out, a.overwrite)  # before minutes of collection, not after
    cfg = collect.CollectConfig(env=a.env, style=a.style, episodes=a.episodes, steps=a.steps, noise=a.noise,
                                batch=a.batch, seed=a.seed).resolved()
    import jax  # pylint: disable=import-outside-toplevel

    print(f'collecting {cfg.episodes} + {cfg.val_episodes} (val) {cfg.style} episodes x {cfg.steps} states in '
          f'{cfg.env}, noise {cfg.noise}, {cfg.batch} at a time on {jax.devices()[0]}')
    physics = {k: v for k, v in (('iterations', a.iterations), ('ls_iterations', a.ls_iterations)) if v is not None}
    res = collect.collect(cfg, physics=physics)
    train, val = collect.write(res, a.out, overwrite=a.overwrite)
    png = a.out[:-4] + '.png'
    collect.plot(res, png)
    res.stats.update(train=train, val=val if cfg.val_episodes else None, picture=png)
    with open(a.out[:-4] + '.json', 'w') as f:
        json.dump(res.stats, f, indent=1)
    print(json.dumps(res.stats, indent=1))
    return 0


def cmd_train(a):
    """Train the quasimetric and the policies on an OGBench-format dataset."""
    _enable_compile_cache()
    from aqm_mjx import dataset, envs, train  # pylint: disable=import-outside-toplevel

    try:
        inferred, style = train.infer_env(a.dataset)
    except ValueError:
        if a.env is None and not a.resume:
            raise
        inferred, style = None, None
    env_name = a.env or inferred
    cfg = None
    obs_size = action_size = None
    if not a.resume:
        env = envs.make(env_name)
        obs_size, action_size = env.obs_size, env.action_size
        over = {'env': env_name, 'seed': a.seed}
        if style == 'explore':
            over['policy_goals'] = 'random'  # AQM: uniform random goals on explore datasets
        cfg = train.TrainConfig.preset(a.preset, **over).with_overrides(a.set or [])
    data = dataset.read_ogbench(a.dataset, obs_size=obs_size, action_size=action_size, add_info=False)
    print(f'dataset {a.dataset}: {len(data["terminals"])} states, {int(data["terminals"].sum())} trajectories')
    if cfg is not None:
        print(f'preset {cfg.preset}: {cfg.steps} updates of batch {cfg.batch_size}, quasimetric {cfg.q_hidden} -> '
              f'{cfg.n_components}x{cfg.component_size}, policies {cfg.pi_hidden}, objective {cfg.objective}, '
              f'push offset {cfg.offset}')
    train.train(cfg, data, a.out, resume=a.resume, steps=a.steps, dataset_path=os.path.abspath(a.dataset))
    print(f'wrote {a.out} (config.json, metrics.jsonl, checkpoints/)')
    return 0


def _given(**options) -> dict:
    """The options the user set (``None``: not given, so the config class's default applies)."""
    return {k: v for k, v in options.items() if v is not None}


def _run_config(a):
    from aqm_mjx import evaluate, pipeline, train  # pylint: disable=import-outside-toplevel

    tcfg = train.TrainConfig.preset(a.preset, env=a.env, seed=a.seed).with_overrides(a.set or [])
    ecfg = evaluate.EvalConfig(episodes=a.eval_episodes, steps=a.eval_steps, envs=a.envs, seed=a.seed,
                               **_given(delta=a.delta))
    return pipeline.RunConfig(train=tcfg, eval=ecfg)


def cmd_run(a):
    """The whole pipeline: data -> train -> keypoints -> evaluate (step by step, or as one program)."""
    _enable_compile_cache()
    import jax  # pylint: disable=import-outside-toplevel

    from aqm_mjx import dataset, envs, pipeline  # pylint: disable=import-outside-toplevel
    from aqm_mjx.checkpoint import write_json  # pylint: disable=import-outside-toplevel

    envs.parse_name(a.env)
    cfg = _run_config(a)
    out = a.out or os.path.join('runs', a.env)
    print(f'aqm-mjx run: {a.env}, {cfg.train.preset} preset ({cfg.train.steps} updates of batch '
          f'{cfg.train.batch_size}), {cfg.eval.episodes} evaluation episodes per task, on {jax.devices()[0]}; '
          f'output in {out}')
    if not a.one_program:
        pipeline.run_stepwise(cfg, a.env, out, dataset=a.dataset, episodes=a.episodes, collect_batch=a.collect_batch,
                              seed=a.seed, shift=a.shift)
        return 0
    if a.shift != 'base':
        raise ValueError('--one-program evaluates the base layout; drop --shift')
    path = pipeline.data_stage(a.env, out, a.dataset, a.episodes, a.collect_batch)
    env = envs.make(a.env)
    data = dataset.read_ogbench(path, obs_size=env.obs_size, action_size=env.action_size, add_info=False)
    res = pipeline.run_one_program(cfg, a.env, data, a.seeds, a.seed)
    os.makedirs(out, exist_ok=True)
    write_json(os.path.join(out, 'one_program.json'), res)
    print(f'wrote {out}/one_program.json')
    return 0


def cmd_evaluate(a):
    """OGBench's protocol for a trained model, with ablations and test-time shifts in one batch."""
    if a.distributed:
        import jax  # pylint: disable=import-outside-toplevel

        jax.distributed.initialize()  # before any other JAX call: every host runs this same command
    _enable_compile_cache()
    from aqm_mjx import evaluate  # pylint: disable=import-outside-toplevel

    cfg = evaluate.EvalConfig(episodes=a.episodes, tasks=tuple(a.tasks or ()), steps=a.steps, envs=a.envs,
                              ablations=tuple(a.ablations), tau=a.tau, max_keypoints=a.max_keypoints,
                              candidates=a.candidates, selector=a.selector, seed=a.seed,
                              **_given(kappa=a.kappa, delta=a.delta, switch_radius=a.switch_radius))
    evaluate.run_cli(a.checkpoint, cfg, dataset=a.dataset, shift=a.shift, out=a.out)
    return 0


def main(argv=None):
    p = argparse.ArgumentParser(prog='aqm-mjx', description='Adaptive Quasimetric Mapping on MuJoCo MJX.')
    sub = p.add_subparsers(dest='cmd', required=True)
    r = sub.add_parser(
        'run', help='the whole pipeline: collect (or --dataset) -> train -> keypoints -> evaluate',
        description='Collect a navigate dataset in MJX (or use --dataset), train the quasimetric and policies, '
                    'select keypoints, and evaluate AQM and its ablations with OGBench\'s protocol. Each stage '
                    'shows its progress; training checkpoints, so re-running the same command after an interrupt '
                    'resumes. Writes OUT/summary.json and OUT/eval/*.png. --one-program runs training, keypoints '
                    'and evaluation as one jitted program, vmapped over --seeds.')
    r.add_argument('--env', default='antmaze-medium', help='environment name (see `aqm-mjx envs`)')
    r.add_argument('--out', default=None, help='run folder (default runs/ENV)')
    r.add_argument('--dataset', default=None, help='an OGBench-format .npz to train on instead of collecting')
    r.add_argument('--episodes', type=int, default=100, help='navigate episodes to collect (1001 states each)')
    r.add_argument('--collect-batch', type=int, default=55,
                   help='episodes collected side by side (default: the 100 + 10 of the default run in 2 calls)')
    r.add_argument('--preset', default='cpu', choices=['cpu', 'paper', 'tiny'],
                   help='training scale: cpu (minutes on a 2-core CPU), paper (Appendix 10; for a GPU), tiny')
    r.add_argument('--set', action='append', metavar='KEY=VALUE', help='override a training config field')
    r.add_argument('--eval-episodes', type=int, default=4, help='evaluation episodes per task (OGBench: 50)')
    r.add_argument('--eval-steps', type=int, default=0, help='control steps per evaluation episode (0: env limit)')
    r.add_argument('--envs', type=int, default=64, help='environments per jitted evaluation call')
    r.add_argument('--delta', type=float, default=None, help="IWE repel radius (quasimetric units; default: EvalConfig's)")
    r.add_argument('--shift', default='base', help="evaluation layout: base, all, or a variant (close-I-J)")
    r.add_argument('--seed', type=int, default=0)
    r.add_argument('--one-program', action='store_true',
                   help='train, select keypoints and evaluate as one jitted program (no checkpoints)')
    r.add_argument('--seeds', type=int, default=1, help='with --one-program: seeds vmapped in the one program')
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
    c.add_argument('--iterations', type=int, default=None,
                   help="MJX solver iterations (default MuJoCo's: 100); fewer trade fidelity for speed")
    c.add_argument('--ls-iterations', type=int, default=None, help="MJX line-search iterations (default MuJoCo's: 50)")
    c.add_argument('--out', required=True, help='output .npz (the -val twin, .png and .json go beside it)')
    c.add_argument('--overwrite', action='store_true', help='replace existing output files')
    c.set_defaults(fn=cmd_collect)
    t = sub.add_parser('train', help='train the quasimetric and the policies on a dataset (Orbax checkpoints)',
                       description='Train AQM\'s quasimetric (IQE + QRL) and policies (Q-AWR target, Q-SAW main) '
                                   'on an OGBench-format .npz. Writes OUT/config.json, OUT/metrics.jsonl (JSON lines) '
                                   'and Orbax checkpoints in OUT/checkpoints.')
    t.add_argument('--dataset', required=True, help='OGBench .npz (e.g. antmaze-large-navigate-v0.npz)')
    t.add_argument('--env', default=None,
                   help='environment; inferred from a file name such as antmaze-large-navigate-v0.npz when omitted')
    t.add_argument('--preset', default='cpu', choices=['cpu', 'paper', 'tiny'],
                   help='cpu: minutes on a 2-core CPU; paper: Appendix 10 sizes (3x512, batch 1024, 1e6 updates); '
                        'tiny: smoke tests')
    t.add_argument('--set', action='append', metavar='KEY=VALUE',
                   help='override a config field, e.g. --set batch_size=512 --set q_hidden=512,512 (repeatable)')
    t.add_argument('--steps', type=int, default=None, help='total updates (overrides the preset; extends a resumed run)')
    t.add_argument('--seed', type=int, default=0)
    t.add_argument('--out', required=True, help='run folder')
    t.add_argument('--resume', action='store_true',
                   help='continue the run in --out from its newest readable checkpoint (its saved config is used)')
    t.set_defaults(fn=cmd_train)
    v = sub.add_parser(
        'evaluate', help='evaluate a trained model: OGBench protocol, ablations and shifts in one batch',
        description='OGBench protocol: every task, --episodes each, deterministic actions clipped to [-1, 1], '
                    'success at the last step. The AQM agent, its ablations and every shifted layout run as rows '
                    'of one batch, --envs environments per jitted call, sharded over all devices. Writes '
                    'OUT/results.json, success.png, trajectories.png and, with several layouts, heatmap.png.')
    v.add_argument('--checkpoint', required=True, help='run folder written by `aqm-mjx train`')
    v.add_argument('--dataset', default=None, help='states to select keypoints from (default: the training dataset)')
    v.add_argument('--envs', type=int, default=1024, help='environments per jitted call (GPU: thousands)')
    v.add_argument('--episodes', type=int, default=50, help='episodes per task, agent and layout (OGBench: 50)')
    v.add_argument('--tasks', type=int, nargs='*', default=None, help='task ids (default: all five)')
    v.add_argument('--steps', type=int, default=0, help='control steps per episode (default: the env limit, 1000)')
    v.add_argument('--shift', default='base',
                   help="layout: 'base', 'all' (the maze's shift suite), or one variant such as close-3-3")
    v.add_argument('--kappa', type=float, default=None, help="budget slack of the AQM agent (default: EvalConfig's)")
    v.add_argument('--ablations', nargs='*', default=['no-pruning', 'flat'],
                   help="extra agents in the same batch: no-pruning, flat, kappa=X (none: pass the flag empty)")
    v.add_argument('--delta', type=float, default=None, help="IWE repel radius (quasimetric units; default: EvalConfig's)")
    v.add_argument('--tau', type=float, default=0.0, help='edge and attachment radius (default 2 delta)')
    v.add_argument('--switch-radius', type=float, default=None,
                   help="d(s, z) at which a keypoint counts as reached (default: EvalConfig's)")
    v.add_argument('--max-keypoints', type=int, default=256)
    v.add_argument('--candidates', type=int, default=10_000, help='dataset states encoded as IWE candidates')
    v.add_argument('--selector', default='iwe', choices=['iwe', 'fps', 'random'])
    v.add_argument('--seed', type=int, default=0)
    v.add_argument('--out', default=None, help='output folder (default CHECKPOINT/eval)')
    v.add_argument('--distributed', action='store_true',
                   help='multi-host: call jax.distributed.initialize() first (run the same command on every host)')
    v.set_defaults(fn=cmd_evaluate)
    a = p.parse_args(argv)
    try:
        return a.fn(a)
    except (ValueError, TypeError, FileExistsError, FileNotFoundError, RuntimeError) as err:
        print(f'aqm-mjx: error: {err}', file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        # files are written atomically and checkpoints are complete or absent: nothing half-written
        print(f'\naqm-mjx {a.cmd}: interrupted. Run the same command again to resume (training continues '
              'from its last checkpoint; finished stages are not redone).', file=sys.stderr)
        return 130


if __name__ == '__main__':
    raise SystemExit(main())
