"""``aqm-mjx compare``: seeds trained as one vmapped program into ordinary run folders, resume
without redoing finished methods, intervals a person can recompute, and requests checked first."""

import dataclasses
import json
import math
import os
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats as sps

from aqm_mjx import assess, cli, compare, envs, files, pipeline, presets, run
from aqm_mjx.data import dataset as ds_io
from aqm_mjx.data import synthetic
from aqm_mjx.evaluation import plots, report, stats
from aqm_mjx.learn import fit, methods
from aqm_mjx.pipeline import stage_keys

QUIET = dict(log=lambda *_: None)


def test_t_quantiles_match_scipy_and_intervals_are_recomputable():
    for df in list(range(1, 60)) + [100, 1000, 10 ** 6]:
        assert stats.t975(df) == pytest.approx(sps.t.ppf(0.975, df), rel=1e-4)
    with pytest.raises(ValueError, match='degree of freedom'):
        stats.t975(0)
    # two seeds at 0.8 and 0.9: mean 0.85, sd 0.0707, half-width 12.706 * 0.0707 / sqrt(2) = 0.635
    lo, hi = stats.seed_interval([0.8, 0.9])
    assert (lo, hi) == (pytest.approx(0.85 - 0.6353, abs=1e-3), 1.0)
    lo, hi = stats.seed_interval([0.5, 0.6, 0.7])
    assert hi - 0.6 == pytest.approx(sps.t.ppf(0.975, 2) * 0.1 / math.sqrt(3), rel=1e-4)
    assert all(math.isnan(x) for x in stats.seed_interval([0.5]))
    # Wilson's interval, recomputed from its formula: 45 of 50
    z, n, p = 1.959964, 50, 0.9
    c = (p + z * z / (2 * n)) / (1 + z * z / n)
    h = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    assert stats.wilson(45, 50) == (pytest.approx(c - h), pytest.approx(c + h))
    assert stats.wilson(0, 10)[0] == 0.0 and stats.wilson(10, 10)[1] == pytest.approx(1.0)
    with pytest.raises(ValueError, match='successes'):
        stats.wilson(11, 10)


def test_cuts_split_by_outcome_by_hand():
    # 5 episodes: successes cut 0, 1 and 2 legs (mean 1), failures 4 and 6 (mean 5); all: 13 / 5
    c = stats.cuts_by_outcome([True, False, True, True, False], [0, 4, 1, 2, 6])
    assert c == dict(all=pytest.approx(2.6), succeeded=pytest.approx(1.0), failed=pytest.approx(5.0), n=5, n_succeeded=3)
    every = stats.cuts_by_outcome([True, True], [1, 2])
    assert every['succeeded'] == 1.5 and math.isnan(every['failed'])
    with pytest.raises(ValueError, match='one entry per episode'):
        stats.cuts_by_outcome([True, False], [1, 2, 3])


def test_newcombe_and_paired_intervals_by_hand():
    # Newcombe (1998), method 10, his example (a): 56/70 against 48/80 gives 0.0524 to 0.3339
    lo, hi = stats.newcombe(56, 70, 48, 80)
    assert (lo, hi) == (pytest.approx(0.0524, abs=1e-4), pytest.approx(0.3339, abs=1e-4))
    # per-seed differences 0.15 and 0.30: mean 0.225, sd 0.1061, half-width 12.706 * 0.1061 / sqrt(2) = 0.953
    lo, hi = stats.paired_interval([0.15, 0.30])
    assert (lo, hi) == (pytest.approx(0.225 - 0.9531, abs=1e-3), pytest.approx(0.225 + 0.9531, abs=1e-3))
    assert lo < 0 and hi > 1  # not clipped: a difference is not a rate
    assert all(math.isnan(x) for x in stats.paired_interval([0.2]))
    with pytest.raises(ValueError, match='finite'):
        stats.paired_interval([0.1, float('nan')])


def test_closure_table_pools_seeds_by_hand(tmp_path):
    """benchmarks/experiments/closure_table.py --pool: two seeds' closure evaluations (2 tasks x 10
    episodes on 2 closed corridors: 40 episodes a seed and row) pooled into rows and differences a
    person can recompute; seeds that do not pool are refused with the reason."""
    def evaluation(name, aqm, flat, episodes=10):
        summary = {row: {v: {f'task_{t}': rates[i][j] for j, t in enumerate((1, 2))}
                         for i, v in enumerate(('close-3-3', 'close-5-4'))}
                   for row, rates in (('aqm', aqm), ('flat', flat))}
        path = tmp_path / f'{name}.json'
        path.write_text(json.dumps(dict(checkpoint=name, variants=['close-3-3', 'close-5-4'], tasks=[1, 2],
                                        config=dict(protocol=dict(episodes=episodes)), summary=summary)))
        return str(path)

    a = evaluation('seed_1', aqm=[[0.5, 0.3], [0.2, 0.0]], flat=[[0.1, 0.1], [0.1, 0.1]])  # 10 and 4 of 40
    b = evaluation('seed_2', aqm=[[0.5, 0.5], [0.5, 0.5]], flat=[[0.2, 0.2], [0.2, 0.2]])  # 20 and 8 of 40
    script = 'benchmarks/experiments/closure_table.py'
    out = tmp_path / 'pooled.json'
    run = subprocess.run([sys.executable, script, '--pool', a, b, '--rows', 'aqm', 'flat', '--json', str(out)],
                         capture_output=True, text=True, check=True)
    p = json.loads(out.read_text())
    aqm, flat, diff = p['rows']['aqm'], p['rows']['flat'], p['differences']['flat']
    assert aqm['per_seed'] == [0.25, 0.5] and flat['per_seed'] == [0.1, 0.2]
    assert aqm['per_layout'] == {'close-3-3': pytest.approx(0.45), 'close-5-4': pytest.approx(0.3)}
    assert aqm['closures'] == 30 / 80 and aqm['closures_ci'] == [pytest.approx(x) for x in stats.wilson(30, 80)]
    assert diff['per_seed'] == [pytest.approx(0.15), pytest.approx(0.3)] and diff['mean'] == pytest.approx(0.225)
    assert diff['paired_ci'] == [pytest.approx(x) for x in stats.paired_interval([0.15, 0.3])]
    assert diff['newcombe_ci'] == [pytest.approx(x) for x in stats.newcombe(30, 80, 12, 80)]
    assert '| aqm | 45.0 | 30.0 | 37.5 [' in run.stdout and 'aqm - flat: +22.5 (paired t [-72.8, +117.8]' in run.stdout

    def refused(*paths, rows=('aqm', 'flat')):
        r = subprocess.run([sys.executable, script, '--pool', *paths, '--rows', *rows], capture_output=True, text=True)
        assert r.returncode != 0
        return r.stderr.strip().splitlines()[-1]

    assert 'a checkpoint appears twice' in refused(a, a)
    assert 'do not pool' in refused(a, evaluation('seed_3', aqm=[[0, 0], [0, 0]], flat=[[0, 0], [0, 0]], episodes=20))
    assert refused(a, b, rows=('aqm', 'no-pruning')).startswith("closure_table: seed_1 has no row ['no-pruning']")
    assert 'no results.json there' in refused(str(tmp_path / 'nowhere'))


