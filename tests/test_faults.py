"""Runs that meet faults: divergence, torn checkpoints, two writers, full disks, damaged inputs.

Each test makes the fault itself and checks the exit code, the one-line message and that nothing
already on disk was lost or left half-written.
"""

import dataclasses
import json
import math
import os
import re
import shutil
import socket
import subprocess
import sys
import time
import types

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from aqm_mjx import cli, files
from aqm_mjx.data import dataset as dsm
from aqm_mjx.data import synthetic
from aqm_mjx.learn import checkpoint as ckpt
from aqm_mjx.learn import fit, methods


@pytest.fixture(scope='module')
def grid_data():
    data = synthetic.grid_walks(synthetic.one_way_grid(5), episodes=50, steps=20, seed=1)
    return {k: data[k] for k in ('observations', 'actions', 'terminals')}


@pytest.fixture
def grid_file(tmp_path, grid_data):
    path = str(tmp_path / 'grid.npz')
    dsm.write_ogbench(path, grid_data)
    return path


def _error_lines(err: str) -> list[str]:
    return [ln for ln in err.splitlines() if ln.startswith('aqm-mjx:')]


def _strict_lines(path: str) -> list[dict]:
    def refuse(name):
        raise ValueError(f'{name} is not JSON')

    with open(path) as f:
        return [json.loads(ln, parse_constant=refuse) for ln in f]


def _nan_after(step: int, name: str = 'gcbc') -> methods.Method:
    """``name`` whose update turns every floating leaf of the state into NaN once past ``step``
    (its metrics, computed before, stay finite: the state check must find it)."""
    base = methods.get(name)

    def make(cfg, obs_size, action_size):
        learner = base.make(cfg, obs_size, action_size)

        def update(state, ds):
            state, m = learner.update(state, ds)
            poison = lambda x: jnp.where(state.step > step, jnp.nan, x) if jnp.issubdtype(x.dtype, jnp.floating) else x
            return jax.tree.map(poison, state), m

        return learner._replace(update=update)

    return methods.Method(name=base.name, config=base.config, make=make)


# ------------------------------------------------------------------------------------ divergence
def test_divergence_stops_with_one_line_and_strict_metrics(tmp_path, grid_file, capsys):
    out = str(tmp_path / 'run')
    rc = cli.main(['train', '--dataset', grid_file, '--env', 'pointmaze-medium', '--preset', 'ci', '--out', out,
                   '--set', 'lr_quasimetric=1e20', '--set', 'lr_policy=1e20'])
    err = capsys.readouterr().err
    assert rc == 2
    lines = _error_lines(err)
    assert len(lines) == 1 and 'training diverged in updates 1-50' in lines[0]
    assert 'lr_quasimetric=1e+20' in lines[0] and 'no checkpoint was written' in lines[0]
    assert fit.checkpoint_steps(out) == []
    metrics = _strict_lines(os.path.join(out, 'metrics.jsonl'))
    assert [m['step'] for m in metrics] == [50]
    assert metrics[0]['qrl/loss'] is None  # non-finite written as null


def test_divergence_keeps_the_last_finite_checkpoint(tmp_path, grid_data):
    cfg = methods.get('gcbc').preset('ci', env='pointmaze-medium', checkpoint_every=50, keep=5)
    out = str(tmp_path / 'run')
    with pytest.raises(fit.DivergedError, match=r'in updates 151-200 \(this run started from the beginning\): non-finite .*state.*newest checkpoint, step 150'):
        fit.train(_nan_after(160), cfg, grid_data, out, progress=False, log=lambda *_: None)
    assert fit.checkpoint_steps(out) == [50, 100, 150]
    t = fit.load(out, log=lambda *_: None)  # the newest is finite and loads
    assert t.step == 150 and all(np.isfinite(np.asarray(x)).all() for x in jax.tree.leaves(t.params))
    assert [m['step'] for m in _strict_lines(os.path.join(out, 'metrics.jsonl'))] == [50, 100, 150, 200]
    # --resume continues from 150 (here with the registry's gcbc, the fault being in the wrapper)
    t = fit.train('gcbc', None, grid_data, out, resume=True, progress=False, log=lambda *_: None)
    lines = _strict_lines(os.path.join(out, 'metrics.jsonl'))
    assert t.step == 200 and [m['step'] for m in lines] == [50, 100, 150, 200]
    assert math.isfinite(lines[-1]['actor/loss'])  # the diverged line was replaced


def test_divergence_of_one_seed_names_its_folder(tmp_path, grid_data):
    cfg = methods.get('gcbc').preset('ci', env='pointmaze-medium')
    outs = [str(tmp_path / f'seed_{i}') for i in range(2)]
    with pytest.raises(fit.DivergedError, match='seed folder .*seed_0.* in updates 101-150'):
        fit.train_seeds(_nan_after(120), [cfg, cfg], grid_data, outs, jax.random.split(jax.random.PRNGKey(0), 2),
                        progress=False, log=lambda *_: None)
    assert [fit.checkpoint_steps(o) for o in outs] == [[100], [100]]


def test_evaluation_refuses_non_finite_parameters(tmp_path, grid_data):
    cfg = methods.get('gcbc').preset('ci', env='pointmaze-medium', steps=100)
    out = str(tmp_path / 'run')
    t = fit.train('gcbc', cfg, grid_data, out, progress=False, log=lambda *_: None)
    saver = ckpt.Checkpointer(out, keep=None)
    bad = jax.tree.map(lambda x: x * jnp.nan if jnp.issubdtype(x.dtype, jnp.floating) else x, t.state)
    saver.save(200, bad, t.meta)  # as an older version could have written it
    saver.close()
    logs = []
    assert fit.load(out, log=logs.append).step == 100  # the newest fails its check: the previous, with one line
    assert len(logs) == 1 and 'checkpoint 200' in logs[0] and 'non-finite values in' in logs[0]
    with pytest.raises(ckpt.CheckpointError, match='checkpoint 200 .* non-finite values'):
        fit.load(out, step=200, log=lambda *_: None)
    assert fit.checkpoint_steps(out) == [100, 200]  # a reader moves nothing
    assert not math.isnan(float(jax.tree.leaves(t.params)[0].ravel()[0]))


def _swap_state_bytes(out: str, step: int, other: int) -> None:
    """Replace checkpoint ``step``'s array files with checkpoint ``other``'s, keeping ``step``'s
    config and digest: bytes that decode, finite, to another state, as damage that leaves the file
    format intact would (flipping bytes in place can also break the format, which is then a read
    error instead, depending on which of Orbax's files they land in)."""
    root = os.path.join(out, 'checkpoints')
    shutil.rmtree(os.path.join(root, str(step), 'state'))
    shutil.copytree(os.path.join(root, str(other), 'state'), os.path.join(root, str(step), 'state'))


