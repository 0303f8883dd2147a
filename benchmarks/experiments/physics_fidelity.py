"""Which physics keeps the task: every named setting of :mod:`aqm_mjx.envs.physics` against OGBench's.

    python benchmarks/experiments/physics_fidelity.py --out runs/fidelity                     # CPU, parts below
    python benchmarks/experiments/physics_fidelity.py --parts cost --settings ogbench fast    # one part, two rows
    python benchmarks/experiments/physics_fidelity.py --tiny --out /tmp/fid                   # the script's own test

The control step stays OGBench's 0.1 s in every row; a row changes the integrator and its dt, the
Newton solver's iterations and line search, or the contact caps. Parts (``--parts``):

- ``cost``: physics control steps/s (``jit(vmap(env.physics_step))`` in contact, random actions,
  ``--batch`` environments) and the whole agent's (the shipped checkpoint's evaluation program on
  a fully connected keypoint graph, :mod:`benchmarks/throughput/bench_evaluate`), each with its
  compile time apart; the ratio to the ``ogbench`` row of the same run.
- ``openloop`` (``--host-row``: the reference replayed from its own recorded float32 states, the
  floor that chaos alone sets): ``--episodes`` navigate episodes of the scripted expert collected in OGBench's
  physics in MuJoCo's C library on the host (OGBench's static walls, float64), then their recorded
  actions replayed in MJX at each setting from the same recorded states: the x-y gap to the host's
  trajectory after 10, 100 and 1,000 control steps (windows starting every 100 steps for 10 and
  100), and the episodes whose torso ends upside down (host: the reference's own count). The
  ``ogbench`` row is the floor: the same physics in float32 MJX with wall proxies.
- ``hostgait``: the trot on flat ground in MuJoCo's C library for a grid of integrators, dt and
  solver settings wider than the rows (which settings keep the gait at all, without MJX).
- ``expert``: the scripted expert in MJX at each setting: flat-ground speed along the command and
  flips (``--flat-dirs`` directions, 200 steps, noise 0.2), the waypoint follower's success on the
  maze's 5 tasks (``--expert-episodes`` each), and a collected navigate dataset's statistics
  (goals reached per episode, flips, mean speed, cells visited).
- ``closed``: the shipped checkpoint on report episodes (5 tasks x ``--closed-episodes``, the
  layouts of ``--shift``) in MJX at each setting and in OGBench's environments (the ``ogbench``
  backend, the reference), every rate with its 95% Wilson interval; ``inside`` says whether a
  row's mean lies inside the reference's interval on every layout.

Prints one table per part and, with ``--out``, writes ``fidelity.json`` there. Success rates do not
depend on the machine's load; rates of steps do: time the ``cost`` part alone on a quiet machine.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

os.environ.setdefault('TF_CPP_MIN_LOG_LEVEL', '3')
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from aqm_mjx import envs  # noqa: E402
from aqm_mjx.data import collect  # noqa: E402
from aqm_mjx.envs import mazes, physics  # noqa: E402
from aqm_mjx.evaluation.stats import wilson  # noqa: E402

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))  # benchmarks/: _report
sys.path.insert(0, os.path.join(os.path.dirname(HERE), 'throughput'))
sys.path.insert(0, HERE)
from _report import finish  # noqa: E402

SHIPPED = os.path.join(os.path.dirname(os.path.dirname(HERE)), 'checkpoints', 'aqm-antmaze-medium-navigate-cpu-long')
PARTS = ('cost', 'openloop', 'hostgait', 'expert', 'closed')
GAP_STEPS = (10, 100, 1000)


def up_z(qpos):
    """z of the torso's up axis from the quaternion ``qpos[..., 3:7]`` (< 0: upside down)."""
    return 1 - 2 * (qpos[..., 4] ** 2 + qpos[..., 5] ** 2)