def test_aggregate_rows_from_per_seed_tables():
    def table(m, rates, agents=('flat',)):
        return dict(episodes=10, tasks=[1, 2], variants=['base'],
                    summary={f'{m}:seed_{s}/{a}': {'base': {'task_1': r[0], 'task_2': r[1], 'mean': (r[0] + r[1]) / 2}}
                             for s, r in enumerate(rates) for a in agents})

    rows = compare.aggregate({'gcbc': table('gcbc', [(0.6, 0.8), (1.0, 0.8)]),
                              'aqm': table('aqm', [(1.0, 1.0), (0.8, 1.0)], agents=('aqm', 'no-pruning'))}, [0, 1])
    assert list(rows) == ['gcbc', 'aqm', 'aqm/no-pruning']
    r = rows['gcbc']['base']
    assert r['seed_means'] == [pytest.approx(0.7), pytest.approx(0.9)]
    assert r['mean'] == pytest.approx(0.8) and r['task_1'] == pytest.approx(0.8) and r['task_2'] == pytest.approx(0.8)
    assert r['episodes'] == 40
    assert r['episodes_ci95'] == [pytest.approx(x) for x in stats.wilson(32, 40)]
    assert r['seed_ci95'] == [pytest.approx(x) for x in stats.seed_interval([0.7, 0.9])]
    md = report.comparison_markdown(rows, 'base', [1, 2], [0, 1], 10)
    assert '| gcbc | 80 | 80 | **80** |' in md and '| aqm/no-pruning |' in md


def test_requests_are_checked_before_any_work(tmp_path):
    with pytest.raises(ValueError, match="unknown method 'nope'"):
        compare.method_configs('pointmaze-medium', ['gcbc', 'nope'], 'ci')
    with pytest.raises(ValueError, match='repeat'):
        compare.method_configs('pointmaze-medium', ['gcbc', 'gcbc'], 'ci')
    with pytest.raises(ValueError, match="for method 'hiql', which is not compared"):
        compare.method_configs('pointmaze-medium', ['gcbc'], 'ci', ['hiql:steps=100'])
    # a shared field one method lacks names the method and says how to scope it
    with pytest.raises(ValueError, match='gcbc: .*lr_quasimetric.*gcbc:FIELD=VALUE'):
        compare.method_configs('pointmaze-medium', ['aqm', 'gcbc'], 'ci', ['lr_quasimetric=1e-4'])
    with pytest.raises(ValueError, match=r'^aqm: .*multiple of updates_per_call[^;]*$'):  # a bad value: no scoping hint
        compare.method_configs('pointmaze-medium', ['aqm', 'gcbc'], 'ci', ['steps=7'])
    with pytest.raises(ValueError, match=r"^gcbc: .*'lr_policy'.* \(in gcbc:lr_policy=1\)$"):  # a scoped one names its method
        compare.method_configs('pointmaze-medium', ['aqm', 'gcbc'], 'ci', ['gcbc:lr_policy=1'])
    cfgs = compare.method_configs('pointmaze-medium', ['gcivl', 'gcbc'], 'ci',
                                  ['steps=100', 'gcivl:actor_p_trajectory=0.5', 'gcivl:actor_p_random=0.5'])
    assert cfgs['gcivl'].train.steps == cfgs['gcbc'].train.steps == 100
    assert cfgs['gcivl'].train.actor_p_random == 0.5 and cfgs['gcbc'].train.actor_p_random == 0.0
    assert cfgs['gcbc'].protocol.ablations == ()  # methods alone unless ablations are asked for
    # the CLI reports them as errors (exit 2) before collecting anything
    out = str(tmp_path / 'c')
    assert cli.main(['compare', '--env', 'pointmaze-medium', '--methods', 'gcbc', '--set', 'gcivl:steps=1',
                     '--out', out]) == 2
    assert cli.main(['compare', '--env', 'pointmaze-medium', '--methods', 'gcbc', '--seeds', '0', '--out', out]) == 2
    assert cli.main(['compare', '--env', 'pointmaze-medium', '--methods', 'gcbc', '--set', 'protocol.tasks=9',
                     '--out', out]) == 2
    assert not os.path.exists(os.path.join(out, 'data'))
    # a damaged dataset is named, and leaves no comparison folder (no compare.json, no lock)
    damaged = tmp_path / 'pointmaze-medium-navigate.npz'
    damaged.write_bytes(b'PK\x03\x04 half an archive')
    assert cli.main(['compare', '--env', 'pointmaze-medium', '--methods', 'gcbc', '--dataset', str(damaged),
                     '--out', out]) == 2
    assert not os.path.exists(out)


def _data(tmp_path):
    data = synthetic.point_walks(n_traj=60, t_len=60, seed=0)
    path = str(tmp_path / 'pointmaze-medium-navigate.npz')
    np.savez(path, **data)
    return data, path