@pytest.mark.parametrize('fault', ['nan', 'swapped'])
def test_resume_checks_what_it_restores(tmp_path, grid_file, grid_data, capfd, fault):
    """A newest checkpoint that reads but is unsound (a NaN state saved as newest; its array bytes
    replaced by another checkpoint's) is moved aside with one line naming the fault, and the run resumes from the previous
    step and ends bit-identical to one never interrupted; a divergence message names the step the
    run resumed from."""
    ref, out = str(tmp_path / 'ref'), str(tmp_path / 'run')
    base = ['train', '--dataset', grid_file, '--env', 'pointmaze-medium', '--preset', 'ci']
    assert cli.main(base + ['--out', ref, '--steps', '300']) == 0
    assert cli.main(base + ['--out', out]) == 0  # ci: 200 updates, checkpoints 100 and 200
    if fault == 'nan':
        t = fit.load(out, log=lambda *_: None)
        saver = ckpt.Checkpointer(out, keep=None)
        saver.save(300, jax.tree.map(lambda x: x * jnp.nan if jnp.issubdtype(x.dtype, jnp.floating) else x, t.state),
                   t.meta)
        saver.close()
        newest, why = 300, 'non-finite values in'
    else:
        _swap_state_bytes(out, 200, 100)
        newest, why = 200, 'do not match the digest saved with them'
    damaged = {os.path.relpath(os.path.join(d, n), out): open(os.path.join(d, n), 'rb').read()
               for d, _, names in os.walk(os.path.join(out, 'checkpoints', str(newest))) for n in names}
    capfd.readouterr()
    assert cli.main(['train', '--dataset', grid_file, '--resume', '--steps', '300', '--out', out]) == 0
    o, e = capfd.readouterr()
    warnings = [ln for ln in o.splitlines() if ln.startswith('warning:')]
    assert len(warnings) == 1 and f'checkpoint {newest}' in warnings[0] and why in warnings[0], warnings
    assert 'checkpoints_unreadable' in warnings[0] and 'Traceback' not in e
    start = 200 if fault == 'nan' else 100
    assert f'at step {start}' in o
    aside = os.path.join(out, 'checkpoints_unreadable', str(newest))
    kept = {os.path.relpath(os.path.join(d, n), aside): open(os.path.join(d, n), 'rb').read()
            for d, _, names in os.walk(aside) for n in names}
    assert kept == {os.path.relpath(k, os.path.join('checkpoints', str(newest))): v for k, v in damaged.items()}
    assert fit.checkpoint_steps(out)[-1] == 300 and _leaves(out) == _leaves(ref)

def test_divergence_after_a_resume_names_the_step_it_resumed_from(tmp_path, grid_data, monkeypatch):
    cfg = methods.get('gcbc').preset('ci', env='pointmaze-medium', checkpoint_every=50, keep=5)
    out = str(tmp_path / 'run')
    fit.train('gcbc', cfg, grid_data, out, progress=False, log=lambda *_: None)  # 200 updates
    poisoned = _nan_after(260)
    monkeypatch.setattr(methods, 'get', lambda name: poisoned)  # the saved run's method, now diverging
    with pytest.raises(fit.DivergedError, match=r'in updates 251-300 \(this run resumed from checkpoint 200\): '
                                                r'non-finite .*newest checkpoint, step 250'):
        fit.train('gcbc', None, grid_data, out, resume=True, steps=400, progress=False, log=lambda *_: None)


# -------------------------------------------------------------------------------- torn checkpoints
def _tear(out: str, step: int) -> dict:
    """Overwrite every file of checkpoint ``step``; returns {relative path: bytes} of what is there."""
    root = os.path.join(out, 'checkpoints', str(step))
    torn = {}
    for d, _, names in os.walk(root):
        for name in names:
            path = os.path.join(d, name)
            with open(path, 'wb') as f:
                f.write(b'torn')
            torn[os.path.relpath(path, root)] = b'torn'
    return torn


def _leaves(out: str):
    return [np.asarray(x).tobytes() for x in jax.tree.leaves(fit.load(out, log=lambda *_: None).state)]


def test_resume_sets_a_torn_checkpoint_aside_and_goes_on(tmp_path, grid_file, capfd):
    ref, out = str(tmp_path / 'ref'), str(tmp_path / 'run')
    base = ['train', '--dataset', grid_file, '--env', 'pointmaze-medium', '--preset', 'ci']
    assert cli.main(base + ['--out', ref, '--steps', '300']) == 0
    assert cli.main(base + ['--out', out]) == 0
    torn = _tear(out, 200)
    capfd.readouterr()
    assert cli.main(['train', '--dataset', grid_file, '--resume', '--steps', '300', '--out', out]) == 0
    o, e = capfd.readouterr()
    warnings = [ln for ln in o.splitlines() if ln.startswith('warning:')]
    assert len(warnings) == 1 and 'checkpoint 200' in warnings[0] and 'checkpoints_unreadable' in warnings[0]
    assert 'resumed' in o and 'at step 100' in o
    assert 'Traceback' not in e and 'absl' not in e and 'aqm-mjx: error' not in e
    aside = os.path.join(out, 'checkpoints_unreadable', '200')
    kept = {os.path.relpath(os.path.join(d, n), aside): open(os.path.join(d, n), 'rb').read()
            for d, _, names in os.walk(aside) for n in names}
    assert kept == torn  # moved, not deleted
    assert fit.checkpoint_steps(out)[-1] == 300 and _leaves(out) == _leaves(ref)  # as if nothing happened
    steps = [m['step'] for m in _strict_lines(os.path.join(out, 'metrics.jsonl'))]
    assert steps == sorted(set(steps)) and steps[-1] == 300


def test_seeds_resume_past_a_torn_checkpoint(tmp_path, grid_data):
    cfg = methods.get('gcbc').preset('ci', env='pointmaze-medium')
    outs = [str(tmp_path / f'seed_{i}') for i in range(2)]
    keys = jax.random.split(jax.random.PRNGKey(0), 2)
    fit.train_seeds('gcbc', [cfg, cfg], grid_data, outs, keys, progress=False, log=lambda *_: None)
    before = [_leaves(o) for o in outs]
    _tear(outs[1], 200)
    longer = dataclasses.replace(cfg, steps=300)
    logs = []
    fit.train_seeds('gcbc', [longer, longer], grid_data, outs, keys, progress=False, log=logs.append)
    assert any(ln.startswith('warning:') and 'moved to' in ln for ln in logs)
    assert any('resuming 2 seed(s) at step 100' in ln for ln in logs)
    assert [fit.checkpoint_steps(o) for o in outs] == [[100, 200, 300]] * 2
    assert _leaves(outs[0]) != before[0]  # went on to 300
    again = fit.load(outs[1], step=200, log=lambda *_: None).state
    assert [np.asarray(x).tobytes() for x in jax.tree.leaves(again)] == before[1]  # step 200 written again, equal