# ------------------------------------------------------------------------------------------- cost
def cost(settings, a, log):
    import bench_env  # pylint: disable=import-outside-toplevel
    import bench_evaluate  # pylint: disable=import-outside-toplevel

    rows = []
    for name in settings:
        env = envs.make(a.env, physics=name)
        c_phys, r_phys = bench_env.bench_mjx(env, a.batch, a.cost_iters)
        agent, graph, _ = bench_evaluate.make_agent(env, a.checkpoint, a.keypoints)
        ag, _ = bench_evaluate.agent_rate(env, agent, graph, a.batch, a.agent_steps, 0.0, 1.0)
        rows.append(dict(part='cost', setting=name, physics=physics.describe(name), batch=a.batch,
                         physics_compile_s=round(c_phys, 1), physics_steps_per_s=round(r_phys, 1),
                         agent_compile_s=ag['compile_s'], agent_steps_per_s=ag['control_steps_per_s']))
        log(json.dumps(rows[-1]))
    ref = next((r for r in rows if r['setting'] == physics.OGBENCH), None)
    for r in rows:
        r['physics_x_ogbench'] = round(r['physics_steps_per_s'] / ref['physics_steps_per_s'], 2) if ref else None
        r['agent_x_ogbench'] = round(r['agent_steps_per_s'] / ref['agent_steps_per_s'], 2) if ref else None
    log(f'\n## cost: {a.env}, batch {a.batch}, {jax.devices()[0].platform} (control steps/s; compile apart)\n')
    log('| setting | physics | physics steps/s | x ogbench | compile s | whole agent steps/s | x ogbench | compile s |')
    log('|---|---|---|---|---|---|---|---|')
    for r in rows:
        log(f'| {r["setting"]} | {r["physics"]} | {r["physics_steps_per_s"]:,.0f} | {r["physics_x_ogbench"]} | '
            f'{r["physics_compile_s"]} | {r["agent_steps_per_s"]:,.0f} | {r["agent_x_ogbench"]} | {r["agent_compile_s"]} |')
    return rows


# -------------------------------------------------------------------------------------- open loop
def host_reference(a):
    """Navigate episodes of the expert in OGBench's physics on the host: ``[E, T, ...]`` arrays."""
    cfg = collect.CollectConfig(env=a.env, style='navigate', episodes=a.episodes * 10 // 10, steps=a.horizon + 1,
                                batch=min(a.episodes, 64), seed=a.seed, physics='mujoco')
    res = collect.collect(cfg, progress=False)
    e, t = cfg.episodes, cfg.steps
    out = {k: res.train[k].reshape(e, t, -1) for k in ('qpos', 'qvel', 'actions')}
    return out


def replay(env, qpos0, qvel0, actions):
    """``actions [B, T, 8]`` from ``(qpos0, qvel0) [B, ...]`` in MJX: qpos ``[T, B, nq]`` after each step."""
    grid = jnp.asarray(env.layout)

    @jax.jit
    def run(qpos0, qvel0, actions):
        data = jax.vmap(env.set_state)(qpos0, qvel0)

        def body(d, act):
            d = jax.vmap(env.physics_step, in_axes=(0, 0, None))(d, act, grid)
            return d, d.qpos
        return jax.lax.scan(body, data, jnp.swapaxes(actions, 0, 1))[1]
    return np.asarray(run(jnp.asarray(qpos0), jnp.asarray(qvel0), jnp.asarray(actions)))


def host_replay(env_name, qpos0, qvel0, actions):
    """The same replay in MuJoCo's C library with OGBench's physics and static walls, from the recorded
    (float32) states: the reference's own divergence from rounding its start state (chaos, not physics).
    Returns qpos ``[T, B, nq]``."""
    import mujoco  # pylint: disable=import-outside-toplevel

    from aqm_mjx.envs import locomaze  # pylint: disable=import-outside-toplevel

    agent, maze = envs.parse_name(env_name)
    m = locomaze.build_mj_model(agent, physics.get(physics.OGBENCH), static_walls=mazes.layout(maze))
    out = np.empty((actions.shape[1], actions.shape[0], m.nq))
    for b in range(actions.shape[0]):
        d = mujoco.MjData(m)
        d.qpos[:], d.qvel[:] = qpos0[b], qvel0[b]
        for t in range(actions.shape[1]):
            d.ctrl[:] = np.clip(actions[b, t], -1, 1)
            mujoco.mj_step(m, d, nstep=locomaze.OGBENCH_SUBSTEPS)
            out[t, b] = d.qpos
    return out


HOST_ROW = 'host float32 start'


