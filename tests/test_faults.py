"""Runs that meet faults: divergence, torn checkpoints, two writers, full disks, damaged inputs.

Each test makes the fault itself and checks the exit code, the one-line message and that nothing
already on disk was lost or left half-written.
"""

import json
import math
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from aqm_mjx import cli
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
    with pytest.raises(fit.DivergedError, match=r'in updates 151-200: non-finite .*state.*newest checkpoint, step 150'):
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
    with pytest.raises(fit.DivergedError, match='checkpoint 200 holds non-finite parameters'):
        fit.load(out, log=lambda *_: None)
    assert fit.load(out, step=100, log=lambda *_: None).step == 100
    assert not math.isnan(float(jax.tree.leaves(t.params)[0].ravel()[0]))
