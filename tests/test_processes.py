"""Several processes as one JAX program (JAX's multi-controller runtime), run here as two CPU
processes of this machine talking through gloo."""

import json
import os
import socket
import subprocess
import sys

import numpy as np
import pytest

from aqm_mjx import processes

ENV = dict(os.environ, JAX_PLATFORMS='cpu', XLA_FLAGS='')  # one CPU device a process


def free_port() -> int:
    with socket.socket() as s:
        s.bind(('127.0.0.1', 0))
        return s.getsockname()[1]


def test_start_refuses_partial_or_bad_arguments_before_any_jax_call():
    assert processes.start() == (0, 1)  # nothing named: this process alone
    for kw, says in ((dict(coordinator='127.0.0.1:1'), 'missing --num-processes, --process-id'),
                     (dict(num_processes=2, process_id=0), 'missing --coordinator'),
                     (dict(coordinator='localhost', num_processes=2, process_id=0), 'expected HOST:PORT'),
                     (dict(coordinator='127.0.0.1:1', num_processes=2, process_id=2), 'expected 0 <= id < 2')):
        with pytest.raises(ValueError, match=says):
            processes.start(**kw)


_GATHER = '''
import sys
from aqm_mjx import processes
pid, n = processes.start(sys.argv[1], 2, int(sys.argv[2]), timeout_s=int(sys.argv[3]))
import jax, numpy as np
from aqm_mjx.evaluation.evaluate import device_mesh, fetch_global, put_global
from jax.sharding import NamedSharding, PartitionSpec
mesh = device_mesh(jax.devices())  # every process's devices
x = put_global(np.arange(8.0), NamedSharding(mesh, PartitionSpec('env')))
y = fetch_global(jax.jit(lambda a: 2 * a + a.sum())(x))
print(pid, n, jax.device_count(), processes.writer(), y.tolist(), flush=True)
'''