def test_vmapped_seeds_equal_separate_runs_and_resume_after_an_interrupt(tmp_path):
    data, path = _data(tmp_path)
    method = methods.get('gcivl')
    cfg = method.preset('ci', env='pointmaze-medium', steps=200, checkpoint_every=100, log_every=50)
    seeds = [3, 4]
    keys = jnp.stack([stage_keys(jax.random.PRNGKey(s))[0] for s in seeds])
    cfgs = [cfg.__class__(**{**cfg.to_dict(), 'seed': s}) for s in seeds]
    outs = [str(tmp_path / 'v' / f'seed_{s}') for s in seeds]
    trained = fit.train_seeds(method, cfgs, data, outs, keys, progress=False, **QUIET)
    for s, o, t in zip(seeds, outs, trained):
        alone = fit.train(method, cfgs[0], data, str(tmp_path / f'alone_{s}'), key=stage_keys(jax.random.PRNGKey(s))[0],
                          progress=False, **QUIET)
        loaded = fit.load(o, **QUIET)
        assert loaded.step == 200 and loaded.config.seed == s
        for a, b, c in zip(jax.tree.leaves(alone.params), jax.tree.leaves(t.params), jax.tree.leaves(loaded.params)):
            np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=2e-4, atol=2e-5)
            assert np.asarray(b).tobytes() == np.asarray(c).tobytes()
        steps = [json.loads(ln)['step'] for ln in open(os.path.join(o, 'metrics.jsonl'))]
        assert steps == [50, 100, 150, 200]
    # an interrupt after step 100 of seed 3 and before seed 4's checkpoint at 200: resume from the common 100
    cut = [str(tmp_path / 'cut' / f'seed_{s}') for s in seeds]
    fit.train_seeds(method, [c.__class__(**{**c.to_dict(), 'steps': 100}) for c in cfgs], data, cut, keys,
                    progress=False, **QUIET)
    for o in cut:  # the shorter run's config records steps 100; the resumed request is the full one
        meta = json.load(open(os.path.join(o, 'config.json')))
        meta['config']['steps'] = 200
        json.dump(meta, open(os.path.join(o, 'config.json'), 'w'))
    logs = []
    resumed = fit.train_seeds(method, cfgs, data, cut, keys, progress=False, log=logs.append)
    assert any('resuming 2 seed(s) at step 100' in ln for ln in logs)
    for a, b in zip(trained, resumed):
        for x, y in zip(jax.tree.leaves(a.state), jax.tree.leaves(b.state)):
            assert np.asarray(x).tobytes() == np.asarray(y).tobytes()
    for o in cut:
        steps = [json.loads(ln)['step'] for ln in open(os.path.join(o, 'metrics.jsonl'))]
        assert steps == [50, 100, 150, 200]  # no step twice
    logs = []
    fit.train_seeds(method, cfgs, data, cut, keys, progress=False, log=logs.append)
    assert logs == ['gcivl: 2 seed(s) complete at step 200, not trained again']
    # a resume checks each folder as a single run's resume does: every differing field named ...
    with pytest.raises(ValueError, match=rf'other settings \(saved vs asked\): batch_size: {cfgs[0].batch_size} vs 8'):
        fit.train_seeds(method, [c.__class__(**{**c.to_dict(), 'batch_size': 8}) for c in cfgs], data, cut, keys,
                        progress=False, **QUIET)
    # ... and a config.json that disagrees with what its checkpoint holds
    for o in cut:
        meta = json.loads(open(os.path.join(o, 'config.json')).read())
        meta['config']['lr'] = 0.5
        open(os.path.join(o, 'config.json'), 'w').write(json.dumps(meta))
    edited = [c.__class__(**{**c.to_dict(), 'lr': 0.5}) for c in cfgs]
    with pytest.raises(ValueError, match='config.json disagrees with the config saved in checkpoint 200'):
        fit.train_seeds(method, edited, data, cut, keys, progress=False, **QUIET)
    with pytest.raises(ValueError, match='differ in more than their seed'):
        fit.train_seeds(method, [cfgs[0], cfgs[1].__class__(**{**cfgs[1].to_dict(), 'steps': 100})], data,
                        [str(tmp_path / 'x0'), str(tmp_path / 'x1')], keys, progress=False, **QUIET)