# ------------------------------------------------------------------------------------ two writers
def test_a_second_writer_is_refused_and_a_killed_holder_frees_the_folder(tmp_path, grid_file, capsys):
    out = str(tmp_path / 'run')
    train = ['train', '--dataset', grid_file, '--env', 'pointmaze-medium', '--preset', 'ci', '--out', out]
    first = subprocess.Popen([sys.executable, '-m', 'aqm_mjx.cli'] + train + ['--steps', str(10 ** 7)],
                             env=dict(os.environ, JAX_PLATFORMS='cpu'), stdout=subprocess.DEVNULL,
                             stderr=subprocess.DEVNULL)
    try:
        deadline = time.time() + 300
        while not fit.checkpoint_steps(out) and time.time() < deadline:  # running, and past its first save
            time.sleep(0.2)
        for argv in (train, ['train', '--dataset', grid_file, '--resume', '--out', out]):
            assert cli.main(argv) == 2, argv
            lines = _error_lines(capsys.readouterr().err)
            assert len(lines) == 1 and f'pid {first.pid} on {socket.gethostname()}' in lines[0], lines
            assert 'in use by another aqm-mjx process' in lines[0] and 'aqm-mjx train' in lines[0]
        # a run onto a training folder is refused for what the folder is, before any lock
        assert cli.main(['run', '--env', 'pointmaze-medium', '--preset', 'ci', '--dataset', grid_file,
                         '--out', out]) == 2
        lines = _error_lines(capsys.readouterr().err)
        assert len(lines) == 1 and 'is a training run folder' in lines[0], lines
        metrics_before = open(os.path.join(out, 'metrics.jsonl')).read()
    finally:
        first.kill()  # SIGKILL: the kernel drops its lock
        first.wait()
    assert open(os.path.join(out, 'metrics.jsonl')).read().startswith(metrics_before)  # nobody else wrote
    assert cli.main(['train', '--dataset', grid_file, '--resume', '--steps', '200', '--out', out]) == 0
    steps = [m['step'] for m in _strict_lines(os.path.join(out, 'metrics.jsonl'))]
    assert steps == sorted(set(steps))


# ------------------------------------------------------------------------ settings of a run folder
def test_run_with_other_settings_is_refused_and_more_steps_extend(tmp_path, grid_data, grid_file):
    from aqm_mjx import files, pipeline, run  # pylint: disable=import-outside-toplevel

    cfg = pipeline.RunConfig.preset('ci', env='pointmaze-medium')
    out, quiet = tmp_path / 'run', (lambda *_: None)
    tdir = str(out / 'train')
    fit.train(cfg.method, cfg.train, grid_data, tdir, progress=False, log=quiet)
    files.write_json(str(out / 'run.json'), {'marker': 1})
    other = cfg.with_overrides(['train.batch_size=32', 'train.seed=3'])
    with pytest.raises(ValueError, match=rf'other settings \(saved vs asked\): batch_size: {cfg.train.batch_size} '
                                         r'vs 32; seed: 0 vs 3'):
        run.run_stepwise(other, str(out), dataset=grid_file, log=quiet)
    assert json.load(open(out / 'run.json')) == {'marker': 1}  # refused before anything was written
    n = cfg.train.steps
    longer = dataclasses.replace(cfg.train, steps=n + 100)
    t = fit.train(cfg.method, longer, grid_data, tdir, resume='auto', progress=False, log=quiet)
    assert t.step == n + 100 and fit.checkpoint_steps(tdir)[-1] == n + 100  # extended, not skipped
    with pytest.raises(ValueError, match=f'trained to step {n + 100}, past the {n} asked for; ask for at least '
                                         rf'{n + 100} updates \(train --steps, run --set train.steps\)'):
        fit.train(cfg.method, cfg.train, grid_data, tdir, resume='auto', progress=False, log=quiet)


def test_resume_checks_every_option_it_is_given(tmp_path, grid_file, grid_data, capsys):
    """--resume with options: the saved values pass, a longer --steps extends, anything else (a --set,
    another method, preset or seed, another dataset) exits 2 with one line naming the fields, and
    nothing on disk changes; config.json keeps the dataset the run was trained on."""
    out = str(tmp_path / 'run')
    base = ['train', '--dataset', grid_file, '--env', 'pointmaze-medium', '--preset', 'ci', '--method', 'gcbc']
    assert cli.main(base + ['--out', out]) == 0
    saved = json.load(open(os.path.join(out, 'config.json')))
    assert saved['dataset'] == os.path.abspath(grid_file) and len(saved['data_sha256']) == 64
    before = {n: open(os.path.join(out, n), 'rb').read() for n in ('config.json', 'metrics.jsonl')}
    steps = fit.checkpoint_steps(out)
    resume = ['train', '--dataset', grid_file, '--resume', '--out', out]
    other = str(tmp_path / 'other.npz')  # the same shapes, one action changed
    changed = dict(grid_data, actions=grid_data['actions'].copy())
    changed['actions'][0, 0] += 0.5
    dsm.write_ogbench(other, changed)
    for extra, fields in ((['--set', 'lr=1e-9', '--set', 'batch_size=7'], ['batch_size: 64 vs 7', 'lr: 0.0003 vs 1e-09']),
                          (['--method', 'aqm'], ["method: 'gcbc' vs 'aqm'"]),
                          (['--preset', 'cpu'], ["preset: 'ci' vs 'cpu'"]),
                          (['--seed', '7'], ['seed: 0 vs 7']),
                          (['--env', 'antmaze-large'], ["env: 'pointmaze-medium' vs 'antmaze-large'"])):
        assert cli.main(resume + extra) == 2, extra
        lines = _error_lines(capsys.readouterr().err)
        assert len(lines) == 1 and 'differ from them (saved vs given)' in lines[0], lines
        assert all(f in lines[0] for f in fields), (fields, lines)
    assert cli.main(['train', '--dataset', other, '--resume', '--out', out]) == 2
    lines = _error_lines(capsys.readouterr().err)
    assert len(lines) == 1 and 'was trained on other data' in lines[0] and other in lines[0], lines
    assert {n: open(os.path.join(out, n), 'rb').read() for n in before} == before
    assert fit.checkpoint_steps(out) == steps
    # the saved values pass; a longer --steps extends; the record of the data stays
    assert cli.main(resume + ['--preset', 'ci', '--method', 'gcbc', '--seed', '0', '--set', 'batch_size=64',
                              '--steps', '300']) == 0
    assert fit.checkpoint_steps(out)[-1] == 300
    after = json.load(open(os.path.join(out, 'config.json')))
    assert (after['dataset'], after['data_sha256']) == (saved['dataset'], saved['data_sha256'])
    # a new run: --steps is what it prints and runs; --set env is refused for --env
    capsys.readouterr()
    assert cli.main(base + ['--out', str(tmp_path / 'n'), '--steps', '100']) == 0
    assert 'preset ci: 100 updates' in capsys.readouterr().out and fit.checkpoint_steps(str(tmp_path / 'n')) == [100]
    assert cli.main(base + ['--out', str(tmp_path / 'e'), '--set', 'env=antmaze-large']) == 2
    assert 'give --env instead' in _error_lines(capsys.readouterr().err)[0]
    assert not os.path.exists(tmp_path / 'e')


def test_a_fresh_start_drops_a_killed_runs_metrics(tmp_path, grid_data):
    out = str(tmp_path / 'run')
    os.makedirs(out)
    with open(os.path.join(out, 'metrics.jsonl'), 'w') as f:
        f.write('{"step": 50, "old": 1}\n{"step": 100, "old": 1}\n{"step": 1')  # killed mid-line, no checkpoint
    cfg = methods.get('gcbc').preset('ci', env='pointmaze-medium')
    fit.train('gcbc', cfg, grid_data, out, resume='auto', progress=False, log=lambda *_: None)
    lines = _strict_lines(os.path.join(out, 'metrics.jsonl'))
    assert [m['step'] for m in lines] == [50, 100, 150, 200] and not any('old' in m for m in lines)