def test_two_processes_shard_one_array_and_gather_it_on_both():
    """The evaluation's own helpers over two processes: an array put on the global mesh (one device a
    process), a jitted program over it, the result gathered on both; process 0 alone is the writer."""
    port = str(free_port())
    procs = [subprocess.Popen([sys.executable, '-c', _GATHER, f'127.0.0.1:{port}', str(i), '60'], env=ENV,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for i in range(2)]
    outs = [p.communicate(timeout=180) for p in procs]
    assert all(p.returncode == 0 for p in procs), outs[0][1][-2000:] + outs[1][1][-2000:]
    want = (2 * np.arange(8.0) + 28).tolist()
    lines = sorted(o.strip().splitlines()[-1] for o, _ in outs)
    assert lines == [f'0 2 2 True {want}', f'1 2 2 False {want}']


def test_a_process_whose_partner_never_comes_names_what_it_waited_for():
    """Process 0 alone of two: it ends within its timeout with one line naming the coordinator."""
    port = str(free_port())
    r = subprocess.run([sys.executable, '-m', 'aqm_mjx.cli', 'evaluate', '--checkpoint', 'nowhere',
                        '--coordinator', f'127.0.0.1:{port}', '--num-processes', '2', '--process-id', '1'],
                       env=dict(ENV, AQM_MJX_PROCESS_TIMEOUT_S='5'), capture_output=True, text=True, timeout=120)
    lines = [ln for ln in r.stderr.strip().splitlines() if ln.startswith('aqm-mjx')]
    assert r.returncode == 2 and len(lines) == 1, r.stderr[-3000:]
    assert f'process 1 of 2 could not join the run through the coordinator 127.0.0.1:{port} within 5 s' in lines[0]


@pytest.mark.slow
def test_evaluate_over_two_processes_equals_one_process(tmp_path):
    """`aqm-mjx evaluate` of one checkpoint on the unchanged maze and a closure, as one process and as
    two (chunks of 10 episodes, each process running every other one on its own device): every
    episode's outcome is the same, and process 0 alone writes."""
    from aqm_mjx import run  # pylint: disable=import-outside-toplevel

    ckpt, path = run.demo_run(str(tmp_path / 'demo'), steps=100)
    argv = ['evaluate', '--checkpoint', ckpt, '--dataset', path, '--preset', 'ci', '--shift', 'base,close-3-3',
            '--episodes', '2', '--horizon', '40', '--ablations', 'no-pruning', '--envs', '10']  # 4 chunks
    one = str(tmp_path / 'one')
    r = subprocess.run([sys.executable, '-m', 'aqm_mjx.cli', *argv, '--out', one], env=ENV, capture_output=True,
                       text=True, timeout=900)
    assert r.returncode == 0, r.stderr[-3000:]
    two, port = str(tmp_path / 'two'), str(free_port())
    procs = [subprocess.Popen([sys.executable, '-m', 'aqm_mjx.cli', *argv, '--out', two, '--coordinator',
                               f'127.0.0.1:{port}', '--num-processes', '2', '--process-id', str(i)], env=ENV,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for i in range(2)]
    outs = [p.communicate(timeout=900) for p in procs]
    assert all(p.returncode == 0 for p in procs), outs[0][1][-3000:] + outs[1][1][-3000:]
    assert 'wrote' in outs[0][0] and 'wrote' not in outs[1][0]
    a, b = (np.load(os.path.join(f, 'episodes.npz')) for f in (one, two))
    assert sorted(a.files) == sorted(b.files) and len(a['success']) == 2 * 2 * 5 * 2
    for k in a.files:
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)
    ra, rb = (json.load(open(os.path.join(f, 'results.json'))) for f in (one, two))
    assert ra['summary'] == rb['summary'] and ra['legs'] == rb['legs']
    assert (ra['device_count'], rb['device_count']) == (1, 2)


def _launch(argv: list, out: str, port: int) -> list:
    """The same `aqm-mjx` command as processes 0 and 1 of a two-process run (coordinator on ``port``)."""
    return [subprocess.Popen([sys.executable, '-m', 'aqm_mjx.cli', *argv, '--out', out, '--coordinator',
                              f'127.0.0.1:{port}', '--num-processes', '2', '--process-id', str(i)], env=ENV,
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for i in range(2)]


def _kill_second_at(procs: list, mark: str) -> tuple[str, list[int]]:
    """Kill process 1 once the checkpoint folder ``mark`` exists; process 0 must end at once (under a
    minute, exit code 2) with one line. Returns that line and the checkpoint steps left on disk."""
    import time  # pylint: disable=import-outside-toplevel

    t_end = time.monotonic() + 600
    while not os.path.isdir(mark) and time.monotonic() < t_end and procs[1].poll() is None:
        time.sleep(0.05)
    assert os.path.isdir(mark), procs[1].communicate()[1][-3000:]
    procs[1].kill()
    t_kill = time.monotonic()
    _, err = procs[0].communicate(timeout=300)
    waited = time.monotonic() - t_kill
    procs[1].communicate()
    lines = [ln for ln in err.splitlines() if ln.startswith('aqm-mjx')]
    assert procs[0].returncode == 2 and len(lines) == 1, err[-3000:]
    assert waited < 60 and 'Check failure stack trace' not in err  # at once, not after XLA's shutdown barrier
    assert 'run the same command again on every process' in lines[0], lines
    return lines[0], sorted(int(s) for s in os.listdir(os.path.dirname(mark)))


def _final_states(folder: str) -> dict:
    """{run folder: its newest checkpoint's arrays} of a comparison folder."""
    import glob  # pylint: disable=import-outside-toplevel

    import jax  # pylint: disable=import-outside-toplevel

    from aqm_mjx.learn import fit  # pylint: disable=import-outside-toplevel

    return {os.path.relpath(f, folder): [np.asarray(x) for x in jax.tree.leaves(fit.load(f, log=lambda *_: None).state)]
            for f in sorted(glob.glob(os.path.join(folder, 'train', '*', 'seed_*')))}


@pytest.mark.slow
def test_compare_over_two_processes_equals_one_process_and_resumes_after_a_kill(tmp_path):
    """`aqm-mjx compare --seeds 2` of two flat methods over two processes (seed i trained on process i,
    process 0 writing every checkpoint): process 1 killed mid-training ends process 0 with one line;
    the same command again resumes, and every final state and episode equals the one-process run's.

    Bit for bit on antmaze's shapes (29-d observations, 8-d actions: random ones here), where XLA's CPU
    program of one seed computes as each seed of the vmapped pair does; on pointmaze's 2-d ones the
    two programs differ in the last bits (RESULTS.md section 7.7)."""
    rng = np.random.default_rng(0)
    path = str(tmp_path / 'antmaze-medium-navigate.npz')
    terminals = np.zeros(5000, bool)
    terminals[99::100] = True
    np.savez(path, observations=rng.normal(size=(5000, 29)).astype(np.float32),
             actions=rng.uniform(-1, 1, (5000, 8)).astype(np.float32), terminals=terminals)
    argv = ['compare', '--env', 'antmaze-medium', '--methods', 'gcbc', 'gcivl', '--seeds', '2', '--preset', 'ci',
            '--dataset', path, '--set', 'train.steps=1000', '--set', 'protocol.episodes=1',
            '--set', 'protocol.horizon=40']
    one = str(tmp_path / 'one')
    r = subprocess.run([sys.executable, '-m', 'aqm_mjx.cli', *argv, '--out', one], env=ENV, capture_output=True,
                       text=True, timeout=900)
    assert r.returncode == 0, r.stderr[-3000:]
    two = str(tmp_path / 'two')
    line, steps = _kill_second_at(_launch(argv, two, free_port()),
                                  os.path.join(two, 'train', 'gcbc', 'seed_1', 'checkpoints', '300'))
    assert 'process 0 of 2' in line, line
    assert steps and max(steps) < 1000  # killed mid-training

    procs = _launch(argv, two, free_port())
    outs = [p.communicate(timeout=900) for p in procs]
    assert all(p.returncode == 0 for p in procs), outs[0][1][-3000:] + outs[1][1][-3000:]
    assert 'gcbc: resuming 1 seed(s) at step' in outs[0][0] and 'gcbc: resuming 1 seed(s) at step' in outs[1][0]
    assert 'wrote' in outs[0][0] and 'wrote' not in outs[1][0]  # process 0 alone writes the tables
    a, b = _final_states(one), _final_states(two)
    assert list(a) == list(b) == ['train/gcbc/seed_0', 'train/gcbc/seed_1', 'train/gcivl/seed_0', 'train/gcivl/seed_1']
    for k in a:
        assert len(a[k]) == len(b[k]) and all(np.array_equal(x, y) for x, y in zip(a[k], b[k])), k
    for m in ('gcbc', 'gcivl'):
        for s in (0, 1):
            ea, eb = (np.load(os.path.join(f, 'eval', m, f'{m}:seed_{s}', 'episodes.npz')) for f in (one, two))
            for k in ea.files:
                np.testing.assert_array_equal(ea[k], eb[k], err_msg=f'{m} seed {s} {k}')
    ra, rb = (json.load(open(os.path.join(f, 'results.json'))) for f in (one, two))
    assert ra['rows'] == rb['rows'] and ra['data_sha256'] == rb['data_sha256']


def test_one_process_may_name_the_host_backend(tmp_path, capsys):
    """`--backend ogbench` is refused with several processes only: one process goes on to the checkpoint
    (here a missing one, named)."""
    from aqm_mjx.cli import main  # pylint: disable=import-outside-toplevel

    missing = str(tmp_path / 'nowhere')
    assert main(['evaluate', '--checkpoint', missing, '--preset', 'ci', '--backend', 'ogbench']) == 2
    err = capsys.readouterr().err
    assert 'several processes' not in err and 'nowhere' in err, err


def _model_outputs(folder: str, obs: np.ndarray) -> tuple:
    """(quasimetric distances, main-policy actions) of a trained run on fixed states."""
    import jax  # pylint: disable=import-outside-toplevel

    from aqm_mjx.learn import fit  # pylint: disable=import-outside-toplevel

    t = fit.load(folder, log=lambda *_: None)
    z = t.learner.distance.encode(t.agent.aux, obs)
    h = len(obs) // 2
    return (t.step, np.asarray(t.learner.distance.dist(t.agent.aux, z[:h], z[h:])),
            np.asarray(t.agent.controller(t.agent.aux, obs[:h], obs[h:], 0, jax.random.PRNGKey(0))))


@pytest.mark.slow
def test_train_over_two_processes_is_one_run_and_resumes_after_a_kill(tmp_path):
    """`aqm-mjx train` as two processes: one data-parallel run (each batch split over both processes'
    devices, the gradients summed across them), process 0 alone writing the folder. Process 1 killed
    after checkpoint 200 ends process 0 with one line, leaving only whole checkpoints; the same command
    again (with ``--resume``, as any train) resumes at the newest one and ends with the model of the
    one-process run, to float rounding (the sums run in another order), with the same metric lines."""
    rng = np.random.default_rng(0)
    path = str(tmp_path / 'antmaze-medium-navigate.npz')
    terminals = np.zeros(5000, bool)
    terminals[99::100] = True
    obs = rng.normal(size=(5000, 29)).astype(np.float32)
    np.savez(path, observations=obs, actions=rng.uniform(-1, 1, (5000, 8)).astype(np.float32), terminals=terminals)
    argv = ['train', '--dataset', path, '--preset', 'ci', '--steps', '400']
    one = str(tmp_path / 'one')
    r = subprocess.run([sys.executable, '-m', 'aqm_mjx.cli', *argv, '--out', one], env=ENV, capture_output=True,
                       text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    two = str(tmp_path / 'two')
    line, steps = _kill_second_at(_launch(argv, two, free_port()), os.path.join(two, 'checkpoints', '200'))
    assert 'process 0 of 2 lost process 1 while running the updates' in line, line
    assert max(steps) < 400, steps  # killed mid-training
    assert not [n for n in os.listdir(os.path.join(two, 'checkpoints')) if 'tmp' in n]  # no half-written checkpoint

    procs = _launch(argv + ['--resume'], two, free_port())  # train's own rule: a run is continued with --resume
    outs = [p.communicate(timeout=600) for p in procs]
    assert all(p.returncode == 0 for p in procs), outs[0][1][-3000:] + outs[1][1][-3000:]
    assert all(f'resumed {two} at step {max(steps)}' in o for o, _ in outs), outs[0][0][-2000:]
    assert 'wrote' in outs[0][0] and 'wrote' not in outs[1][0]  # process 0 alone writes
    (s1, d1, a1), (s2, d2, a2) = _model_outputs(one, obs[:512]), _model_outputs(two, obs[:512])
    assert s1 == s2 == 400
    np.testing.assert_allclose(d2, d1, rtol=1e-4)
    np.testing.assert_allclose(a2, a1, atol=1e-4)
    ma, mb = ([json.loads(ln) for ln in open(os.path.join(f, 'metrics.jsonl'))] for f in (one, two))
    assert [m['step'] for m in ma] == [m['step'] for m in mb]  # the killed run's extra lines were cut
    np.testing.assert_allclose([m['qrl/loss'] for m in mb], [m['qrl/loss'] for m in ma], rtol=1e-4)


@pytest.mark.slow
def test_run_over_two_processes_gives_the_one_process_episodes(tmp_path):
    """`aqm-mjx run` as two processes (point maze, `ci` preset): both collect the data, a share of
    the chunks each, and process 0 writes every file; training is one data-parallel run, the evaluation
    runs each process's share of the episodes in MJX; every episode (success, cuts, legs) and the
    keypoint count equal the one-process run's in MJX (the point maze does not amplify the training's
    float rounding as the ant's contacts would)."""
    argv = ['run', '--env', 'pointmaze-medium', '--preset', 'ci']
    one = str(tmp_path / 'one')
    r = subprocess.run([sys.executable, '-m', 'aqm_mjx.cli', *argv, '--backend', 'mjx', '--out', one], env=ENV,
                       capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stderr[-3000:]
    two = str(tmp_path / 'two')
    procs = _launch(argv, two, free_port())
    outs = [p.communicate(timeout=900) for p in procs]
    assert all(p.returncode == 0 for p in procs), outs[0][1][-3000:] + outs[1][1][-3000:]
    assert all('[1/4 data] collecting' in o and 'over 2 processes' in o for o, _ in outs)
    assert 'wrote' in outs[0][0] and 'wrote' not in outs[1][0]  # process 0 alone writes
    ea, eb = (np.load(os.path.join(f, 'eval', 'episodes.npz')) for f in (one, two))
    assert ea.files == eb.files and len(ea['success']) == 30
    for k in ea.files:
        np.testing.assert_array_equal(ea[k], eb[k], err_msg=k)
    sa, sb = (json.load(open(os.path.join(f, 'summary.json'))) for f in (one, two))
    assert sa['keypoints'] == sb['keypoints'] and sa['success'] == sb['success']


@pytest.mark.parametrize('physics', ['mujoco', pytest.param('mjx', marks=pytest.mark.slow)])
def test_collect_over_two_processes_writes_the_one_process_dataset(tmp_path, physics):
    """`aqm-mjx collect` as two processes: 11 episodes in chunks of 4 (chunks 1 and 3 on process 0,
    chunk 2 on process 1, which has none in the second round); process 0 alone writes, and the files
    hold the arrays one process collects, episode for episode."""
    from aqm_mjx.data import collect  # pylint: disable=import-outside-toplevel
    from aqm_mjx.data import dataset as dsm  # pylint: disable=import-outside-toplevel

    argv = ['collect', '--env', 'pointmaze-medium', '--style', 'stitch', '--episodes', '10', '--steps', '30',
            '--batch', '4', '--seed', '5', '--physics', physics]
    out = str(tmp_path / 'pm.npz')
    procs = _launch(argv, out, free_port())
    outs = [p.communicate(timeout=600) for p in procs]
    assert all(p.returncode == 0 for p in procs), outs[0][1][-3000:] + outs[1][1][-3000:]
    said = [[ln for ln in o.splitlines() if not ln.startswith('[Gloo]')] for o, _ in outs]
    assert 'collecting 10 + 1 (val)' in said[0][0] and said[1] == []  # process 0 alone speaks and writes
    assert json.load(open(str(tmp_path / 'pm.json')))['processes'] == 2
    one = collect.collect(collect.CollectConfig(env='pointmaze-medium', style='stitch', episodes=10, steps=30,
                                                batch=4, seed=5, physics=physics), progress=False)
    for got, want in ((dsm.read_ogbench(out), one.train), (dsm.read_ogbench(dsm.val_path(out)), one.val)):
        assert sorted(got) == sorted(want)
        for k in want:
            np.testing.assert_array_equal(got[k], want[k], err_msg=k)


def test_a_collection_whose_partner_dies_ends_with_one_line_and_writes_nothing(tmp_path):
    """Process 1 killed once it has joined: process 0 ends at its next gather with one line naming the
    lost partner and the chunks, exit code 2, and no dataset file exists."""
    argv = ['collect', '--env', 'pointmaze-medium', '--style', 'stitch', '--episodes', '200', '--steps', '200',
            '--batch', '4', '--physics', 'mujoco']
    out = str(tmp_path / 'pm.npz')
    procs = _launch(argv, out, free_port())
    for ln in procs[1].stderr:  # the partner has joined the run (and made its collectives' connections)
        if 'processes joined' in ln:
            break
    procs[1].kill()
    procs[1].communicate()
    _, err = procs[0].communicate(timeout=300)
    lines = [ln for ln in err.splitlines() if ln.startswith('aqm-mjx')]
    assert procs[0].returncode == 2 and len(lines) == 1, err[-3000:]
    assert 'process 0 of 2 lost process 1 while collecting chunks' in lines[0], lines
    assert not any(os.path.exists(str(tmp_path / f)) for f in ('pm.npz', 'pm-val.npz', 'pm.json', 'pm.png'))
