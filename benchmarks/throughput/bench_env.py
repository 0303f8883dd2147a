"""Physics and control steps/s of the MJX maze environments against plain MuJoCo, in one run.

In contact: every measurement steps a walking-like ant (uniform random actions after the ant has
settled on the floor), never a standing one. Compile time is printed apart from run time, and each
jitted step is called twice before timing (the second call is where a weakly typed field would
recompile; see the 'timing trap').

    python benchmarks/throughput/bench_env.py                      # CPU defaults: batches 1, 64, 256
    python benchmarks/throughput/bench_env.py --batches 1 64 256 1024 4096 --iters 20   # on a GPU
    python benchmarks/throughput/bench_env.py --iterations 1 --ls-iterations 4          # Brax-style solver

Rows: 'ant alone' is OGBench's ant on an empty floor (no wall geoms at all); 'medium', 'large',
'giant' are our environments (3 wall proxies + contact caps, the grid as data). 'mujoco 1 thread'
is plain MuJoCo C on OGBench's own model of the large maze (61 static walls); 'mujoco.rollout' is
the same on all cores. The ratio column divides the ant-alone rate by the row's rate at the same
batch (1.0 = walls cost nothing).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import time

os.environ.setdefault('TF_CPP_MIN_LOG_LEVEL', '3')  # before jaxlib loads: no XLA lines on cached executables (see cli.py)
import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from aqm_mjx import envs
from aqm_mjx._mjx import mjx
from aqm_mjx.envs import locomaze, mazes
from aqm_mjx.envs import physics as physics_presets


def _batched(tree, b):
    return jax.tree.map(lambda x: jnp.broadcast_to(x, (b,) + x.shape), tree)


def bench_mjx(env, batch, iters, alone=False):
    """Control steps/s of ``jit(vmap(env.physics_step))`` in contact. Returns (compile_s, rate)."""
    if alone:
        m = locomaze.build_mj_model('ant', env.physics, n_proxies=0)
        mx = mjx.put_model(m, impl=env.physics.impl)

        def control(d, a, g):
            del g
            d = d.replace(ctrl=jnp.clip(a, -1, 1))
            return jax.lax.scan(lambda d, _: (mjx.step(mx, d), None), d, None, length=5)[0]

        data0 = locomaze.strip_weak_types(mjx.make_data(mx))
    else:
        control = env.physics_step
        data0 = env.template
    step = jax.jit(jax.vmap(control))
    key = jax.random.PRNGKey(0)
    grid = jnp.broadcast_to(jnp.asarray(env.layout), (batch,) + env.layout.shape)
    data = _batched(data0, batch)
    # Start each ant at a random free cell so that wall proxies are in play, settled on the floor.
    free = np.argwhere(env.layout == 0)
    rng = np.random.default_rng(0)
    xy = mazes.ij_to_xy(free[rng.integers(len(free), size=batch)]) + rng.uniform(-1.5, 1.5, (batch, 2))
    data = data.replace(qpos=data.qpos.at[:, :2].set(jnp.asarray(xy, data.qpos.dtype)))
    actions = jax.random.uniform(key, (iters + 12, batch, env.action_size), minval=-1, maxval=1)
    t0 = time.perf_counter()
    data = step(data, actions[0], grid)
    jax.block_until_ready(data)
    compile_s = time.perf_counter() - t0
    for k in range(1, 12):  # second call (timing trap) and settling into contact
        data = step(data, actions[k], grid)
    jax.block_until_ready(data)
    t0 = time.perf_counter()
    for k in range(12, 12 + iters):
        data = step(data, actions[k], grid)
    jax.block_until_ready(data)
    dt = time.perf_counter() - t0
    assert bool(jnp.all(jnp.isfinite(data.qpos))), 'non-finite state in benchmark'
    return compile_s, batch * iters / dt


def bench_mujoco(maze, steps, physics):
    """Plain MuJoCo C on OGBench's model of the maze (static walls): one thread and mujoco.rollout."""
    m = locomaze.build_mj_model('ant', physics, static_walls=mazes.layout(maze))
    d = mujoco.MjData(m)
    rng = np.random.default_rng(0)
    ctrl = rng.uniform(-1, 1, (steps, m.nu))
    for k in range(10):  # settle
        d.ctrl[:] = ctrl[k]
        mujoco.mj_step(m, d, nstep=physics.substeps)
    t0 = time.perf_counter()
    for k in range(steps):
        d.ctrl[:] = ctrl[k]
        mujoco.mj_step(m, d, nstep=physics.substeps)
    one = steps / (time.perf_counter() - t0)
    rollout_rate = None
    try:
        from mujoco import rollout  # pylint: disable=import-outside-toplevel

        n_threads = os.cpu_count() or 1
        n_roll = max(2 * n_threads, 8)
        state0 = np.zeros((n_roll, mujoco.mj_stateSize(m, mujoco.mjtState.mjSTATE_FULLPHYSICS)))
        mujoco.mj_getState(m, d, state0[0], mujoco.mjtState.mjSTATE_FULLPHYSICS)
        state0[:] = state0[0]
        nstep = physics.substeps * max(steps // n_roll, 20)
        ctrl_r = np.repeat(rng.uniform(-1, 1, (n_roll, nstep // physics.substeps, m.nu)), physics.substeps, axis=1)
        datas = [mujoco.MjData(m) for _ in range(n_threads)]
        with rollout.Rollout(nthread=n_threads) as r:
            r.rollout([m] * n_roll, datas, state0, ctrl_r)  # warm-up
            t0 = time.perf_counter()
            r.rollout([m] * n_roll, datas, state0, ctrl_r)
            rollout_rate = n_roll * nstep / physics.substeps / (time.perf_counter() - t0)
    except Exception as e:  # pragma: no cover - older mujoco without the Rollout class
        print(f'  (mujoco.rollout unavailable: {e})')
    return one, rollout_rate


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument('--batches', type=int, nargs='+', default=[1, 64, 256], help='environment batch sizes')
    p.add_argument('--mazes', nargs='+', default=['medium', 'large', 'giant'], help='mazes to time')
    p.add_argument('--iters', type=int, default=5, help='timed control steps per measurement')
    p.add_argument('--physics-preset', default='ogbench', choices=list(physics_presets.NAMES),
                   help="named physics (aqm_mjx.envs.physics): 'ogbench' (RK4, Newton 100/50), 'fast', ...")
    p.add_argument('--iterations', type=int, default=None, help="solver iterations (default: the preset's)")
    p.add_argument('--ls-iterations', type=int, default=None, help="line-search iterations (default: the preset's)")
    p.add_argument('--impl', default='jax', choices=['jax', 'warp'], help='MJX implementation')
    p.add_argument('--mujoco-steps', type=int, default=2000, help='control steps for the plain MuJoCo rows')
    p.add_argument('--json', default=None, help='also write the rows to this JSON file')
    a = p.parse_args(argv)
    # The three mazes compile to the same program (the grid is an argument): let the cache see it.
    jax.config.update('jax_compilation_cache_dir', os.path.expanduser('~/.cache/aqm_mjx/jax'))
    jax.config.update('jax_persistent_cache_min_compile_time_secs', 1.0)
    chosen = dataclasses.replace(physics_presets.get(a.physics_preset), impl=a.impl,
                                 **{k: v for k, v in (('iterations', a.iterations), ('ls_iterations', a.ls_iterations))
                                    if v is not None})
    physics = dict(physics=chosen)
    sub = chosen.substeps
    dev = jax.devices()[0]
    print(f'# bench_env: {dev.platform} {dev.device_kind}, {os.cpu_count()} CPU cores, {platform.processor() or platform.machine()}')
    print(f'# physics: {physics_presets.describe(chosen)}, random actions in contact, {a.iters} timed control '
          'steps per row')
    rows = []
    print(f'{"system":<26}{"batch":>7}{"compile s":>11}{"control/s":>12}{"physics/s":>12}{"x ant alone":>13}')
    for b in a.batches:
        base_env = envs.make('antmaze-medium', **physics)
        c, alone = bench_mjx(base_env, b, a.iters, alone=True)
        rows.append(dict(system='mjx ant alone', batch=b, compile_s=c, control_per_s=alone))
        print(f'{"mjx ant alone":<26}{b:>7}{c:>11.1f}{alone:>12.0f}{sub * alone:>12.0f}{1.0:>13.2f}', flush=True)
        for maze in a.mazes:
            env = envs.make(f'antmaze-{maze}', **physics)
            c, rate = bench_mjx(env, b, a.iters)
            rows.append(dict(system=f'mjx antmaze-{maze}', batch=b, compile_s=c, control_per_s=rate, ratio=alone / rate))
            print(f'{"mjx antmaze-" + maze:<26}{b:>7}{c:>11.1f}{rate:>12.0f}{sub * rate:>12.0f}{alone / rate:>13.2f}', flush=True)
    ref_physics = dataclasses.replace(chosen, impl='jax')
    for maze in a.mazes:
        one, roll = bench_mujoco(maze, a.mujoco_steps, ref_physics)
        rows.append(dict(system=f'mujoco 1 thread {maze}', control_per_s=one))
        print(f'{"mujoco 1 thread " + maze:<26}{1:>7}{"-":>11}{one:>12.0f}{sub * one:>12.0f}{"":>13}')
        if roll:
            rows.append(dict(system=f'mujoco.rollout {maze}', control_per_s=roll, threads=os.cpu_count()))
            print(f'{"mujoco.rollout " + maze:<26}{os.cpu_count():>7}{"-":>11}{roll:>12.0f}{sub * roll:>12.0f}{"":>13}')
    best = max((r for r in rows if r['system'].startswith('mjx antmaze-large')), key=lambda r: r['control_per_s'])
    ref = next(r for r in rows if r['system'] == 'mujoco 1 thread large')
    print(f'# best MJX large-maze rate {best["control_per_s"]:.0f} control steps/s at batch {best["batch"]} = '
          f'{best["control_per_s"] / ref["control_per_s"]:.2f}x plain MuJoCo on one thread')
    if a.json:
        with open(a.json, 'w') as f:
            json.dump(dict(device=str(dev), physics=physics_presets.describe(chosen), rows=rows), f, indent=1)


if __name__ == '__main__':
    main()
