"""``kill -9`` at random moments of ``aqm-mjx train``, each followed by a resume: does the run
always end bit-identical to one that was never interrupted?

    python benchmarks/experiments/bench_kill_resume.py [--kills 10] [--steps 3000] [--seed 0] [--out DIR]

A reference run trains uninterrupted. A second run in another folder is started, killed with
SIGKILL after a random delay (anywhere from start-up and compilation to the middle of a checkpoint
save), started again (``--resume`` once it holds a checkpoint, as a user would), ``--kills`` times;
then it is left to finish. The script prints each kill (delay, newest checkpoint at that moment),
then checks: every parameter, optimiser and target array equal byte for byte to the reference,
``metrics.jsonl`` strict JSON with each logged step once, and no temporary Orbax folder left.
Exits 1 on any difference. The model is the ``ci`` preset of AQM on a 5 x 5 grid dataset (CPU).
"""

from __future__ import annotations

import argparse
import json
import os
import random
import signal
import subprocess
import sys
import tempfile
import time

import jax
import numpy as np


def _cmd(dataset: str, out: str, steps: int, resume: bool) -> list[str]:
    cmd = [sys.executable, '-m', 'aqm_mjx.cli', 'train', '--dataset', dataset, '--out', out]
    if resume:
        return cmd + ['--resume']
    return cmd + ['--env', 'pointmaze-medium', '--preset', 'ci', '--steps', str(steps), '--set', 'updates_per_call=50',
                  '--set', 'log_every=50', '--set', 'checkpoint_every=50', '--set', 'keep=3']


def _last_step(path: str) -> int:
    """The last whole metric line's step (0 when there is none yet)."""
    try:
        with open(path) as f:
            lines = [ln for ln in f if ln.endswith('\n')]
        return json.loads(lines[-1])['step'] if lines else 0
    except (OSError, ValueError, KeyError):
        return 0


def _leaves(out: str) -> tuple[list[bytes], int]:
    from aqm_mjx.learn import fit  # pylint: disable=import-outside-toplevel

    t = fit.load(out, log=lambda *_: None)
    return [np.asarray(x).tobytes() for x in jax.tree.leaves(t.state)], t.step


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    p.add_argument('--kills', type=int, default=10)
    p.add_argument('--steps', type=int, default=3000)
    p.add_argument('--seed', type=int, default=0, help='seed of the kill delays')
    p.add_argument('--out', default=None, help='work folder (default: a temporary one)')
    a = p.parse_args(argv)
    from aqm_mjx.data import dataset as dsm  # pylint: disable=import-outside-toplevel
    from aqm_mjx.data import synthetic  # pylint: disable=import-outside-toplevel
    from aqm_mjx.learn import fit  # pylint: disable=import-outside-toplevel

    work = a.out or tempfile.mkdtemp(prefix='bench_kill_')
    os.makedirs(work, exist_ok=True)
    data = synthetic.grid_walks(synthetic.one_way_grid(5), episodes=50, steps=20, seed=1)
    dataset = os.path.join(work, 'grid.npz')
    dsm.write_ogbench(dataset, {k: data[k] for k in ('observations', 'actions', 'terminals')})
    env = dict(os.environ, JAX_PLATFORMS='cpu')
    ref, cut = os.path.join(work, 'ref'), os.path.join(work, 'cut')
    t0 = time.perf_counter()
    subprocess.run(_cmd(dataset, os.path.join(work, 'short'), 50, False), check=True, env=env, capture_output=True)
    t_start = time.perf_counter() - t0  # start-up, compile and one chunk
    t0 = time.perf_counter()
    subprocess.run(_cmd(dataset, ref, a.steps, False), check=True, env=env, capture_output=True)
    t_ref = time.perf_counter() - t0
    print(f'reference: {a.steps} updates uninterrupted in {t_ref:.1f} s ({t_start:.1f} s to start, compile and run '
          f'the first 50)')
    # Kills by progress, not by the clock (this machine's speed varies): kill k waits until the run
    # has logged step ~k/(kills+1) of the way, then a random 0-0.4 s more (mid-chunk, mid-save:
    # every chunk ends in a checkpoint); every third kill instead lands at a random moment of
    # start-up, restore or compilation.
    rng = random.Random(a.seed)
    metrics = os.path.join(cut, 'metrics.jsonl')
    for k in range(a.kills):
        resume = bool(fit.checkpoint_steps(cut))
        proc = subprocess.Popen(_cmd(dataset, cut, a.steps, resume), env=env, stdout=subprocess.DEVNULL,
                                stderr=subprocess.DEVNULL)
        t0 = time.perf_counter()
        if k % 3 == 2:
            moment = 'start-up'
            time.sleep(rng.uniform(0.3, t_start))
        else:
            target = (k + 1) * a.steps // (a.kills + 1)
            moment = f'past step {target}'
            while proc.poll() is None and _last_step(metrics) < target:
                time.sleep(0.01)
            time.sleep(rng.uniform(0.0, 0.4))
        delay = time.perf_counter() - t0
        ended = proc.poll() is not None
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        have = fit.checkpoint_steps(cut)
        print(f'kill {k + 1:2d}: {moment:<15} after {delay:5.1f} s of a {"resumed" if resume else "fresh"} run; newest '
              f'checkpoint {have[-1] if have else "none"}' + (' (the run had already ended)' if ended else ''))
    resume = bool(fit.checkpoint_steps(cut))
    done = subprocess.run(_cmd(dataset, cut, a.steps, resume), env=env, capture_output=True, text=True)
    if done.returncode:
        print(f'the final {"resume" if resume else "run"} failed:\n{done.stderr[-2000:]}')
        return 1
    (x, sx), (y, sy) = _leaves(ref), _leaves(cut)
    same = sx == sy == a.steps and len(x) == len(y) and all(u == v for u, v in zip(x, y))
    with open(os.path.join(cut, 'metrics.jsonl')) as f:
        steps = [json.loads(ln, parse_constant=lambda c: (_ for _ in ()).throw(ValueError(c)))['step'] for ln in f]
    metrics_ok = steps == sorted(set(steps)) and steps[-1] == a.steps
    leftovers = [n for n in os.listdir(os.path.join(cut, 'checkpoints')) if 'tmp' in n]
    print(f'{a.kills} kills, then a resume to step {sy}: state {"bit-identical" if same else "DIFFERENT"} to the '
          f'uninterrupted run ({len(x)} arrays); metrics.jsonl {"strict JSON, each step once" if metrics_ok else "BAD"}'
          f'; temporary checkpoint folders left: {len(leftovers)}')
    return 0 if same and metrics_ok and not leftovers else 1


if __name__ == '__main__':
    raise SystemExit(main())