def test_compare_trains_evaluates_and_resumes_without_redoing_finished_methods(tmp_path, monkeypatch):
    _, path = _data(tmp_path)
    out = str(tmp_path / 'cmp')
    over = ['steps=100', 'protocol.tasks=1', 'protocol.episodes=2', 'protocol.horizon=20', 'protocol.curve_episodes=1']
    first = compare.compare('pointmaze-medium', ['gcbc'], 2, out, preset='ci', dataset=path, overrides=over, **QUIET)
    row = first['rows']['gcbc']['base']
    for s in (0, 1):  # the learning curve: a point at the checkpoint (step 100), 1 episode of the one task
        lines = plots.read_metrics(os.path.join(out, 'train', 'gcbc', f'seed_{s}', 'metrics.jsonl'))
        assert [(ln['step'], ln['eval/episodes']) for ln in lines if 'eval/success' in ln] == [(100, 1)]
    assert os.path.getsize(os.path.join(out, 'curves.png')) > 5000
    assert row['episodes'] == 4 and len(row['seed_means']) == 2
    res = json.load(open(os.path.join(out, 'eval', 'gcbc', 'results.json')))
    assert set(res['checkpoints']) == {'gcbc:seed_0', 'gcbc:seed_1'}
    top = json.load(open(os.path.join(out, 'results.json')))  # what made it: version, commit, command
    assert res['provenance']['version'] == top['provenance']['version'] and 'commit' in top['provenance']
    assert row['seed_means'] == [res['summary'][f'gcbc:seed_{s}/flat']['base']['mean'] for s in (0, 1)]
    for s in (0, 1):
        assert fit.read_meta(os.path.join(out, 'train', 'gcbc', f'seed_{s}'))[1].seed == s
    stamp = {p: os.path.getmtime(p) for p in (os.path.join(out, 'eval', 'gcbc', 'results.json'),
                                              os.path.join(out, 'train', 'gcbc', 'seed_1', 'metrics.jsonl'))}
    assert res['config'] == first['configs']['gcbc'] and res['split'] == first['split'] == 'report'
    # adding a method to the same folder trains and evaluates only the new one; a default changed in
    # between (here the ci preset's kappa) reaches the new method's row, and the finished row keeps
    # the config it was evaluated with
    ci = dict(presets.RUN['ci'], agent=dict(presets.RUN['ci']['agent'], kappa=0.7))
    monkeypatch.setitem(presets.RUN, 'ci', ci)
    logs = []
    second = compare.compare('pointmaze-medium', ['gcbc', 'gcivl'], 2, out, preset='ci', dataset=path, overrides=over,
                             log=logs.append)
    assert second['configs']['gcbc']['agent']['kappa'] == 0.0 and second['configs']['gcivl']['agent']['kappa'] == 0.7
    assert second['configs']['gcbc'] == first['configs']['gcbc']
    assert 'gcbc: 2 seed(s) complete at step 100, not trained again' in logs
    assert any(ln.startswith('gcbc: evaluated already') for ln in logs)
    assert all(os.path.getmtime(p) == t for p, t in stamp.items())
    assert list(second['rows']) == ['gcbc', 'gcivl'] and second['rows']['gcbc'] == first['rows']['gcbc']
    assert json.load(open(os.path.join(out, 'compare.json')))['methods'] == ['gcbc', 'gcivl']
    assert os.path.getsize(os.path.join(out, 'success.png')) > 5000
    assert '| gcivl |' in open(os.path.join(out, 'table.md')).read()
    # the folder holds one comparison: other settings are refused, naming what differs
    with pytest.raises(ValueError, match='overrides'):
        compare.compare('pointmaze-medium', ['gcbc'], 2, out, preset='ci', dataset=path, overrides=over[:1], **QUIET)
    # the data's SHA-256 is recorded beside the request and in the table's JSON; a file changed under the
    # folder is refused before any work, and the folder's record is kept as it was
    digest = ds_io.fingerprint(assess.read_data(path, envs.make('pointmaze-medium')))
    saved = json.load(open(os.path.join(out, 'compare.json')))
    assert first['data_sha256'] == second['data_sha256'] == saved['data_sha256'] == digest and len(digest) == 64
    data, _ = _data(tmp_path)
    data['actions'][7, 1] += 0.25
    np.savez(path, **data)
    with pytest.raises(ValueError, match=f'the data changed since this comparison began.*{saved["data_sha256"][:16]}'):
        compare.compare('pointmaze-medium', ['gcbc', 'gcivl'], 2, out, preset='ci', dataset=path, overrides=over,
                        **QUIET)
    assert json.load(open(os.path.join(out, 'compare.json'))) == saved


@pytest.mark.slow  # two pointmaze evaluations: about 100 s
def test_compare_planners_adds_each_method_under_another_planner_on_the_same_episodes(tmp_path):
    _, path = _data(tmp_path)
    out = str(tmp_path / 'cmp')
    over = ['steps=100', 'protocol.tasks=1', 'protocol.episodes=2', 'protocol.horizon=20', 'protocol.curve_episodes=0',
            'agent.distance_check=false', 'protocol.ablations=no-pruning,flat']
    logs = []
    res = compare.compare('pointmaze-medium', ['gcbc', 'gcivl'], 2, out, preset='ci', dataset=path, overrides=over,
                          planners=['flat', 'aqm'], log=logs.append)
    # gcbc has no value; gcivl runs flat on its own, so only gcivl+aqm is new (with its ablation rows)
    assert 'gcbc: no value to plan with, so no gcbc+aqm row' in logs
    # gcivl's own row is flat by its own rule, not for want of a distance: the line says which
    assert ('gcivl runs flat: no map, its controller aimed at the goal (its own rule; --planner aqm|ttgs plans on '
            'its distance)') in logs
    assert [k for k in res['rows'] if not k.startswith('gcivl+aqm/')] == ['gcbc', 'gcivl', 'gcivl+aqm']
    assert 'gcivl+aqm/flat' in res['rows'] and res['configs']['gcivl+aqm']['agent']['planner'] == 'aqm'
    # the same checkpoints: GCIVL's flat row under AQM's map is GCIVL's own row, seed for seed
    assert res['rows']['gcivl+aqm/flat']['base']['seed_means'] == res['rows']['gcivl']['base']['seed_means']
    ev = json.load(open(os.path.join(out, 'eval', 'gcivl+aqm', 'results.json')))
    assert set(ev['checkpoints']) == {'gcivl:seed_0', 'gcivl:seed_1'}
    assert '| gcivl+aqm |' in open(os.path.join(out, 'table.md')).read()
    again = []
    compare.compare('pointmaze-medium', ['gcbc', 'gcivl'], 2, out, preset='ci', dataset=path, overrides=over,
                    planners=['aqm'], log=again.append)
    assert not any('evaluate under planner' in ln for ln in again)  # finished: read, not run again
    with pytest.raises(ValueError, match="unknown planner 'astar'"):
        compare.compare('pointmaze-medium', ['gcivl'], 2, out, preset='ci', dataset=path, overrides=over,
                        planners=['astar'], **QUIET)