def _edit_config(out: str, edit) -> None:
    path = os.path.join(out, 'config.json')
    meta = json.load(open(path))
    edit(meta)
    with open(path, 'w') as f:
        json.dump(meta, f)


def test_an_edited_config_json_is_named_and_checkpoints_stay(tmp_path, grid_data, grid_file, capsys):
    out = str(tmp_path / 'run')
    cfg = methods.get('gcbc').preset('ci', env='pointmaze-medium')
    fit.train('gcbc', cfg, grid_data, out, progress=False, log=lambda *_: None)
    original = open(os.path.join(out, 'config.json')).read()
    listing = sorted(os.listdir(os.path.join(out, 'checkpoints')))

    def restore():
        with open(os.path.join(out, 'config.json'), 'w') as f:
            f.write(original)

    def both(meta):
        meta['obs_size'] = 29
        meta['config']['env'] = 'antmaze-large'

    cases = [
        (both, r"config.json disagrees with the config saved in checkpoint 200 \(config.json vs checkpoint\): "
               r"env: 'antmaze-large' vs 'pointmaze-medium'; obs_size: 29 vs 2"),
        (lambda m: m.pop('config'), r"config.json: no 'config' \(is this a run folder"),
        (lambda m: m['config'].update(batch_size='abc'), r"GCBCConfig.batch_size must be int; got 'abc'"),
        (lambda m: m['config'].update(actor_hidden=[0, -3]), r'actor_hidden must be one or more layer widths'),
    ]
    for edit, message in cases:
        _edit_config(out, edit)
        with pytest.raises(ValueError, match=message):
            fit.load(out, log=lambda *_: None)
        for argv in (['evaluate', '--checkpoint', out, '--dataset', grid_file],
                     ['train', '--dataset', grid_file, '--resume', '--steps', '300', '--out', out]):
            assert cli.main(argv) == 2
            lines = _error_lines(capsys.readouterr().err)
            assert len(lines) == 1 and re.search(message, lines[0]), (argv, lines)
        assert sorted(os.listdir(os.path.join(out, 'checkpoints'))) == listing  # nothing moved aside
        assert not os.path.exists(os.path.join(out, 'checkpoints_unreadable'))
        restore()
    # truncated, or not an object: the file is named, no JSON decoder's position alone
    for text, message in ((original[: len(original) // 2], r'config.json is not valid JSON \(.*\); it is damaged or '
                                                              'truncated'),
                          ('[1, 2]', r'config.json holds a JSON list, not the object')):
        with open(os.path.join(out, 'config.json'), 'w') as f:
            f.write(text)
        for argv in (['evaluate', '--checkpoint', out, '--dataset', grid_file],
                     ['train', '--dataset', grid_file, '--resume', '--steps', '300', '--out', out]):
            assert cli.main(argv) == 2
            lines = _error_lines(capsys.readouterr().err)
            assert len(lines) == 1 and re.search(message, lines[0]) and out in lines[0], (argv, lines)
        assert sorted(os.listdir(os.path.join(out, 'checkpoints'))) == listing
        restore()
    assert fit.load(out, log=lambda *_: None).step == 200


# ------------------------------------------------------------------------------ damaged datasets
def test_damaged_or_odd_dataset_files_are_named(tmp_path, grid_file, grid_data, capsys):
    raw = open(grid_file, 'rb').read()
    flipped = bytearray(raw)
    for i in range(len(raw) // 3, len(raw) // 3 + 64):  # inside the compressed observations
        flipped[i] ^= 0xFF
    complex_obs = dict(grid_data, observations=grid_data['observations'].astype(np.complex64))
    cases = {'empty.npz': (b'', r'empty file \(0 bytes\)'),
             'text.npz': (b'observations,actions\n1,2\n', r"not an .npz archive .*starts with b'obse'"),
             'flipped.npz': (bytes(flipped), r'is damaged \((BadZipFile|error|ValueError)'),
             'cut.npz': (raw[: len(raw) // 2], r'damaged .npz archive \(BadZipFile'),
             'complex.npz': (complex_obs, r'observations has dtype complex64; expected real numbers')}
    for name, (content, message) in cases.items():
        path = str(tmp_path / name)
        if isinstance(content, dict):
            np.savez(path, **content)
        else:
            with open(path, 'wb') as f:
                f.write(content)
        with pytest.raises(dsm.DatasetError, match=message):
            dsm.read_ogbench(path)
        out = str(tmp_path / f'run-{name}')
        for argv in (['train', '--dataset', path, '--env', 'pointmaze-medium', '--out', out],
                     ['run', '--dataset', path, '--env', 'pointmaze-medium', '--preset', 'ci', '--out', out],
                     ['compare', '--dataset', path, '--env', 'pointmaze-medium', '--preset', 'ci', '--methods',
                      'gcbc', '--seeds', '1', '--out', out]):
            assert cli.main(argv) == 2, argv
            lines = _error_lines(capsys.readouterr().err)
            assert len(lines) == 1 and re.search(message, lines[0]), (name, argv[0], lines)
            assert not os.path.exists(out), argv  # nothing left behind: no run.json, compare.json or lock
    with pytest.raises(dsm.DatasetError, match='observations has dtype complex64'):
        dsm.to_device(complex_obs)  # arrays handed over in code are held to the same rule


def test_a_dataset_named_for_another_maze_is_refused(tmp_path, grid_file, capsys):
    named = str(tmp_path / 'pointmaze-medium-navigate-v0.npz')
    os.replace(grid_file, named)
    out = str(tmp_path / 'run')
    assert cli.main(['train', '--dataset', named, '--env', 'pointmaze-large', '--out', out]) == 2
    lines = _error_lines(capsys.readouterr().err)
    assert len(lines) == 1 and 'named for pointmaze-medium, not pointmaze-large' in lines[0]
    assert not os.path.exists(out)


# ----------------------------------------------------------------------- full and read-only disks
@pytest.fixture
def small_disk(tmp_path):
    """``mount(size) -> folder``: a tmpfs of ``size`` (a real full disk); ``remount_ro(folder)``.
    Skips where mounting is not allowed (the suite runs as root in CI, where it is)."""
    mounted = []

    def mount(size: str) -> str:
        folder = tmp_path / f'disk{len(mounted)}'
        folder.mkdir()
        p = subprocess.run(['mount', '-t', 'tmpfs', '-o', f'size={size}', 'tmpfs', str(folder)], capture_output=True)
        if p.returncode:
            pytest.skip(f'cannot mount a tmpfs here: {p.stderr.decode().strip()}')
        mounted.append(str(folder))
        return str(folder)

    def remount_ro(folder: str) -> None:
        subprocess.run(['mount', '-o', 'remount,ro', folder], check=True)

    mount.remount_ro = remount_ro
    yield mount
    for folder in mounted:
        subprocess.run(['umount', '-l', folder], check=False)


def _fill(folder: str, leave: int = 0) -> str:
    """Fill the file system of ``folder`` up to ``leave`` free bytes; returns the filler's path."""
    import shutil  # pylint: disable=import-outside-toplevel

    path = os.path.join(folder, 'filler')
    with open(path, 'wb') as f:
        try:
            while shutil.disk_usage(folder).free > leave:
                f.write(b'\0' * min(1 << 20, max(shutil.disk_usage(folder).free - leave, 1)))
                f.flush()
        except OSError:
            pass
    return path


def test_disk_full_during_training_leaves_the_last_checkpoint_and_resumes(small_disk, grid_file, capsys,
                                                                         monkeypatch):
    disk = small_disk('64m')
    out = os.path.join(disk, 'run')
    argv = ['train', '--dataset', grid_file, '--env', 'pointmaze-medium', '--preset', 'ci', '--out', out,
            '--set', 'checkpoint_every=50']
    real_save, saves = ckpt.Checkpointer.save, []

    def save_then_fill(self, step, state, config):
        if saves:  # the disk fills up (another job) after the first checkpoint
            _fill(disk)
        saves.append(step)
        real_save(self, step, state, config)

    monkeypatch.setattr(ckpt.Checkpointer, 'save', save_then_fill)
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    lines = _error_lines(err)
    assert len(lines) == 1 and 'cannot write checkpoint 100' in lines[0] and 'No space left' in lines[0], err
    assert sorted(os.listdir(os.path.join(out, 'checkpoints'))) == ['50']  # no temporary folder left
    steps = [m['step'] for m in _strict_lines(os.path.join(out, 'metrics.jsonl'))]  # whole lines only
    assert steps == sorted(set(steps))
    monkeypatch.setattr(ckpt.Checkpointer, 'save', real_save)
    os.remove(os.path.join(disk, 'filler'))
    assert cli.main(['train', '--dataset', grid_file, '--resume', '--out', out]) == 0
    assert fit.checkpoint_steps(out)[-1] == 200


def test_no_room_and_read_only_outputs_fail_before_the_work(small_disk, grid_file, grid_data, capsys, tmp_path):
    disk = small_disk('64m')
    run_dir = os.path.join(disk, 'run')
    cfg = methods.get('gcbc').preset('ci', env='pointmaze-medium', steps=100)
    fit.train('gcbc', cfg, grid_data, run_dir, progress=False, log=lambda *_: None)
    before = {os.path.relpath(os.path.join(d, n), run_dir) for d, _, ns in os.walk(run_dir) for n in ns}
    # no room: checkpoints of a new run, a collection
    _fill(disk, leave=200_000)
    cases = [(['train', '--dataset', grid_file, '--env', 'pointmaze-medium', '--preset', 'ci', '--out',
               os.path.join(disk, 'new')], r'checkpoints of .* MiB needs about .* MiB in .*new; only .* MiB are free'),
             (['collect', '--env', 'antmaze-medium', '--out', os.path.join(disk, 'd.npz')],
              r'the collected dataset needs about .* MiB')]
    for argv, message in cases:
        assert cli.main(argv) == 2
        lines = _error_lines(capsys.readouterr().err)
        assert len(lines) == 1 and re.search(message, lines[0]), lines
    os.remove(os.path.join(disk, 'filler'))
    # read-only: resume, evaluate, collect all stop at once
    small_disk.remount_ro(disk)
    cases = [['train', '--dataset', grid_file, '--resume', '--steps', '200', '--out', run_dir],
             ['evaluate', '--checkpoint', run_dir, '--dataset', grid_file],
             ['collect', '--env', 'pointmaze-medium', '--out', os.path.join(disk, 'd.npz')]]
    for argv in cases:
        assert cli.main(argv) == 2
        lines = _error_lines(capsys.readouterr().err)
        assert len(lines) == 1 and 'Read-only file system' in lines[0], lines
    after = {os.path.relpath(os.path.join(d, n), run_dir) for d, _, ns in os.walk(run_dir) for n in ns}
    assert after == before and not os.path.exists(os.path.join(disk, 'new'))
    # a file where a folder should be
    blocker = str(tmp_path / 'file')
    open(blocker, 'w').close()
    assert cli.main(['collect', '--env', 'pointmaze-medium', '--out', blocker + '/x.npz']) == 2
    assert 'is a file, not a folder' in _error_lines(capsys.readouterr().err)[0]


def test_nothing_long_ends_in_a_lost_result(small_disk, grid_file, grid_data, tmp_path, capsys, monkeypatch):
    """A full disk: a new train leaves no empty folder or lock behind; a metrics line that does not fit
    is cut off whole (nothing left to flush at close); evaluate reserves room for its outputs before
    any episode; a collect whose picture does not fit keeps its complete data and says so."""
    from aqm_mjx.data import collect  # pylint: disable=import-outside-toplevel

    disk = small_disk('8m')
    metrics = os.path.join(disk, 'metrics.jsonl')
    with open(metrics, 'wb') as f:
        f.write(b'{"step": 50}\n')  # a whole line; its page has room left
    run_dir = str(tmp_path / 'run')
    cfg = methods.get('gcbc').preset('ci', env='pointmaze-medium', steps=100)
    fit.train('gcbc', cfg, grid_data, run_dir, progress=False, log=lambda *_: None)
    _fill(disk)
    # train: not even the lock's line fits; exit 2, one line naming the folder, no folder left
    new = os.path.join(disk, 'new')
    assert cli.main(['train', '--dataset', grid_file, '--env', 'pointmaze-medium', '--preset', 'ci', '--out', new]) == 2
    lines = _error_lines(capsys.readouterr().err)
    assert len(lines) == 1 and new in lines[0] and 'No space left' in lines[0], lines
    assert not os.path.exists(new)
    # a metrics line longer than the room left: a partial write, then ENOSPC; the file is cut back whole
    f = open(metrics, 'ab', buffering=0)  # pylint: disable=consider-using-with
    with pytest.raises(OSError, match=f'cannot append to {re.escape(metrics)}: No space left'):
        fit._append(f, json.dumps({'step': 100, 'pad': 'x' * 20000}) + '\n')
    f.close()  # nothing buffered: no second error, no torn line
    assert open(metrics, 'rb').read() == b'{"step": 50}\n'
    # evaluate: refused before the map and the episodes (fit.load is not reached)
    monkeypatch.setattr(fit, 'load', lambda *a, **k: pytest.fail('loaded a checkpoint on a full disk'))
    ev_out = os.path.join(disk, 'eval')
    assert cli.main(['evaluate', '--checkpoint', run_dir, '--dataset', grid_file, '--out', ev_out]) == 2
    lines = _error_lines(capsys.readouterr().err)
    assert len(lines) == 1 and "the evaluation's results and pictures needs about 2.0 MiB" in lines[0], lines
    assert not os.path.exists(ev_out)
    monkeypatch.undo()
    # collect: the data are written, the picture finds no room -> a warning, exit 0, data complete
    def no_room(result, path, n=12):
        with open(path, 'wb') as fp:
            fp.write(b'\x89PNG half')
        raise OSError(28, 'No space left on device')

    monkeypatch.setattr(collect, 'plot', no_room)
    out = str(tmp_path / 'pm.npz')
    assert cli.main(['collect', '--env', 'pointmaze-medium', '--style', 'explore', '--episodes', '4', '--steps', '30',
                     '--out', out]) == 0
    err = capsys.readouterr().err
    assert f'warning: {tmp_path / "pm.png"} could not be written (No space left on device); the data in' in err
    assert not os.path.exists(tmp_path / 'pm.png')  # no half picture
    assert dsm.read_ogbench(out, add_info=False)['observations'].shape == (4 * 30, 2)
    assert json.load(open(tmp_path / 'pm.json'))['picture'] is None


def test_batches_that_cannot_fit_are_refused_before_compiling(tmp_path, grid_file, grid_data, capsys, monkeypatch):
    """With 1 GiB available, absurd sizes exit 2 with one line naming the option, before anything is
    compiled or written; the sizes the suite uses pass the same check."""
    from aqm_mjx import envs, memory  # pylint: disable=import-outside-toplevel
    from aqm_mjx.data import collect  # pylint: disable=import-outside-toplevel

    run_dir = str(tmp_path / 'run')
    fit.train('gcbc', methods.get('gcbc').preset('ci', env='pointmaze-medium', steps=100), grid_data, run_dir,
              progress=False, log=lambda *_: None)
    gib = 2 ** 30
    monkeypatch.setattr(memory, 'host_available', lambda: gib)
    monkeypatch.setattr(memory, 'available', lambda: (gib, 'host'))
    monkeypatch.setattr(jax, 'jit', lambda *a, **k: pytest.fail('compiled before the memory check'))
    cases = [(['collect', '--env', 'pointmaze-medium', '--episodes', '1000000', '--batch', '64',
               '--out', str(tmp_path / 'c.npz')], 'lower --episodes'),
             (['collect', '--env', 'pointmaze-medium', '--episodes', '10', '--batch', '100000000',
               '--out', str(tmp_path / 'c.npz')], 'lower --batch'),
             (['evaluate', '--checkpoint', run_dir, '--dataset', grid_file, '--episodes', '100000000',
               '--out', str(tmp_path / 'ev')], 'lower --episodes'),
             (['evaluate', '--checkpoint', run_dir, '--dataset', grid_file, '--envs', '1000000000',
               '--out', str(tmp_path / 'ev')], 'lower --envs'),
             (['train', '--dataset', grid_file, '--env', 'pointmaze-medium', '--preset', 'ci', '--set',
               'batch_size=100000000', '--out', str(tmp_path / 'tr')], 'lower --set batch_size'),
             # a size field alone (the case: 50M IQE components grew past 15 GB before any refusal)
             (['train', '--dataset', grid_file, '--env', 'pointmaze-medium', '--preset', 'ci', '--set',
               'n_components=50000000', '--out', str(tmp_path / 'tr')], 'n_components'),
             (['train', '--dataset', grid_file, '--env', 'pointmaze-medium', '--preset', 'ci', '--method', 'crl',
               '--set', 'latent=50000000', '--out', str(tmp_path / 'tr')], 'latent'),
             (['train', '--dataset', grid_file, '--env', 'pointmaze-medium', '--preset', 'ci', '--set',
               'q_hidden=100000,100000', '--out', str(tmp_path / 'tr')], 'q_hidden'),
             (['run', '--env', 'pointmaze-medium', '--preset', 'ci', '--dataset', grid_file, '--set',
               'n_components=50000000', '--out', str(tmp_path / 'rn')], 'n_components'),
             (['compare', '--env', 'pointmaze-medium', '--preset', 'ci', '--dataset', grid_file, '--methods', 'gcbc',
               '--seeds', '2', '--set', 'gcbc:actor_hidden=20000,20000', '--out', str(tmp_path / 'cm')], 'or --seeds')]
    for argv, option in cases:
        assert cli.main(argv) == 2, argv
        lines = _error_lines(capsys.readouterr().err)
        assert len(lines) == 1 and 'memory; 1.0 GiB are available' in lines[0] and option in lines[0], lines
    assert sorted(os.listdir(tmp_path)) == ['grid.npz', 'run']  # nothing written
    # what the suite runs fits in that 1 GiB
    collect.check_memory(collect.CollectConfig(env='antmaze-medium', episodes=100, batch=55))
    for name in methods.names():  # every method's cpu networks, state included
        m = methods.get(name)
        memory.check(memory.training_bytes(m.preset('cpu', env='antmaze-medium'), 29, 8, m), name, 'x')
    # by hand: the ci AQM (29 -> 32 -> 32 -> 32 IQE, a 61 -> 32 -> 32 -> 8 policy twice, Adam's two moments)
    aqm = methods.get('aqm')
    state, outputs = memory.learner_state(aqm, aqm.preset('ci', env='antmaze-medium'), 29, 8)
    iqe = (29 * 32 + 32) + (32 * 32 + 32) + (32 * 32 + 32) + 1  # two hidden layers, the 32 components, alpha
    assert state > 3 * 4 * iqe and outputs >= 3 * (32 + 32 + 32)
    assert 0 < memory.env_state_bytes(envs.make('antmaze-medium')) < 2 ** 20


def test_ctrl_c_during_a_save_leaves_no_partial_checkpoint(tmp_path, grid_file, capfd, monkeypatch):
    """Ctrl-C while Orbax writes checkpoint 100 (its temporary folder already there): exit 130, the
    resume hint and no traceback, no temporary folder left; --resume goes on from the start."""
    out = str(tmp_path / 'run')
    real = ckpt.Checkpointer.save

    def interrupted(self, step, state, config):
        if step == 100:
            def partial_then_interrupt(*a, **k):
                os.makedirs(os.path.join(out, 'checkpoints', '100.orbax-checkpoint-tmp-1764752000'), exist_ok=True)
                with open(os.path.join(out, 'checkpoints', '100.orbax-checkpoint-tmp-1764752000', 'part'), 'wb') as f:
                    f.write(b'half an array')
                raise KeyboardInterrupt
            self._mngr.save = partial_then_interrupt
        return real(self, step, state, config)

    monkeypatch.setattr(ckpt.Checkpointer, 'save', interrupted)
    capfd.readouterr()
    assert cli.main(['train', '--dataset', grid_file, '--env', 'pointmaze-medium', '--preset', 'ci', '--out', out]) == 130
    _, e = capfd.readouterr()
    assert 'interrupted. Run the same command with --resume' in e and 'Traceback' not in e, e
    assert os.listdir(os.path.join(out, 'checkpoints')) == []
    monkeypatch.setattr(ckpt.Checkpointer, 'save', real)
    assert cli.main(['train', '--dataset', grid_file, '--resume', '--out', out]) == 0
    assert fit.checkpoint_steps(out) == [100, 200]


def test_a_disk_that_fills_in_the_middle_of_a_save_or_a_results_write(tmp_path, grid_file, capfd, monkeypatch):
    """The disk fills while Orbax writes checkpoint 200 (half its files there): exit 2, one line naming the
    checkpoint and the full disk, no temporary folder, checkpoint 100 kept byte for byte and metrics
    not past it; --resume then ends bit-identical to a run never interrupted. A results.json or
    episodes.npz write that fills the disk leaves the previous files whole."""
    from aqm_mjx.evaluation import report  # pylint: disable=import-outside-toplevel

    ref, out = str(tmp_path / 'ref'), str(tmp_path / 'run')
    base = ['train', '--dataset', grid_file, '--env', 'pointmaze-medium', '--preset', 'ci']
    assert cli.main(base + ['--out', ref]) == 0
    real = ckpt.Checkpointer.save

    def fills(self, step, state, config):
        if step == 200:
            def half_then_full(*a, **k):
                tmp = os.path.join(out, 'checkpoints', '200.orbax-checkpoint-tmp-1764752001')
                os.makedirs(tmp, exist_ok=True)
                with open(os.path.join(tmp, 'part'), 'wb') as f:
                    f.write(b'half an array')
                raise OSError(28, 'No space left on device')
            self._mngr.save = half_then_full
        return real(self, step, state, config)

    monkeypatch.setattr(ckpt.Checkpointer, 'save', fills)
    capfd.readouterr()
    assert cli.main(base + ['--out', out]) == 2
    _, e = capfd.readouterr()
    lines = _error_lines(e)
    assert len(lines) == 1 and 'cannot write checkpoint 200' in lines[0] and 'No space left' in lines[0], e
    assert 'Traceback' not in e and sorted(os.listdir(os.path.join(out, 'checkpoints'))) == ['100']
    first = os.path.join(out, 'checkpoints', '100')
    kept = {os.path.relpath(os.path.join(d, n), first): open(os.path.join(d, n), 'rb').read()
            for d, _, ns in os.walk(first) for n in ns}
    assert fit.load(out, log=lambda *_: None).step == 100  # the checkpoint before the failed save reads
    assert {os.path.relpath(os.path.join(d, n), first): open(os.path.join(d, n), 'rb').read()
            for d, _, ns in os.walk(first) for n in ns} == kept
    monkeypatch.setattr(ckpt.Checkpointer, 'save', real)
    assert cli.main(['train', '--dataset', grid_file, '--resume', '--out', out]) == 0
    assert fit.checkpoint_steps(out) == [100, 200] and _leaves(out) == _leaves(ref)
    # a results write that fills the disk: the old results.json and episodes.npz stay whole
    folder = tmp_path / 'ev'
    folder.mkdir()
    (folder / 'results.json').write_text('{"old": true}')
    np.savez(folder / 'episodes.npz', success=np.array([True]))
    before = {f: (folder / f).read_bytes() for f in ('results.json', 'episodes.npz')}

    def full_savez(path, **arrays):
        with open(path, 'wb') as f:
            f.write(b'PK half')
        raise OSError(28, 'No space left on device')

    monkeypatch.setattr(np, 'savez_compressed', full_savez)
    res = types.SimpleNamespace(table=types.SimpleNamespace(agent=[0], variant=[0], task=[1], episode=[0]),
                                agents=['aqm'], variants=['base'], success=[True], pruned=[0], removed=[0],
                                n_legs=[1])
    with pytest.raises(OSError, match='No space left'):
        report.write_episodes(res, str(folder / 'episodes.npz'))
    monkeypatch.setattr(files, 'os', types.SimpleNamespace(**{**vars(os), 'replace': _full_replace}))
    with pytest.raises(OSError, match='No space left'):
        files.write_json(str(folder / 'results.json'), {'new': True})
    monkeypatch.undo()
    assert {f: (folder / f).read_bytes() for f in ('results.json', 'episodes.npz')} == before
    assert sorted(os.listdir(folder)) == ['episodes.npz', 'results.json']  # no temporary file left


def _full_replace(src, dst):
    raise OSError(28, 'No space left on device')


def test_evaluating_a_folder_in_training_names_the_writer(tmp_path, grid_data):
    """fit.load of a folder another process holds: one warning naming that process (pid, command), and
    an error naming it when no checkpoint can be read; a folder nobody holds: no warning."""
    out = str(tmp_path / 'run')
    fit.train('gcbc', methods.get('gcbc').preset('ci', env='pointmaze-medium', steps=100), grid_data, out,
              progress=False, log=lambda *_: None)
    logs = []
    assert fit.load(out, log=logs.append).step == 100 and logs == []
    holder = subprocess.Popen([sys.executable, '-c', 'import sys, time\nfrom aqm_mjx import files\n'
                               f'with files.run_lock({out!r}):\n    print("held", flush=True)\n    time.sleep(60)'],
                              stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == 'held'
        assert fit.load(out, log=logs.append).step == 100
        assert len(logs) == 1 and f'being trained by another process (pid {holder.pid} on' in logs[0], logs
        _tear(out, 100)  # as when the writer deletes the step being read (keep)
        with pytest.raises(ckpt.CheckpointError, match=rf'while another process trains into it \(pid {holder.pid}'):
            fit.load(out, log=lambda *_: None)
    finally:
        holder.kill()
        holder.wait()


# ------------------------------------------------------------------- arguments checked up front
def test_bad_arguments_are_named_before_any_work(tmp_path, grid_data, grid_file, capsys, monkeypatch):
    run_dir = str(tmp_path / 'run')
    cfg = methods.get('gcbc').preset('ci', env='pointmaze-medium', steps=100)
    fit.train('gcbc', cfg, grid_data, run_dir, progress=False, log=lambda *_: None)

    def no_loading(*a, **k):
        raise AssertionError('loaded a checkpoint before checking the arguments')

    monkeypatch.setattr(fit, 'load', no_loading)
    ev = ['evaluate', '--checkpoint', run_dir, '--dataset', grid_file]
    cases = [(ev + ['--tasks', '0'], r'task'),
             (ev + ['--tasks', '1', '1'], r'ProtocolConfig.tasks repeats task\(s\) \[1\]'),
             (ev + ['--shift', 'bogus'], r'bogus'),
             (ev + ['--delta', '-1'], r'MapConfig.delta must be a finite number > 0; got -1'),
             (['evaluate', '--checkpoint', run_dir, '--dataset', str(tmp_path / 'missing.npz')],
              r'--dataset .*missing.npz: no such file'),
             (['render', '--env', 'pointmaze-medium', '--deltas', '0', '--out', str(tmp_path / 'r.png')],
              r'--deltas must be finite numbers > 0; got \[0.0\]'),
             (['train', '--dataset', grid_file, '--env', 'pointmaze-medium', '--out', str(tmp_path / 'q'),
               '--set', 'q_hidden=0,-3'], r'AQMConfig.q_hidden must be one or more layer widths >= 1'),
             (['train', '--dataset', grid_file, '--env', 'pointmaze-medium', '--out', str(tmp_path / 'q'),
               '--set', 'batch_size=abc'], r"batch_size \(int\): cannot read 'abc'")]
    for argv, message in cases:
        assert cli.main(argv) == 2, argv
        lines = _error_lines(capsys.readouterr().err)
        assert len(lines) == 1 and re.search(message, lines[0]), (argv, lines)
    assert not os.path.exists(tmp_path / 'q') and not os.path.exists(tmp_path / 'ro')
    assert not os.path.exists(os.path.join(run_dir, 'eval'))


def test_training_bar_draws_once_per_chunk(tmp_path, grid_data, monkeypatch):
    """Logs of long runs hold one bar line per jitted chunk (a redraw for the postfix doubled them)."""
    import io
    import tqdm.auto

    draws, bars = [], []

    class Counting(tqdm.auto.tqdm):  # draws on every update, whatever the time since the last one
        def __init__(self, *args, **kwargs):
            super().__init__(*args, mininterval=0, miniters=0, file=io.StringIO(), **kwargs)

        def display(self, *args, **kwargs):
            draws.append(self.n)
            return super().display(*args, **kwargs)

        def set_postfix(self, ordered_dict=None, refresh=True, **kwargs):
            self.postfix_seen = dict(ordered_dict or {})
            bars.append(self)
            return super().set_postfix(ordered_dict, refresh=refresh, **kwargs)

    monkeypatch.setattr(tqdm.auto, 'tqdm', Counting)
    cfg = methods.get('gcbc').preset('ci', env='pointmaze-medium', steps=100)
    fit.train('gcbc', cfg, grid_data, str(tmp_path / 'run'), progress=True, log=lambda *_: None)
    u = cfg.updates_per_call
    # open, the 'compiling' note before the first chunk, each chunk, close
    assert 100 % u == 0 and draws == [0, 0] + list(range(u, 101, u)) + [100]
    assert list(bars[0].postfix_seen) == ['actor']  # gcbc's loss, under its label


def test_a_metrics_file_that_is_not_text_is_named(tmp_path):
    """A metrics.jsonl replaced by binary bytes: reading it for curves or trimming it on resume is one
    error naming the file (not a codec traceback), and the file is left as it was."""
    from aqm_mjx import files  # pylint: disable=import-outside-toplevel
    from aqm_mjx.evaluation import plots  # pylint: disable=import-outside-toplevel
    from aqm_mjx.learn import folder  # pylint: disable=import-outside-toplevel

    path = str(tmp_path / 'metrics.jsonl')
    junk = b'{"step": 50}\n\x89PNG\r\n\x1a\n\xff\xfe'
    with open(path, 'wb') as f:
        f.write(junk)
    for read in (lambda: plots.read_metrics(path), lambda: folder.trim_metrics(path, 100)):
        with pytest.raises(files.BadFileError, match=f'{re.escape(path)} is not text .* byte 13 cannot be read'):
            read()
    assert open(path, 'rb').read() == junk
    with open(path, 'w') as f:
        f.write('{"step": 50}\n{"step": 150}\n{"st')  # text, a torn last line: read as before
    assert plots.read_metrics(path) == [{'step': 50}, {'step': 150}]


def _damage_every_checkpoint(out: str, how: str) -> None:
    """Every data file of every checkpoint's state: truncated to 10 bytes, a byte flipped, or removed."""
    for step in os.listdir(os.path.join(out, 'checkpoints')):
        for d, _, names in os.walk(os.path.join(out, 'checkpoints', step, 'state')):
            for n in names:
                p = os.path.join(d, n)
                if os.path.basename(d) != 'd':
                    continue
                if how == 'truncate':
                    os.truncate(p, 10)
                elif how == 'flip':
                    b = bytearray(open(p, 'rb').read())
                    b[len(b) // 2] ^= 0xFF
                    open(p, 'wb').write(bytes(b))
                else:
                    os.remove(p)


@pytest.mark.parametrize('how', ['truncate', 'flip', 'remove'])
def test_resume_with_every_checkpoint_damaged_prints_its_lines_and_nothing_else(tmp_path, grid_file, how):
    """`train --resume` on a run whose every checkpoint is damaged: each is named in one warning line and
    the run ends with one error line, three runs in a row, with none of the tracebacks that Orbax's
    abandoned reads used to print afterwards (``Event loop is closed``, ``Task exception was never
    retrieved``: 3 runs in 5 before)."""
    out = str(tmp_path / 'run')
    assert cli.main(['train', '--dataset', grid_file, '--env', 'pointmaze-medium', '--preset', 'ci',
                     '--out', out]) == 0  # checkpoints 100 and 200
    for k in range(3):
        run_dir = str(tmp_path / f'run{k}')
        shutil.copytree(out, run_dir)
        _damage_every_checkpoint(run_dir, how)
        r = subprocess.run([sys.executable, '-m', 'aqm_mjx.cli', 'train', '--dataset', grid_file, '--resume',
                            '--out', run_dir], capture_output=True, text=True, timeout=300,
                           env=dict(os.environ, JAX_PLATFORMS='cpu'))
        text = r.stdout + r.stderr
        assert r.returncode == 2 and len(_error_lines(r.stderr)) == 1, text[-3000:]
        assert 'checkpoint 200' in _error_lines(r.stderr)[0] and 'checkpoint 100' in _error_lines(r.stderr)[0]
        warnings = [ln for ln in r.stdout.splitlines() if ln.startswith('warning:')]
        assert len(warnings) == 2, text[-3000:]
        assert 'Traceback' not in text and 'Event loop' not in text and 'never retrieved' not in text, text[-3000:]


def test_a_run_trained_from_arrays_resumes_with_the_file_written_from_them(tmp_path):
    """The data fingerprint config.json records is the file's: a dict with float ``terminals`` (as the
    synthetic walks give) and the .npz written from it agree (they did not: the demo model could not be
    resumed with its own file)."""
    from aqm_mjx.learn import folder  # pylint: disable=import-outside-toplevel

    data = synthetic.point_walks(n_traj=20, t_len=50, seed=0)
    assert data['terminals'].dtype != bool
    path = str(tmp_path / 'pointmaze-medium-navigate.npz')
    np.savez(path, **data)
    read = dsm.read_ogbench(path)
    assert read['terminals'].dtype == bool
    assert folder.fingerprint(data) == folder.fingerprint(read)
    out = str(tmp_path / 'run')
    cfg = methods.get('gcbc').preset('ci', env='pointmaze-medium', steps=100)
    fit.train('gcbc', cfg, data, out, dataset_path=path, progress=False, log=lambda *_: None)
    assert cli.main(['train', '--dataset', path, '--resume', '--steps', '200', '--out', out]) == 0
    assert fit.checkpoint_steps(out)[-1] == 200


def test_one_program_refuses_bad_input_before_it_writes(tmp_path, grid_file, capsys):
    """`run --one-program`: a damaged --dataset, --seeds 0 and an update that cannot fit in memory are
    each one error line, and no run folder (no lock file) is left behind."""
    damaged = str(tmp_path / 'pointmaze-medium-navigate.npz')
    with open(grid_file, 'rb') as f:
        open(damaged, 'wb').write(f.read()[:300])  # cut inside the zip
    base = ['run', '--env', 'pointmaze-medium', '--preset', 'ci', '--one-program']
    cases = [(['--dataset', damaged], 'pointmaze-medium-navigate.npz'),
             (['--dataset', grid_file, '--seeds', '0'], '--seeds must be an integer >= 1'),
             (['--dataset', grid_file, '--seeds', '2', '--set', 'n_components=50000000'], 'n_components')]
    for k, (extra, says) in enumerate(cases):
        out = str(tmp_path / f'out{k}')
        capsys.readouterr()
        assert cli.main(base + extra + ['--out', out]) == 2
        lines = _error_lines(capsys.readouterr().err)
        assert len(lines) == 1 and says in lines[0], (extra, lines)
        assert not os.path.exists(out), extra