def openloop(settings, a, log):
    ref = host_reference(a)
    qpos, qvel, act = ref['qpos'], ref['qvel'], ref['actions']
    e, t1 = qpos.shape[:2]
    horizon = t1 - 1
    short = [s for s in GAP_STEPS if s < horizon] + [horizon]
    starts = np.arange(0, horizon - 100 + 1, 100) if horizon >= 100 else np.array([0])
    host_flips = int((up_z(qpos[:, -1]) < 0).sum())
    rows = []
    win = min(100, horizon)
    s_q = np.concatenate([qpos[:, s] for s in starts])
    s_v = np.concatenate([qvel[:, s] for s in starts])
    s_a = np.concatenate([act[:, s:s + win] for s in starts])
    for name in ([HOST_ROW] if a.host_row else []) + list(settings):
        t0 = time.perf_counter()
        if name == HOST_ROW:
            full = host_replay(a.env, qpos[:, 0], qvel[:, 0], act[:, :horizon])
            windows = host_replay(a.env, s_q, s_v, s_a)
        else:
            env = envs.make(a.env, physics=name)
            full = replay(env, qpos[:, 0], qvel[:, 0], act[:, :horizon])  # [T, E, nq]
            windows = replay(env, s_q, s_v, s_a)  # [win, E * len(starts), nq]
        ref_w = np.concatenate([qpos[:, s + 1:s + win + 1] for s in starts])  # [E*S, win, nq]
        row = dict(part='openloop', setting=name, episodes=int(e),
                   physics='OGBench\'s in MuJoCo C, float64' if name == HOST_ROW else physics.describe(name),
                   host_flips=host_flips, flips=int((up_z(full[-1]) < 0).sum()),
                   seconds=round(time.perf_counter() - t0, 1))
        for n in short:
            if n >= horizon:
                gap = np.linalg.norm(full[n - 1, :, :2] - qpos[:, n, :2], axis=-1)
            else:
                gap = np.linalg.norm(windows[n - 1, :, :2] - ref_w[:, n - 1, :2], axis=-1)
            row[f'gap_{n}'] = dict(median=round(float(np.median(gap)), 3), p90=round(float(np.quantile(gap, 0.9)), 3),
                                   max=round(float(gap.max()), 3), n=int(gap.size))
        rows.append(row)
        log(json.dumps(row))
    log(f'\n## open loop: {e} host episodes of the expert ({a.env}, OGBench physics in MuJoCo C, float64), '
        'x-y gap in m (median / 90th percentile) after n control steps\n')
    log('| setting | ' + ' | '.join(f'gap after {n}' for n in short) + ' | flipped at the end (host: '
        f'{host_flips}) |')
    log('|---|' + '---|' * len(short) + '---|')
    for r in rows:
        log(f'| {r["setting"]} | ' + ' | '.join(f'{r[f"gap_{n}"]["median"]} / {r[f"gap_{n}"]["p90"]}' for n in short)
            + f' | {r["flips"]}/{r["episodes"]} |')
    return rows