def test_baselines_take_ogbench_settings_for_stitch_and_explore_data():
    """OGBench's hyperparameters.sh: on stitch data every method but GCBC draws half its actor goals
    from random dataset states, on explore data all of them, with the explore alphas; navigate keeps
    trajectory goals; a scoped override still wins."""
    names = ['gcbc', 'gcivl', 'gciql', 'qrl', 'crl', 'hiql', 'saw']
    for style, (p_rand, p_traj) in (('navigate', (0.0, 1.0)), ('stitch', (0.5, 0.5)), ('explore', (1.0, 0.0))):
        cfgs = compare.method_configs('antmaze-medium', names, 'ci', style=style)
        for n in names:
            want = (0.0, 1.0) if n == 'gcbc' else (p_rand, p_traj)
            assert (cfgs[n].train.actor_p_random, cfgs[n].train.actor_p_trajectory) == want, (n, style)
    nav = compare.method_configs('antmaze-medium', names, 'ci', style='navigate')
    exp = compare.method_configs('antmaze-medium', names, 'ci', style='explore')
    assert [exp[n].train.alpha for n in ('gcivl', 'gciql', 'qrl', 'crl')] == [10.0, 0.01, 0.001, 0.003]
    assert [nav[n].train.alpha for n in ('gcivl', 'gciql', 'qrl', 'crl')] == [10.0, 0.3, 0.003, 0.1]
    assert (exp['hiql'].train.high_alpha, exp['hiql'].train.low_alpha) == (10.0, 10.0)
    assert (nav['hiql'].train.high_alpha, nav['hiql'].train.low_alpha) == (3.0, 3.0)
    scoped = compare.method_configs('antmaze-medium', ['gcivl'], 'ci', ['gcivl:actor_p_random=0.0',
                                                                      'gcivl:actor_p_trajectory=1.0'], style='stitch')
    assert scoped['gcivl'].train.actor_p_random == 0.0


def test_the_explore_rule_reaches_every_entry_point(tmp_path, monkeypatch):
    """AQM draws uniform random policy goals on explore data (paper App. 10.3) in ``train``, ``run``
    (both paths build their config the same way) and ``compare``; other methods and other styles
    keep theirs, and an explicit override wins."""
    from aqm_mjx import pipeline, run  # pylint: disable=import-outside-toplevel
    from aqm_mjx.data import dataset as dsm  # pylint: disable=import-outside-toplevel

    assert pipeline.RunConfig.preset('ci', style='explore').train.policy_goals == 'random'
    assert pipeline.RunConfig.preset('ci', style='navigate').train.policy_goals == 'trajectory'
    cfgs = compare.method_configs('antmaze-medium', ['aqm', 'gcivl'], 'ci', style='explore')
    assert cfgs['aqm'].train.policy_goals == 'random' and not hasattr(cfgs['gcivl'].train, 'policy_goals')
    data = synthetic.grid_walks(synthetic.one_way_grid(5), episodes=20, steps=20, seed=1)
    path = str(tmp_path / 'pointmaze-medium-explore-v0.npz')
    dsm.write_ogbench(path, {k: data[k] for k in ('observations', 'actions', 'terminals')})
    seen = []
    monkeypatch.setattr(run, 'run_stepwise', lambda cfg, out, **kw: seen.append(cfg.train.policy_goals))
    for extra, want in (([], 'random'), (['--set', 'train.policy_goals=trajectory'], 'trajectory')):
        assert cli.main(['run', '--env', 'pointmaze-medium', '--preset', 'ci', '--dataset', path,
                         '--out', str(tmp_path / 'r')] + extra) == 0
        assert seen[-1] == want
    out = str(tmp_path / 't')
    assert cli.main(['train', '--dataset', path, '--preset', 'ci', '--steps', '50', '--set', 'updates_per_call=50',
                     '--set', 'log_every=50', '--set', 'checkpoint_every=50', '--out', out]) == 0
    assert json.load(open(os.path.join(out, 'config.json')))['config']['policy_goals'] == 'random'


def _finished(folder, methods_rates, sha='ab' * 32, overrides=('protocol.episodes=10',), episodes=10, seeds=(0, 1),
              configs=None):
    """A compare folder's results.json as compare writes it: rows from per-seed tables via aggregate
    (``methods_rates[m]``: (task 1, task 2) success of each seed in ``seeds``)."""
    per = {m: dict(episodes=episodes, tasks=[1, 2], variants=['base'],
                   summary={f'{lab}/{"aqm" if m == "aqm" else "flat"}':
                            {'base': {'task_1': r[0], 'task_2': r[1], 'mean': (r[0] + r[1]) / 2}}
                            for lab, r in zip(assess.checkpoint_labels([f'seed_{s}' for s in seeds], [m] * len(seeds)),
                                              rates)}) for m, rates in methods_rates.items()}
    result = dict(env='antmaze-medium', style='navigate', preset='cpu', seeds=list(seeds), eval_seed=0, shift='base',
                  overrides=list(overrides), dataset=None, data_sha256=sha, methods=list(methods_rates), tasks=[1, 2],
                  episodes=episodes, variants=['base'], rows=compare.aggregate(per, list(seeds)),
                  configs=configs or {m: {'method': m, 'train': {'seed': seeds[0]}} for m in methods_rates})
    os.makedirs(folder)
    with open(os.path.join(folder, 'results.json'), 'w') as f:
        json.dump(result, f, sort_keys=True)  # as files.write_json: rows alphabetical, not in method order
    return result


