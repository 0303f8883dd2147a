"""One table holds every default (aqm_mjx/presets.py): the configs' dataclass defaults come from it,
and a value changed there reaches every command that builds a config."""

import ast
import pathlib

import pytest

from aqm_mjx import assess, cli, compare, envs, pipeline, presets, run
from aqm_mjx.agent.rules import AgentConfig
from aqm_mjx.evaluation import protocol
from aqm_mjx.learn import methods
from aqm_mjx.learn.learner import LoopConfig
from aqm_mjx.mapping.build import MapConfig

ROOT = pathlib.Path(__file__).resolve().parents[1] / 'aqm_mjx'


def test_the_classes_defaults_are_the_default_presets():
    row = presets.RUN[presets.DEFAULT]
    assert (AgentConfig().kappa, AgentConfig().switch_radius) == (row['agent']['kappa'], row['agent']['switch_radius'])
    assert MapConfig().delta == row['map']['delta']
    loop = LoopConfig()
    assert {k: getattr(loop, k) for k in presets.LOOP[presets.DEFAULT]} == presets.LOOP[presets.DEFAULT]
    assert loop.preset == presets.DEFAULT
    # every row sets the shared fields itself, so none inherits the default row's value by accident
    for name, r in presets.RUN.items():
        for part, fields in presets.SHARED.items():
            assert set(fields) <= set(r[part]), (name, part)
    with pytest.raises(ValueError, match='not set by every preset'):
        presets.default('agent', 'cut_slack')
    with pytest.raises(ValueError, match="unknown run preset 'cpu-longer'"):
        pipeline.RunConfig.preset('cpu-longer')


def test_every_preset_names_a_network_size_row_and_longer_presets_train_the_cpu_networks():
    from aqm_mjx.learn import aqm
    from aqm_mjx.learn.baselines import base

    assert set(presets.NETWORKS) == set(presets.LOOP) == set(presets.RUN)
    assert set(presets.NETWORKS.values()) == set(aqm.SIZES) == set(base.SIZES)
    for name in methods.names():  # cpu-long and cpu-giant: the cpu networks, their own loops
        cpu = methods.get(name).preset('cpu').to_dict()
        for longer in ('cpu-long', 'cpu-giant'):
            cfg = methods.get(name).preset(longer).to_dict()
            differ = {k for k in cpu if cfg[k] != cpu[k]}
            derived = {'tdr_steps'}  # GAS's phase boundary: half the run's steps
            assert differ <= set(presets.LOOP[longer]) | {'preset'} | derived, (name, longer, differ)
    with pytest.raises(ValueError, match="unknown preset 'cpu-longer'"):
        presets.networks('cpu-longer')


def test_every_method_takes_the_loop_from_the_one_table():
    for name in methods.names():
        for p in presets.LOOP:
            cfg = methods.get(name).preset(p)
            assert {k: getattr(cfg, k) for k in presets.LOOP[p]} == presets.LOOP[p], (name, p)


def test_a_changed_preset_reaches_run_evaluate_compare_and_the_one_program(monkeypatch, tmp_path):
    """The ci row's kappa and delta, and its loop's batch size, changed in the table alone, are what
    ``run`` (both paths), ``evaluate``, ``compare`` and the one program's episode table use."""
    ci = dict(presets.RUN['ci'], agent=dict(presets.RUN['ci']['agent'], kappa=0.37),
              map=dict(presets.RUN['ci']['map'], delta=0.41))
    monkeypatch.setitem(presets.RUN, 'ci', ci)
    monkeypatch.setitem(presets.LOOP, 'ci', dict(presets.LOOP['ci'], batch_size=48))
    parser = cli.build_parser()

    def seen(cfg):
        return cfg.agent.kappa, cfg.map.delta, cfg.train.batch_size

    want = (0.37, 0.41, 48)
    # run, step by step and as one program
    for extra in ([], ['--one-program', '--seeds', '2']):
        assert seen(cli.run_config(parser.parse_args(['run', '--preset', 'ci', '--env', 'pointmaze-medium', *extra]))) \
            == want
    # compare: every method's row
    for cfg in compare.method_configs('pointmaze-medium', ['aqm', 'gcbc'], 'ci').values():
        assert seen(cfg) == want
    # the one program: its episode table budgets the AQM row at that kappa
    cfg = pipeline.RunConfig.preset('ci', env='pointmaze-medium')
    table = pipeline.make_run(cfg, envs.make('pointmaze-medium')).episodes.table
    assert table.kappa[table.agent == 0].tolist() == pytest.approx([0.37] * int((table.agent == 0).sum()))
    # evaluate: a checkpoint trained at the ci preset takes the ci row (the batch is the checkpoint's own)
    ckpt, path = run.demo_run(str(tmp_path), steps=50)
    _, _, cfg, _ = assess.prepare_evaluation(ckpt, None, path, 'base', [])
    assert (cfg.agent.kappa, cfg.map.delta, cfg.train.batch_size) == (0.37, 0.41, 48)
    # the command line's --preset on evaluate reads the same row
    a = parser.parse_args(['evaluate', '--checkpoint', ckpt, '--preset', 'ci'])
    assert a.preset == 'ci' and seen(pipeline.RunConfig.preset(a.preset)) == want


def _numeric_defaults(path):
    """``(line, name)`` of every keyword argument or parameter default named kappa, delta or
    switch_radius that is a number written in ``path``."""
    names = {'kappa', 'delta', 'switch_radius'}
    out = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.keyword) and node.arg in names and isinstance(node.value, ast.Constant):
            out.append((node.lineno, node.arg))
        if isinstance(node, (ast.FunctionDef, ast.Lambda)):
            args = node.args.args + node.args.kwonlyargs
            defaults = [None] * (len(node.args.args) - len(node.args.defaults)) + list(node.args.defaults) + \
                list(node.args.kw_defaults)
            out += [(a.lineno, a.arg) for a, d in zip(args, defaults)
                    if a.arg in names and isinstance(d, ast.Constant) and not isinstance(d.value, bool)]
        if isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name) and node.target.id in names:
            v = node.value
            first = v.args[0] if isinstance(v, ast.Call) and v.args else v
            if isinstance(first, ast.Constant):
                out.append((node.lineno, node.target.id))
    return out


def test_no_other_literal_default_of_kappa_delta_or_switch_radius():
    # the oracle's delta is in metres on the exact maze distance, a parameter of its own, not the map's
    allowed = {('agent/oracle.py', 'delta')}
    found = []
    for path in sorted(ROOT.rglob('*.py')):
        rel = str(path.relative_to(ROOT))
        if rel == 'presets.py':
            continue
        found += [f'{rel}:{line} {name}' for line, name in _numeric_defaults(path) if (rel, name) not in allowed]
    assert not found, found


def test_the_stall_rule_kappa_is_finite_in_both_places_that_need_one():
    rows = protocol.agent_specs(float('inf'), ('stall=50',), patience=0.0)
    assert rows[1].kappa == 1.0 and rows[1].patience == 50.0