# ----------------------------------------------------------------------------------------- expert
def expert(settings, a, log):
    import bench_expert  # pylint: disable=import-outside-toplevel

    rows = []
    for name in settings:
        t0 = time.perf_counter()
        speed, flipped = bench_expert.flat_ground(envs.make('antmaze-arena', physics=name), a.flat_dirs, 0.2,
                                                  steps=a.flat_steps)
        env = envs.make(a.env, physics=name)
        success, steps, _ = bench_expert.waypoints(env, a.expert_episodes)
        cfg = collect.CollectConfig(env=a.env, episodes=a.collect_episodes, steps=a.horizon + 1,
                                    batch=a.collect_episodes, seed=a.seed, physics='mjx', physics_preset=name)
        res = collect.collect(cfg, progress=False)
        q = res.train['qpos'].reshape(a.collect_episodes, a.horizon + 1, -1)
        cells = {tuple(c) for c in mazes.xy_to_ij(q[:, :, :2].reshape(-1, 2)).tolist()}
        lo, hi = wilson(float(success.sum()), len(success))
        rows.append(dict(part='expert', setting=name, physics=physics.describe(name),
                         flat_speed=round(float(speed.mean()), 3), flat_slowest=round(float(speed.min()), 3),
                         flat_flips=int(flipped.sum()), flat_runs=int(len(flipped)),
                         waypoint_success=round(float(success.mean()), 4), waypoint_ci=[round(lo, 4), round(hi, 4)],
                         waypoint_episodes=int(len(success)),
                         waypoint_steps=round(float(steps[success > 0].mean()), 1) if success.any() else None,
                         data_goals_per_episode=round(float(res.stats['goals_reached_mean']), 2),
                         data_flips=int(res.stats['flipped_episodes']),  # training and validation episodes
                         data_episodes=int(res.stats['episodes'] + res.stats['val_episodes']),
                         data_speed=round(float(np.linalg.norm(np.diff(q[:, :, :2], axis=1), axis=-1).mean() / 0.1), 3),
                         data_cells=len(cells), seconds=round(time.perf_counter() - t0, 1)))
        log(json.dumps(rows[-1]))
    log(f'\n## the scripted expert in MJX ({a.env}; flat ground: {a.flat_dirs} directions x {a.flat_steps} steps, '
        'noise 0.2)\n')
    log('| setting | flat speed m/s (slowest) | flat flips | waypoint success [95% CI] | steps | data: goals/episode | '
        'data: flips | data: speed m/s | data: cells |')
    log('|---|---|---|---|---|---|---|---|---|')
    for r in rows:
        ci = r['waypoint_ci']
        log(f'| {r["setting"]} | {r["flat_speed"]} ({r["flat_slowest"]}) | {r["flat_flips"]}/{r["flat_runs"]} | '
            f'{100 * r["waypoint_success"]:.0f}% [{100 * ci[0]:.0f}-{100 * ci[1]:.0f}] of {r["waypoint_episodes"]} | '
            f'{r["waypoint_steps"]} | {r["data_goals_per_episode"]} | {r["data_flips"]}/{r["data_episodes"]} | '
            f'{r["data_speed"]} | {r["data_cells"]} |')
    return rows


# ------------------------------------------------------------------------------------- host gait
#: (integrator, substeps, iterations, line search) of the host gait check: wider than the MJX rows
HOST_GAIT = [('rk4', 5, 100, 50), ('rk4', 5, 10, 10), ('rk4', 5, 4, 8), ('rk4', 5, 2, 4), ('rk4', 5, 1, 4),
             ('rk4', 5, 1, 2), ('rk4', 5, 1, 1), ('rk4', 4, 100, 50), ('rk4', 3, 100, 50), ('rk4', 2, 100, 50),
             ('euler', 5, 100, 50), ('euler', 10, 100, 50), ('euler', 5, 1, 4), ('euler', 10, 1, 4), ('euler', 20, 1, 4),
             ('implicitfast', 5, 100, 50), ('implicitfast', 10, 100, 50), ('implicitfast', 5, 1, 4)]


def hostgait(settings, a, log):
    """The trot on flat ground in MuJoCo's C library (no MJX): does a setting keep the gait at all?
    ``--flat-dirs`` commanded directions x ``--flat-steps`` control steps from OGBench's initial pose,
    noise 0: speed along the command and flips, for a grid of integrators, dt and solver settings
    wider than the MJX rows (``settings`` is not used)."""
    del settings
    import mujoco  # pylint: disable=import-outside-toplevel

    from aqm_mjx.data import expert as gait  # pylint: disable=import-outside-toplevel
    from aqm_mjx.envs.locomaze import PhysicsOptions, build_mj_model  # pylint: disable=import-outside-toplevel

    act = jax.jit(gait.gait_action)
    rows = []
    for integ, sub, it, ls in HOST_GAIT:
        m = build_mj_model('ant', PhysicsOptions(integrator=integ, substeps=sub, iterations=it, ls_iterations=ls),
                           n_proxies=0)
        speeds, flips = [], 0
        for k in range(a.flat_dirs):
            d = mujoco.MjData(m)
            ang = 2 * np.pi * k / a.flat_dirs
            cmd = np.array([np.cos(ang), np.sin(ang)], np.float32)
            x0 = d.qpos[:2].copy()
            for t in range(a.flat_steps):
                u = act(jnp.asarray(d.qpos, jnp.float32), jnp.asarray(d.qvel, jnp.float32), cmd, t, 0.0)
                d.ctrl[:] = np.clip(np.asarray(u), -1, 1)
                mujoco.mj_step(m, d, nstep=sub)
            speeds.append(float(np.dot(d.qpos[:2] - x0, cmd) / (a.flat_steps * 0.1)))
            flips += int(up_z(d.qpos) < 0)
        rows.append(dict(part='hostgait', integrator=integ, substeps=sub, dt=round(0.1 / sub, 4), iterations=it,
                         ls_iterations=ls, speed=round(float(np.mean(speeds)), 3), slowest=round(min(speeds), 3),
                         flips=flips, runs=a.flat_dirs))
        log(json.dumps(rows[-1]))
    log(f'\n## the trot on flat ground in MuJoCo C (no MJX): {a.flat_dirs} directions x {a.flat_steps} steps, '
        'noise 0\n')
    log('| integrator | substeps x dt | Newton iterations / line search | speed m/s (slowest) | flips |')
    log('|---|---|---|---|---|')
    for r in rows:
        log(f'| {r["integrator"]} | {r["substeps"]} x {r["dt"]} | {r["iterations"]}/{r["ls_iterations"]} | '
            f'{r["speed"]} ({r["slowest"]}) | {r["flips"]}/{r["runs"]} |')
    return rows