def test_merge_puts_rows_of_the_same_data_and_episodes_in_one_table(tmp_path):
    a, b, out = (str(tmp_path / n) for n in ('a', 'b', 'out'))
    ra = _finished(a, {'aqm': [(0.9, 0.7), (1.0, 0.8)], 'qrl': [(0.2, 0.0), (0.1, 0.1)]},
                   overrides=('protocol.episodes=10', 'qrl:protocol.ablations=flat'))
    rb = _finished(b, {'hiql': [(0.3, 0.1), (0.0, 0.2)], 'crl': [(0.0, 0.0), (0.1, 0.1)]})
    before = {f: open(os.path.join(f, 'results.json')).read() for f in (a, b)}
    merged = compare.merge([a, b], out, **QUIET)
    assert merged['methods'] == ['aqm', 'qrl', 'hiql', 'crl'] and list(merged['rows']) == ['aqm', 'qrl', 'hiql', 'crl']
    assert merged['rows']['aqm'] == ra['rows']['aqm'] and merged['rows']['hiql'] == rb['rows']['hiql']
    # hiql: seed means 0.2 and 0.1, 6 of 40 pooled episodes
    h = merged['rows']['hiql']['base']
    assert h['mean'] == pytest.approx(0.15) and h['episodes_ci95'] == [pytest.approx(x) for x in stats.wilson(6, 40)]
    assert merged['overrides'] == ['protocol.episodes=10', 'qrl:protocol.ablations=flat']
    assert merged['merged_from'] == {'aqm': os.path.abspath(a), 'qrl': os.path.abspath(a), 'hiql': os.path.abspath(b),
                                     'crl': os.path.abspath(b)}
    table = open(os.path.join(out, 'table.md')).read()
    assert table.index('| qrl |') < table.index('| hiql |') < table.index('| crl |')  # in method order
    assert '| aqm | 95 | 75 | **85** |' in table and '| hiql | 15 | 15 | **15** |' in table
    assert os.path.getsize(os.path.join(out, 'success.png')) > 5000
    assert json.load(open(os.path.join(out, 'results.json'))) == merged
    assert cli.main(['merge', a, b, '--out', str(tmp_path / 'cli')]) == 0
    assert json.load(open(tmp_path / 'cli' / 'results.json'))['rows'] == merged['rows']
    # what would put rows of other data or episodes side by side is refused, naming it
    other = str(tmp_path / 'other')
    _finished(other, {'saw': [(0.5, 0.5), (0.5, 0.5)]}, sha='cd' * 32)
    with pytest.raises(ValueError, match='differ in data_sha256'):
        compare.merge([a, other], str(tmp_path / 'x'), **QUIET)
    with open(os.path.join(other, 'compare.json'), 'w') as f:  # as a compare folder has one
        f.write('{}')
    fewer = str(tmp_path / 'fewer')
    _finished(fewer, {'saw': [(0.5, 0.5), (0.5, 0.5)]}, overrides=('protocol.episodes=5',), episodes=5)
    with pytest.raises(ValueError, match='differ in episodes.*overrides'):
        compare.merge([a, fewer], str(tmp_path / 'x'), **QUIET)
    # how many processes stepped OGBench's environments is not a setting of the numbers; the backend is
    workers = str(tmp_path / 'workers')
    _finished(workers, {'gcbc': [(0.0, 0.0), (0.0, 0.1)]}, overrides=('protocol.workers=12', 'protocol.episodes=10'))
    assert compare.merge([a, workers], str(tmp_path / 'w'), **QUIET)['overrides'] == ['protocol.episodes=10',
                                                                                      'qrl:protocol.ablations=flat']
    backend = str(tmp_path / 'backend')
    _finished(backend, {'gcbc': [(0.0, 0.0), (0.0, 0.1)]}, overrides=('protocol.backend=ogbench', 'protocol.episodes=10'))
    with pytest.raises(ValueError, match='differ in overrides'):
        compare.merge([a, backend], str(tmp_path / 'x'), **QUIET)
    again = str(tmp_path / 'again')
    _finished(again, {'qrl': [(0.5, 0.5), (0.5, 0.5)]})
    with pytest.raises(ValueError, match="method 'qrl' has seed 0 in both"):
        compare.merge([a, again], str(tmp_path / 'x'), **QUIET)
    with pytest.raises(ValueError, match='is or lies inside the input'):
        compare.merge([a, b], a, **QUIET)
    with pytest.raises(ValueError, match='is or lies inside the input'):  # the same folder spelled another way
        compare.merge([a, b], os.path.relpath(b) + os.sep, **QUIET)
    with pytest.raises(ValueError, match='is a comparison folder'):  # another comparison's folder
        compare.merge([a, b], other, **QUIET)
    with pytest.raises(ValueError, match='folders repeat'):
        compare.merge([a, os.path.relpath(a)], str(tmp_path / 'x'), **QUIET)
    with pytest.raises(ValueError, match='at least two'):
        compare.merge([a], out, **QUIET)
    assert cli.main(['merge', a, str(tmp_path / 'missing'), '--out', str(tmp_path / 'y')]) == 2
    assert {f: open(os.path.join(f, 'results.json')).read() for f in (a, b)} == before  # inputs only read
    assert not os.path.exists(tmp_path / 'x') and not os.path.exists(tmp_path / 'y')
    # a second writer of OUT is refused while another process holds its lock, and writes nothing
    held = str(tmp_path / 'held')
    holder = subprocess.Popen([sys.executable, '-c', 'import sys, time\nfrom aqm_mjx import files\n'
                               f'with files.run_lock({held!r}):\n    print("held", flush=True)\n    time.sleep(60)'],
                              stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == 'held'
        with pytest.raises(files.LockedError):
            compare.merge([a, b], held, **QUIET)
        assert not os.path.exists(os.path.join(held, 'results.json'))
    finally:
        holder.kill()
        holder.wait()


def test_merge_pools_the_seeds_of_one_method_from_two_folders(tmp_path):
    """Seeds 0-1 of aqm and gcbc in one folder, seed 2 of both (the same command, --seeds 1 --seed 2) in
    another, gas's seeds 0-2 in a third: one table over seeds 0-2, aqm's numbers those of one folder
    holding all three seeds; other configs, shared seeds or missing seeds are refused, naming them."""
    a, b, c = (str(tmp_path / n) for n in ('a', 'b', 'c'))
    aqm = [(0.9, 0.7), (1.0, 0.8), (0.5, 0.1)]  # (task 1, task 2) of seeds 0, 1, 2
    gcbc = [(0.0, 0.0), (0.1, 0.1), (0.3, 0.0)]
    _finished(a, {'aqm': aqm[:2], 'gcbc': gcbc[:2]}, seeds=(0, 1))
    _finished(b, {'aqm': aqm[2:], 'gcbc': gcbc[2:]}, seeds=(2,), overrides=('protocol.episodes=10', 'protocol.workers=4'))
    _finished(c, {'gas': [(0.0, 0.1)] * 3}, seeds=(0, 1, 2))
    whole = _finished(str(tmp_path / 'whole'), {'aqm': aqm, 'gcbc': gcbc}, seeds=(0, 1, 2))
    merged = compare.merge([a, c, b], str(tmp_path / 'out'), **QUIET)
    assert merged['seeds'] == [0, 1, 2] and merged['methods'] == ['aqm', 'gcbc', 'gas']
    for m in ('aqm', 'gcbc'):  # pooled exactly as one folder of the three seeds would hold them
        got, want = merged['rows'][m]['base'], whole['rows'][m]['base']
        assert got.keys() == want.keys()
        for k in want:
            assert got[k] == (pytest.approx(want[k]) if not isinstance(want[k], list)
                              else [pytest.approx(x) for x in want[k]]), (m, k)
    # by hand: aqm's seed means 0.8, 0.9, 0.3; task 1 (0.9 + 1.0 + 0.5) / 3; 16 + 18 + 6 wins of 60 episodes
    g = merged['rows']['aqm']['base']
    assert g['seed_means'] == [pytest.approx(0.8), pytest.approx(0.9), pytest.approx(0.3)]
    assert g['task_1'] == pytest.approx(0.8) and g['episodes'] == 60
    assert g['episodes_ci95'] == [pytest.approx(x) for x in stats.wilson(16 + 18 + 6, 60)]
    assert merged['merged_from']['aqm'] == [os.path.abspath(a), os.path.abspath(b)]
    assert merged['merged_from']['gas'] == os.path.abspath(c)
    assert '| aqm | 80 | 53 | **67** |' in open(tmp_path / 'out' / 'table.md').read()
    # a merged table as an input passes on the folders that computed its rows, pooled ones too
    d = str(tmp_path / 'd')
    _finished(d, {'gcivl': [(0.2, 0.2)] * 3}, seeds=(0, 1, 2))
    again = compare.merge([str(tmp_path / 'out'), d], str(tmp_path / 'again'), **QUIET)
    assert again['rows'] == dict(merged['rows'], gcivl=again['rows']['gcivl'])
    assert again['merged_from'] == dict(merged['merged_from'], gcivl=os.path.abspath(d))
    e, t = str(tmp_path / 'e'), str(tmp_path / 't')
    _finished(e, {'crl': [(0.1, 0.1)] * 2}, seeds=(0, 1))
    compare.merge([a, e], t, **QUIET)
    _finished(str(tmp_path / 'b3'), {'aqm': aqm[2:], 'gcbc': gcbc[2:], 'crl': [(0.3, 0.3)]}, seeds=(2,))
    three = compare.merge([t, str(tmp_path / 'b3')], str(tmp_path / 'three'), **QUIET)
    assert three['merged_from']['aqm'] == [os.path.abspath(a), str(tmp_path / 'b3')]
    assert three['merged_from']['crl'] == [os.path.abspath(e), str(tmp_path / 'b3')]
    with open(os.path.join(t, 'results.json')) as f:
        r = json.load(f)
    r['merged_from'] = {'aqm': 3}
    with open(os.path.join(t, 'results.json'), 'w') as f:
        json.dump(r, f)
    with pytest.raises(files.BadFileError, match="'merged_from' is not an object of folders"):
        compare.merge([t, str(tmp_path / 'b3')], str(tmp_path / 'x'), **QUIET)
    # a method with seeds the others lack
    with pytest.raises(ValueError, match=r"cover different seeds \(aqm: \[0, 1\]; gcbc: \[0, 1\]; gas: \[0, 1, 2\]"):
        compare.merge([a, c], str(tmp_path / 'x'), **QUIET)
    # the same seed twice
    twice = str(tmp_path / 'twice')
    _finished(twice, {'aqm': aqm[1:]}, seeds=(1, 2))
    with pytest.raises(ValueError, match="method 'aqm' has seed 1 in both"):
        compare.merge([a, twice], str(tmp_path / 'x'), **QUIET)
    # seeds trained otherwise: another config value or another METHOD: override
    other = str(tmp_path / 'other')
    _finished(other, {'aqm': aqm[2:], 'gcbc': gcbc[2:]}, seeds=(2,),
              configs={'aqm': {'method': 'aqm', 'train': {'seed': 2, 'steps': 5}}, 'gcbc': {'method': 'gcbc', 'train': {'seed': 2}}})
    with pytest.raises(ValueError, match="method 'aqm' in .*other and .*a differs in train.steps"):
        compare.merge([a, other], str(tmp_path / 'x'), **QUIET)
    scoped = str(tmp_path / 'scoped')
    _finished(scoped, {'aqm': aqm[2:], 'gcbc': gcbc[2:]}, seeds=(2,), overrides=('protocol.episodes=10', 'aqm:map.delta=3'))
    with pytest.raises(ValueError, match="differs in its overrides"):
        compare.merge([a, scoped], str(tmp_path / 'x'), **QUIET)
    # a folder whose rows hold another number of seed means than its seeds (the first folder too)
    short = str(tmp_path / 'short')
    r = _finished(short, {'aqm': aqm[:2], 'gcbc': gcbc[:2]}, seeds=(0, 1))
    r['rows']['aqm']['base']['seed_means'] = [0.8]
    with open(os.path.join(short, 'results.json'), 'w') as f:
        json.dump(r, f)
    with pytest.raises(ValueError, match=r"short/results.json: rows \['aqm'\] hold another number of seed means"):
        compare.merge([short, b], str(tmp_path / 'x'), **QUIET)
    assert not os.path.exists(tmp_path / 'x')


def _tree(folder) -> dict:
    """{relative path: bytes} of every file under ``folder`` (symbolic links as their targets' names)."""
    out = {}
    for root, dirs, names in os.walk(folder):
        for n in names + [d for d in dirs if os.path.islink(os.path.join(root, d))]:
            p = os.path.join(root, n)
            out[os.path.relpath(p, folder)] = os.readlink(p) if os.path.islink(p) else open(p, 'rb').read()
    return out


def test_merge_never_writes_into_an_input(tmp_path, capsys):
    """An --out inside an input, equal to one however spelled, a symbolic link into one, or holding
    one is refused with exit 2 and one line before anything is written; damaged inputs (no rows or
    configs, a list, methods as a string, truncated JSON) are named, not tracebacks; every input's
    bytes are unchanged and no output folder is left."""
    a, b = str(tmp_path / 'r' / 'cmp'), str(tmp_path / 'r' / 'cmpB')
    _finished(a, {'aqm': [(0.9, 0.7), (1.0, 0.8)], 'gcbc': [(0.2, 0.0), (0.1, 0.1)]})
    _finished(b, {'hiql': [(0.3, 0.1), (0.0, 0.2)]})
    os.makedirs(os.path.join(a, 'eval', 'gcbc'))
    with open(os.path.join(a, 'eval', 'gcbc', 'results.json'), 'w') as f:
        f.write('{"gcbc": "its own evaluation"}')
    os.symlink(os.path.join(a, 'eval'), str(tmp_path / 'link'))
    before = {f: _tree(f) for f in (a, b)}
    cases = [(os.path.join(a, 'eval', 'gcbc'), 'is or lies inside the input'),  # the case
             (os.path.join(a, 'new'), 'is or lies inside the input'),          # not there yet, still inside
             (str(tmp_path / 'link' / 'gcbc'), 'is or lies inside the input'),  # a link into an input
             (str(tmp_path / 'link'), 'is or lies inside the input'),
             (str(tmp_path / 'r'), 'holds the input')]                          # an input inside the output
    for out, msg in cases:
        capsys.readouterr()
        assert cli.main(['merge', a, b, '--out', out]) == 2, out
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and msg in err[0] and 'Traceback' not in err[0], err
    assert {f: _tree(f) for f in (a, b)} == before
    assert not os.path.exists(os.path.join(a, 'new'))
    # damaged inputs: the file and the fault named
    good = json.load(open(os.path.join(b, 'results.json')))
    bad = str(tmp_path / 'bad')
    os.makedirs(bad)
    for text, msg in ((json.dumps({k: v for k, v in good.items() if k != 'configs'}), "'configs' is missing"),
                      (json.dumps({k: v for k, v in good.items() if k != 'rows'}), "'rows' is missing"),
                      (json.dumps(dict(good, methods='hiql')), "'methods' is 'hiql'"),
                      (json.dumps(dict(good, rows={})), "'rows' lacks method(s) ['hiql']"),
                      (json.dumps([good]), 'holds a JSON list'),
                      (json.dumps(dict(good, rows={'hiql': {'base': dict(good['rows']['hiql']['base'], mean='abc')}})),
                       "row 'hiql', layout 'base': mean not success rates in [0, 1]"),
                      # a rate of 750% (the case), a negative seed mean, an interval upside down
                      (json.dumps(dict(good, rows={'hiql': {'base': dict(good['rows']['hiql']['base'], mean=7.5)}})),
                       "row 'hiql', layout 'base': mean not success rates in [0, 1]"),
                      (json.dumps(dict(good, rows={'hiql': {'base': dict(good['rows']['hiql']['base'],
                                                                         seed_means=[0.2, -0.1])}})),
                       'seed_means not success rates'),
                      (json.dumps(dict(good, rows={'hiql': {'base': dict(good['rows']['hiql']['base'],
                                                                         episodes_ci95=[0.6, 0.2])}})),
                       'episodes_ci95 not success rates'),
                      (json.dumps(good)[:200], 'is not valid JSON')):
        with open(os.path.join(bad, 'results.json'), 'w') as f:
            f.write(text)
        capsys.readouterr()
        assert cli.main(['merge', a, bad, '--out', str(tmp_path / 'x')]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and os.path.join(bad, 'results.json') in err[0] and msg in err[0], (msg, err)
    assert not os.path.exists(tmp_path / 'x') and {f: _tree(f) for f in (a, b)} == before


def test_learning_curve_points_land_in_each_seed_folder_and_restart_with_a_resume(tmp_path):
    """A Curve's point runs at every checkpoint for every seed with that seed's state and step; its
    metrics are a line of their own in that seed's metrics.jsonl; draw gets the folders each time; a
    resume drops the points past the restart step and computes them again."""
    data, _ = _data(tmp_path)
    method = methods.get('gcbc')
    cfg = method.preset('ci', env='pointmaze-medium', steps=200, checkpoint_every=100, log_every=50)
    cfgs = [dataclasses.replace(cfg, seed=s) for s in (3, 4)]
    outs = [str(tmp_path / f'seed_{s}') for s in (3, 4)]
    keys = jnp.stack([stage_keys(jax.random.PRNGKey(s))[0] for s in (3, 4)])
    seen, drawn = [], []

    def point(trained):
        seen.append((trained.config.seed, trained.step, int(trained.state.step)))
        return {'eval/success': trained.step / 1000 + trained.config.seed / 10, 'eval/episodes': 4}

    fit.train_seeds(method, cfgs, data, outs, keys, progress=False, curve=fit.Curve(point, drawn.append), **QUIET)
    assert seen == [(3, 100, 100), (4, 100, 100), (3, 200, 200), (4, 200, 200)]
    assert drawn == [outs, outs]
    for s, o in zip((3, 4), outs):
        lines = [json.loads(ln) for ln in open(os.path.join(o, 'metrics.jsonl'))]
        assert [ln['step'] for ln in lines] == [50, 100, 100, 150, 200, 200]
        points = [(ln['step'], ln['eval/success']) for ln in lines if 'eval/success' in ln]
        assert points == [(100, pytest.approx(0.1 + s / 10)), (200, pytest.approx(0.2 + s / 10))]
        assert not any('loss' in k for ln in lines if 'eval/success' in ln for k in ln)  # a line of its own
    # extended from the checkpoint at 200: the point at 200 is not repeated, 300 is new
    seen.clear()
    fit.train_seeds(method, [dataclasses.replace(c, steps=300) for c in cfgs], data, outs, keys, progress=False,
                    curve=fit.Curve(point), **QUIET)
    assert seen == [(3, 300, 300), (4, 300, 300)]
    steps = [json.loads(ln)['step'] for ln in open(os.path.join(outs[0], 'metrics.jsonl')) if 'eval/success' in ln]
    assert steps == [100, 200, 300]