# ------------------------------------------------------------------------------------- closed loop
def closed(settings, a, log):
    from aqm_mjx import assess  # pylint: disable=import-outside-toplevel

    runs = [('ogbench backend', 'ogbench', physics.OGBENCH)] + [(f'mjx {s}', 'mjx', s) for s in settings]
    rows = []
    if a.reference:  # the reference's rows from an earlier run of the same episodes
        with open(a.reference) as f:
            rows = [r for r in json.load(f)['rows'] if r.get('part') == 'closed' and r['backend'] == 'ogbench']
        if not rows:
            raise SystemExit(f'--reference {a.reference}: no closed-loop rows of the ogbench backend in it')
        log(f'ogbench backend: its rows from {a.reference}')
    for label, backend, name in runs[1:] if rows else runs:
        t0 = time.perf_counter()
        over = [f'protocol.backend={backend}', f'protocol.physics_preset={name}',
                f'protocol.episodes={a.closed_episodes}', f'protocol.envs={a.closed_envs}',
                'protocol.ablations=' + ','.join(a.ablations)]
        out = os.path.join(a.out or '/tmp/physics_fidelity', 'closed', label.replace(' ', '_'))
        res, _ = assess.evaluate_checkpoint(a.checkpoint, shift=a.shift, out=out, seed=a.eval_seed, overrides=over,
                                            log=lambda *x: None)
        for agent_i, agent_name in enumerate(res.agents):
            for v_i, variant in enumerate(res.variants):
                sel = (np.asarray(res.table.agent) == agent_i) & (np.asarray(res.table.variant) == v_i)
                k, n = int(res.success[sel].sum()), int(sel.sum())
                lo, hi = wilson(float(k), n)
                rows.append(dict(part='closed', run=label, backend=backend, setting=name,
                                 physics=physics.describe(name) if backend == 'mjx' else 'OGBench\'s environments',
                                 agent=agent_name, layout=variant, successes=k, episodes=n, rate=round(k / n, 4),
                                 ci=[round(lo, 4), round(hi, 4)]))
        log(f'{label}: ' + ', '.join(f'{r["agent"]}/{r["layout"]} {100 * r["rate"]:.1f}%' for r in rows
                                     if r['run'] == label) + f'  [{time.perf_counter() - t0:.0f} s]')
    ref = {(r['agent'], r['layout']): r for r in rows if r['backend'] == 'ogbench'}
    for r in rows:
        c = ref[(r['agent'], r['layout'])]['ci']
        r['inside_reference_ci'] = bool(c[0] <= r['rate'] <= c[1])
    log(f'\n## closed loop: the shipped checkpoint, report episodes (5 tasks x {a.closed_episodes}), success % [95% '
        'Wilson]\n')
    layouts = list(dict.fromkeys(r['layout'] for r in rows))
    agents = list(dict.fromkeys(r['agent'] for r in rows))
    log('| run | agent | ' + ' | '.join(layouts) + ' | every layout inside the reference\'s interval |')
    log('|---|---|' + '---|' * len(layouts) + '---|')
    for label, _, _ in runs:
        for ag in agents:
            mine = {r['layout']: r for r in rows if r['run'] == label and r['agent'] == ag}
            log(f'| {label} | {ag} | ' + ' | '.join(
                f'{100 * mine[v]["rate"]:.1f} [{100 * mine[v]["ci"][0]:.0f}-{100 * mine[v]["ci"][1]:.0f}]'
                for v in layouts) + f' | {"yes" if all(m["inside_reference_ci"] for m in mine.values()) else "no"} |')
    return rows


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument('--parts', nargs='+', default=list(PARTS), choices=PARTS)
    p.add_argument('--settings', nargs='+', default=list(physics.STUDY), choices=list(physics.NAMES),
                   help='rows of the study (default: all of them; the closed loop defaults to ogbench and fast)')
    p.add_argument('--closed-settings', nargs='+', default=[physics.OGBENCH, physics.FAST], choices=list(physics.NAMES))
    p.add_argument('--env', default='antmaze-medium')
    p.add_argument('--checkpoint', default=SHIPPED)
    p.add_argument('--batch', type=int, default=64, help='cost: environments per call')
    p.add_argument('--cost-iters', type=int, default=30, help='cost: timed physics calls')
    p.add_argument('--agent-steps', type=int, default=20, help='cost: control steps of the timed agent call')
    p.add_argument('--keypoints', type=int, default=64)
    p.add_argument('--episodes', type=int, default=32, help='openloop: host episodes')
    p.add_argument('--host-row', action='store_true',
                   help="openloop: also the reference's own replay from the recorded float32 states (chaos floor)")
    p.add_argument('--horizon', type=int, default=1000, help='openloop and expert data: control steps per episode')
    p.add_argument('--flat-dirs', type=int, default=16)
    p.add_argument('--flat-steps', type=int, default=200)
    p.add_argument('--expert-episodes', type=int, default=10, help='expert: waypoint episodes per task')
    p.add_argument('--collect-episodes', type=int, default=16, help='expert: episodes of the collected data')
    p.add_argument('--closed-episodes', type=int, default=50, help='closed: report episodes per task')
    p.add_argument('--closed-envs', type=int, default=250, help='closed: environments per jitted chunk')
    p.add_argument('--shift', default='closures')
    p.add_argument('--ablations', nargs='*', default=[], help="closed: rows beside AQM ('no-pruning', 'flat')")
    p.add_argument('--reference', default=None,
                   help="closed: fidelity.json of an earlier closed run with the same episodes: its ogbench-backend "
                        'rows are the reference instead of running them again')
    p.add_argument('--eval-seed', type=int, default=0)
    p.add_argument('--seed', type=int, default=0)
    p.add_argument('--tiny', action='store_true', help='every part at a few steps and episodes (the script\'s test)')
    p.add_argument('--out', default=None, help='folder for fidelity.json (and the closed loop\'s evaluations)')
    a = p.parse_args(argv)
    if a.tiny:
        a.batch, a.cost_iters, a.agent_steps, a.keypoints = 4, 2, 3, 8
        a.episodes, a.horizon, a.flat_dirs, a.flat_steps = 2, 20, 2, 5
        a.expert_episodes, a.collect_episodes, a.closed_episodes, a.closed_envs = 1, 2, 1, 5
        a.shift = 'base'
    if a.out:
        os.makedirs(a.out, exist_ok=True)
    lines = []

    def log(*x):
        print(*x, flush=True)
        lines.append(' '.join(map(str, x)))

    log(f'# physics fidelity: {a.env}, parts {" ".join(a.parts)}, on {jax.devices()[0].platform}'
        + (' (tiny sizes: the script\'s test, not a measurement)' if a.tiny else ''))
    rows = []
    for part in a.parts:
        chosen = a.closed_settings if part == 'closed' else a.settings
        rows += dict(cost=cost, openloop=openloop, hostgait=hostgait, expert=expert, closed=closed)[part](chosen, a, log)
    if a.out:
        with open(os.path.join(a.out, 'fidelity.md'), 'w') as f:
            f.write('\n'.join(lines) + '\n')
    finish(rows, os.path.join(a.out, 'fidelity.json') if a.out else None)
    return rows


if __name__ == '__main__':
    main()
