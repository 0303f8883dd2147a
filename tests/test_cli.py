"""The package imports silently and the CLI's cheap commands work and fail clearly."""

import os
import subprocess
import sys

import pytest

from aqm_mjx import cli


def test_import_prints_nothing():
    out = subprocess.run([sys.executable, '-c', 'import aqm_mjx, aqm_mjx.envs'], capture_output=True, text=True, check=True)
    assert out.stdout == '' and 'warp' not in out.stderr.lower()


def test_envs_and_render(tmp_path, capsys):
    assert cli.main(['envs']) == 0
    assert 'antmaze-giant' in capsys.readouterr().out
    png = tmp_path / 'giant.png'
    assert cli.main(['render', '--env', 'antmaze-giant', '--out', str(png)]) == 0
    assert png.read_bytes()[:8] == b'\x89PNG\r\n\x1a\n' and png.stat().st_size > 5000


def test_render_out_is_a_picture_a_folder_or_refused(tmp_path, capsys):
    """render --out DIR writes DIR/ENV.png (not DIR.png beside it); a name without a suffix gets
    .png and the printed path is the file written; a suffix that is no picture is refused in one line."""
    folder = tmp_path / 'pics'
    folder.mkdir()
    assert cli.main(['render', '--env', 'pointmaze-medium', '--out', str(folder)]) == 0
    assert os.listdir(folder) == ['pointmaze-medium.png'] and not (tmp_path / 'pics.png').exists()
    assert capsys.readouterr().out.strip() == f'wrote {folder / "pointmaze-medium.png"}'
    assert cli.main(['render', '--env', 'pointmaze-medium', '--out', str(tmp_path / 'maze')]) == 0
    assert (tmp_path / 'maze.png').read_bytes()[:4] == b'\x89PNG' and capsys.readouterr().out.strip().endswith('maze.png')
    assert cli.main(['render', '--env', 'pointmaze-medium', '--out', str(tmp_path / 'new') + os.sep]) == 0
    assert (tmp_path / 'new' / 'pointmaze-medium.png').exists()
    assert cli.main(['render', '--env', 'pointmaze-medium', '--out', str(tmp_path / 'maze.txt')]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and 'not .txt' in err[0] and not (tmp_path / 'maze.txt').exists()


def test_unknown_env_is_a_clear_error(capsys):
    assert cli.main(['render', '--env', 'antmaze-huge']) == 2
    assert "unknown environment 'antmaze-huge'" in capsys.readouterr().err


def test_keypoint_maps_picture(tmp_path, capsys):
    png = tmp_path / 'kp.png'
    assert cli.main(['render', '--env', 'antmaze-medium', '--deltas', '4', '8', '--out', str(png)]) == 0
    out = capsys.readouterr().out
    assert out.count('1 component(s)') == 2 and png.stat().st_size > 10000


def test_section_options_come_from_the_config_fields(capsys):
    """Every map, agent and protocol field is an option of run and evaluate, with the field's help;
    no default is typed in the parser (unset options are None and keep the preset's value)."""
    import dataclasses

    import pytest

    from aqm_mjx import pipeline

    for cmd in ('run', 'evaluate'):
        with pytest.raises(SystemExit):
            cli.main([cmd, '--help'])
        text = ' '.join(capsys.readouterr().out.split())
        for section in pipeline.SECTIONS:
            for f in dataclasses.fields(type(getattr(pipeline.RunConfig(), section))):
                assert '--' + f.name.replace('_', '-') in text, (cmd, f.name)
                assert ' '.join(f.metadata['help'].split())[:30] in text, (cmd, f.name)


def test_run_config_overrides_name_the_problem():
    import pytest

    from aqm_mjx import pipeline

    cfg = pipeline.RunConfig.preset('cpu')
    new = cfg.with_overrides(['map.delta=12', 'steps=1000', 'agent.kappa=inf', 'protocol.tasks=1,3',
                              'train.q_hidden=64,64', 'protocol.ablations='])
    assert (new.map.delta, new.train.steps, new.agent.kappa, new.protocol.tasks) == (12.0, 1000, float('inf'), (1, 3))
    assert new.train.q_hidden == (64, 64) and new.protocol.ablations == () and new.map.candidates == cfg.map.candidates
    assert pipeline.RunConfig.from_dict(new.to_dict()) == new
    for bad, msg in (('delta=1', None), ('sections.x=1', "unknown section 'sections'"),
                     ('map.radius=3', "unknown MapConfig field 'radius'"),
                     ('train.batch_size=abc', r"AQMConfig.batch_size \(int\): cannot read 'abc'"),
                     ('agent.replan_slots=-1', 'replan_slots must be an integer >= 0'),
                     ('nothing=1', "no section has a field 'nothing'"), ('map.delta', 'not of the form key=value')):
        if msg is None:
            assert cfg.with_overrides([bad]).map.delta == 1.0  # 'delta' is unique to the map section
            continue
        with pytest.raises(ValueError, match=msg):
            cfg.with_overrides([bad])
    # presets hold the paper's evaluation defaults for a paper run
    paper = pipeline.RunConfig.preset('paper')
    assert 10 <= paper.map.delta <= 25 and paper.train.batch_size == 1024 and paper.protocol.episodes == 50


def test_cpu_long_preset_scales_the_cpu_run_for_every_method():
    import pytest

    from aqm_mjx import cli, pipeline, presets
    from aqm_mjx.learn import methods

    cpu, long = pipeline.RunConfig.preset('cpu', env='antmaze-large'), pipeline.RunConfig.preset('cpu-long',
                                                                                               env='antmaze-large')
    # same networks, map, rule and protocol, 2.5x the updates, 4x the data collected on the host
    assert (long.train.steps, cpu.train.steps) == (50_000, 20_000) and long.train.q_hidden == cpu.train.q_hidden
    assert (long.map, long.agent, long.protocol) == (cpu.map, cpu.agent, cpu.protocol)
    assert long.agent.cut_slack == 0.6 and long.protocol.stall_scale == 6.0 and long.train.preset == 'cpu-long'
    assert (pipeline.collect_episodes('cpu-long'), pipeline.collect_episodes('cpu')) == (400, 100)
    assert (pipeline.collect_physics('cpu-long'), pipeline.collect_physics('cpu')) == ('mujoco', 'mjx')
    for name in methods.names():  # every registered method has the preset
        assert pipeline.RunConfig.preset('cpu-long', method=name).train.steps == 50_000, name
    with pytest.raises(ValueError, match="unknown run preset 'cpu-longer'"):
        pipeline.collect_episodes('cpu-longer')
    with pytest.raises(ValueError, match="unknown run preset 'cpu-longer'"):
        pipeline.collect_physics('cpu-longer')
    # the CLI takes the preset's data size and physics unless --collect-episodes / --collect-physics say otherwise
    parser = cli.build_parser()
    assert cli.collect_episodes_of(parser.parse_args(['run', '--preset', 'cpu-long'])) == 400
    assert cli.collect_episodes_of(parser.parse_args(['compare', '--preset', 'cpu-long', '--collect-episodes', '7'])) == 7
    # cpu-quick: cpu-long's data, map, rule and protocol at half its updates; cpu-long is the default preset: a
    # bare run collects its 400 episodes on the host, --preset cpu its 100 in MJX
    quick = pipeline.RunConfig.preset('cpu-quick', env='antmaze-large')
    assert (quick.train.steps, quick.train.batch_size, quick.train.q_hidden) == (25_000, 256, long.train.q_hidden)
    assert (quick.map, quick.agent, quick.protocol) == (long.map, long.agent, long.protocol)
    assert (pipeline.collect_episodes('cpu-quick'), pipeline.collect_physics('cpu-quick')) == (400, 'mujoco')
    assert pipeline.RunConfig.preset(presets.DEFAULT) == pipeline.RunConfig.preset('cpu-long')
    assert presets.DEFAULT == 'cpu-long' and cli.collect_episodes_of(parser.parse_args(['run'])) == 400
    assert cli.collect_physics_of(parser.parse_args(['run'])) == 'mujoco'
    assert cli.collect_episodes_of(parser.parse_args(['run', '--preset', 'cpu'])) == 100
    physics = {(cmd, preset, env, given): cli.collect_physics_of(parser.parse_args(
        [cmd, '--preset', preset, '--env', env] + (['--collect-physics', given] if given else [])))
        for cmd in ('run', 'compare') for preset in ('cpu', 'cpu-long') for env in ('antmaze-medium', 'antmaze-teleport')
        for given in (None, 'mjx', 'mujoco')}
    for (cmd, preset, env, given), got in physics.items():
        # what the user names; else the preset's, except MJX for the teleport portals the host does not model
        want = given or ('mujoco' if preset == 'cpu-long' and env == 'antmaze-medium' else 'mjx')
        assert got == want, (cmd, preset, env, given)
    with pytest.raises(SystemExit):
        parser.parse_args(['run', '--collect-physics', 'brax'])


def test_run_and_compare_collect_in_the_physics_the_preset_or_the_user_names(monkeypatch, tmp_path):
    from aqm_mjx import cli, run
    from aqm_mjx.data import collect

    class Stop(Exception):
        pass

    seen = []

    def fake_collect(cfg, *a, **k):  # the data stage's request, then stop before minutes of collection
        seen.append((cfg.physics, cfg.episodes))
        raise Stop

    monkeypatch.setattr(collect, 'collect', fake_collect)
    runs = [(['run', '--preset', 'ci'], 'mjx'), (['run', '--preset', 'ci', '--collect-physics', 'mujoco'], 'mujoco'),
            (['compare', '--preset', 'ci', '--methods', 'gcbc', '--seeds', '1', '--collect-physics', 'mujoco'],
             'mujoco'),
            (['run', '--preset', 'cpu-long', '--collect-episodes', '3'], 'mujoco'),
            (['compare', '--preset', 'cpu-long', '--methods', 'gcbc', '--seeds', '1', '--collect-episodes', '3'],
             'mujoco')]
    for i, (argv, want) in enumerate(runs):
        with pytest.raises(Stop):
            cli.main(argv + ['--env', 'pointmaze-medium', '--out', str(tmp_path / f'r{i}')])
        assert seen[-1][0] == want, argv
    assert [e for _, e in seen] == [4, 4, 4, 3, 3]
    # the data stage hands the physics to the collection
    with pytest.raises(Stop):
        run.data_stage('pointmaze-medium', str(tmp_path / 'd'), None, 2, 2, physics='mujoco')
    assert seen[-1] == ('mujoco', 2)


def test_cpu_giant_preset_is_cpu_long_with_more_updates_and_a_map_that_fits_the_giant_maze():
    from aqm_mjx import cli, pipeline
    from aqm_mjx.learn import methods

    long, giant = (pipeline.RunConfig.preset(p, env='antmaze-giant') for p in ('cpu-long', 'cpu-giant'))
    # the networks and batch of cpu-long, 3x its updates, the measured map, the paper's single cut at the
    # 0.5% quantile's patience, and 10 episodes a task
    assert (giant.train.steps, giant.train.batch_size) == (150_000, 256) and giant.train.q_hidden == long.train.q_hidden
    assert (giant.map.delta, giant.map.max_keypoints) == (12.0, 512) and giant.agent.cut_slack == 0
    assert (giant.agent.kappa, giant.agent.switch_radius) == (long.agent.kappa, long.agent.switch_radius)
    assert giant.protocol.calibrate == long.protocol.calibrate == 'stall' and giant.protocol.stall_scale == 0
    assert giant.protocol.episodes == 10 and giant.train.preset == 'cpu-giant'
    assert pipeline.collect_episodes('cpu-giant') == 400
    for name in methods.names():  # every registered method has the preset
        assert pipeline.RunConfig.preset('cpu-giant', method=name).train.steps == 150_000, name
    assert cli.collect_episodes_of(cli.build_parser().parse_args(['run', '--preset', 'cpu-giant'])) == 400


_CACHED_PROGRAM = '''
import sys
if sys.argv[1] == 'cli':
    from aqm_mjx import cli
    cli.build_parser()          # the parser alone: the command then imports jax
    cli.enable_compile_cache()
import jax, jax.numpy as jnp
jax.config.update('jax_compilation_cache_dir', sys.argv[2])
jax.config.update('jax_persistent_cache_min_compile_time_secs', 0.0)
f = jax.jit(lambda x, i: (jnp.sin(x) @ x.T)[i].sum() + x.at[i].add(1.0).sum())
print(float(f(jnp.ones((16, 16)), jnp.arange(6) % 5)))
'''


def test_cached_executables_load_without_xla_log_lines(tmp_path):
    """A second run loads the program from the compile cache; XLA logs an E-level line per CPU
    tuning flag it "does not support" when it does. The CLI quiets that log before jaxlib loads."""
    def twice(mode):
        cache = tmp_path / mode
        env = {k: v for k, v in os.environ.items() if k != 'TF_CPP_MIN_LOG_LEVEL'}
        runs = [subprocess.run([sys.executable, '-c', _CACHED_PROGRAM, mode, str(cache)], env=env,
                               capture_output=True, text=True, timeout=120) for _ in range(2)]
        assert all(r.returncode == 0 for r in runs), runs[-1].stderr[-2000:]
        assert runs[0].stdout == runs[1].stdout
        assert any(cache.iterdir()), 'nothing was cached'
        return runs[1].stderr

    if 'cpu_aot_loader' not in twice('plain'):
        pytest.skip('this XLA does not log when it loads a cached executable')
    assert 'cpu_aot_loader' not in twice('cli')


def test_every_help_text_prints_without_format_leftovers(capsys):
    """Each subcommand's --help: exit 0 and no '%%' (argparse formats help strings, not descriptions)."""
    names = [a for a in cli.build_parser()._subparsers._group_actions[0].choices]  # pylint: disable=protected-access
    assert {'compare', 'merge', 'train', 'evaluate', 'collect', 'run'} <= set(names)
    for name in names:
        with pytest.raises(SystemExit) as e:
            cli.main([name, '--help'])
        assert e.value.code == 0
        text = capsys.readouterr().out
        assert '%%' not in text and 'usage: aqm-mjx ' + name in text, name


def test_version_and_provenance(capsys):
    """--version prints the package's version; provenance() names the version, this checkout's commit
    (as git reports it) and the command."""
    import aqm_mjx  # pylint: disable=import-outside-toplevel
    from aqm_mjx import files  # pylint: disable=import-outside-toplevel

    with pytest.raises(SystemExit) as e:
        cli.main(['--version'])
    assert e.value.code == 0 and capsys.readouterr().out.strip() == f'aqm-mjx {aqm_mjx.__version__}'
    p = files.provenance()
    assert p['version'] == aqm_mjx.__version__ and p['command'].startswith('aqm-mjx')
    head = subprocess.run(['git', '-C', os.path.dirname(os.path.dirname(aqm_mjx.__file__)), 'rev-parse', 'HEAD'],
                          capture_output=True, text=True)
    if head.returncode == 0:  # a git checkout (CI's clean clone is one)
        assert p['commit'].split('+')[0] == head.stdout.strip()
    else:
        assert p['commit'] is None
    import jax  # pylint: disable=import-outside-toplevel
    import mujoco  # pylint: disable=import-outside-toplevel

    assert p['libraries']['jax'] == jax.__version__ and p['libraries']['mujoco'] == mujoco.__version__
    assert set(p['libraries']) == set(files.LIBRARIES)
    assert p['device'] == dict(backend=jax.default_backend(), kind=jax.devices()[0].device_kind,
                               count=jax.device_count())


def test_a_configured_compile_cache_wins_over_the_commands_default(tmp_path):
    import jax

    before = jax.config.jax_compilation_cache_dir
    try:
        jax.config.update('jax_compilation_cache_dir', str(tmp_path))
        cli.enable_compile_cache()  # what every command calls first
        assert jax.config.jax_compilation_cache_dir == str(tmp_path)
    finally:
        jax.config.update('jax_compilation_cache_dir', before)


def test_dependencies_are_ranges_that_the_installed_versions_meet():
    """pyproject.toml declares ranges, not exact pins; the versions this suite runs on lie inside them
    (each lower bound is the tested release), and mujoco / mujoco-mjx share one range."""
    import tomllib  # pylint: disable=import-outside-toplevel
    from importlib import metadata  # pylint: disable=import-outside-toplevel

    from packaging.requirements import Requirement  # pylint: disable=import-outside-toplevel

    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    with open(os.path.join(root, 'pyproject.toml'), 'rb') as f:
        deps = [Requirement(d) for d in tomllib.load(f)['project']['dependencies']]
    assert deps and not [str(d) for d in deps if any(s.operator == '==' for s in d.specifier)]
    for d in deps:
        assert d.specifier.contains(metadata.version(d.name), prereleases=True), (d, metadata.version(d.name))
        if d.name in ('jax', 'mujoco', 'mujoco-mjx', 'flax'):  # tested lower bound and an upper bound
            assert {s.operator for s in d.specifier} >= {'>=', '<'}, d
    spec = {d.name: str(d.specifier) for d in deps}
    assert spec['mujoco'] == spec['mujoco-mjx']
    assert not Requirement(f'jax{spec["jax"]}').specifier.contains('0.10.2')  # the miscompiling release


def test_cpu_presets_evaluate_in_ogbench_environments_on_a_host_without_an_accelerator(tmp_path, monkeypatch,
                                                                                        capsys):
    """The rule of the cpu rows: on a CPU-only host `run` and `evaluate` evaluate in OGBench's own
    environments unless the user names a backend or an MJX physics; ci and paper rows, --one-program
    and an accelerator keep MJX. run.json records the backend the run uses."""
    import jax  # pylint: disable=import-outside-toplevel

    from aqm_mjx import assess, files  # pylint: disable=import-outside-toplevel
    from aqm_mjx.cli import commands  # pylint: disable=import-outside-toplevel
    from aqm_mjx.data import collect  # pylint: disable=import-outside-toplevel

    host = ['protocol.backend=ogbench']
    assert jax.default_backend() == 'cpu'
    for preset in ('cpu', 'cpu-long', 'cpu-giant'):
        assert commands.host_backend([preset], []) == host
        assert commands.host_backend([preset], ['protocol.physics_preset=ogbench', 'map.delta=6']) == host
    for overrides in (['protocol.backend=mjx'], ['backend=mjx'], ['protocol.backend=ogbench'],
                      ['protocol.physics_preset=fast'], ['physics_preset=newton-4']):
        assert commands.host_backend(['cpu-long'], overrides) == [], overrides
    assert commands.host_backend(['ci'], []) == commands.host_backend(['paper'], []) == []
    assert commands.host_backend(['cpu-long', 'ci'], []) == []
    with monkeypatch.context() as m:
        m.setattr(jax, 'default_backend', lambda: 'gpu')
        assert commands.host_backend(['cpu-long'], []) == []

    class Stop(Exception):
        pass

    monkeypatch.setattr(collect, 'collect', lambda *a, **k: (_ for _ in ()).throw(Stop()))
    for i, (argv, want) in enumerate([(['--preset', 'cpu-long'], 'ogbench'), (['--preset', 'ci'], 'mjx'),
                                      (['--preset', 'cpu-long', '--backend', 'mjx'], 'mjx'),
                                      (['--preset', 'cpu', '--physics-preset', 'fast'], 'mjx')]):
        out = tmp_path / f'run{i}'
        with pytest.raises(Stop):
            cli.main(['run', '--env', 'pointmaze-medium', '--out', str(out), *argv])
        assert files.read_json(str(out / 'run.json'))['protocol']['backend'] == want, argv
        header = capsys.readouterr().out
        assert ("in OGBench's environments on the host (no accelerator" in header) == (i == 0), header

    seen = []
    monkeypatch.setattr(assess, 'evaluate_checkpoint', lambda *a, overrides=(), **k: seen.append(list(overrides)))
    ship = os.path.join(os.path.dirname(os.path.dirname(__file__)), 'checkpoints',
                        'aqm-antmaze-medium-navigate-cpu-long')
    capsys.readouterr()
    assert cli.main(['evaluate', '--checkpoint', ship, '--out', str(tmp_path / 'ev')]) == 0
    assert "evaluation in OGBench's environments on the host (no accelerator" in capsys.readouterr().out
    assert cli.main(['evaluate', '--checkpoint', ship, '--backend', 'mjx', '--out', str(tmp_path / 'ev')]) == 0
    assert 'on the host' not in capsys.readouterr().out
    assert cli.main(['evaluate', '--checkpoint', ship, '--preset', 'ci', '--out', str(tmp_path / 'ev')]) == 0
    assert [host[0] in s for s in seen] == [True, False, False]


def test_the_parser_imports_no_jax_answers_at_once_and_errors_in_one_line():
    """--help and a wrong argument come from the stored catalog (no JAX, MuJoCo or numpy imported),
    the catalog is the package's own lists, and a usage error is one line naming the problem."""
    import time  # pylint: disable=import-outside-toplevel

    from aqm_mjx.cli import catalog  # pylint: disable=import-outside-toplevel

    assert catalog.load() == catalog.build(), \
        "cli/catalog.json is stale: python -c 'from aqm_mjx.cli import catalog; catalog.write()'"
    probe = ('import sys; from aqm_mjx.cli import build_parser, main; build_parser().parse_args(["run"]); '
             'main(["envs"]); main(["methods"]); '
             'print(sorted(m for m in ("jax", "mujoco", "flax", "numpy", "matplotlib") if m in sys.modules))')
    out = subprocess.run([sys.executable, '-c', probe], capture_output=True, text=True, check=True)
    lines = out.stdout.strip().splitlines()
    assert lines[-1] == '[]', out.stdout  # envs and methods listed, nothing heavy imported
    assert any(ln.startswith('antmaze-giant ') for ln in lines) and any(ln.startswith('aqm ') for ln in lines)
    for argv in (['--help'], ['--version'], ['envs'], ['methods']):
        t0 = time.perf_counter()
        r = subprocess.run([sys.executable, '-m', 'aqm_mjx.cli', *argv], capture_output=True, text=True)
        took = time.perf_counter() - t0
        assert r.returncode == 0 and r.stdout and took < 3.0, (argv, took)  # about 0.1 s alone
    t0 = time.perf_counter()
    r = subprocess.run([sys.executable, '-m', 'aqm_mjx.cli', 'evaluate', '--help'], capture_output=True, text=True)
    took = time.perf_counter() - t0
    assert r.returncode == 0 and '--physics-preset' in r.stdout and '--max-keypoints' in r.stdout
    assert took < 3.0, f'evaluate --help took {took:.1f} s'  # about 0.1 s alone; generous for a loaded CI
    for argv, says in ((['run', '--preset', 'nope'], "argument --preset: invalid choice: 'nope'"),
                       (['train'], 'the following arguments are required: --dataset, --out'),
                       (['evaluate', '--checkpoint', 'x', '--episodes'], 'argument --episodes: expected one argument')):
        r = subprocess.run([sys.executable, '-m', 'aqm_mjx.cli', *argv], capture_output=True, text=True)
        lines = r.stderr.strip().splitlines()
        assert r.returncode == 2 and len(lines) == 1 and says in lines[0], r.stderr
        assert lines[0].startswith(f'aqm-mjx {argv[0]}: error:') and f'see aqm-mjx {argv[0]} --help' in lines[0]


def test_one_output_rule_for_every_command(tmp_path, monkeypatch, capsys):
    """--out is never an input, inside one (but beside a checkpoint's checkpoints/), inside a shipped
    checkpoint, or a folder of another command: refused in one line before any work, nothing written.
    A shipped checkpoint's evaluation goes to runs/eval/NAME by default, not into the checkout."""
    from aqm_mjx import assess  # pylint: disable=import-outside-toplevel

    ship = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), 'checkpoints',
                        'aqm-antmaze-medium-navigate-cpu-long')
    seen = []
    monkeypatch.setattr(assess, 'evaluate_checkpoint', lambda c, cfg, out=None, **k: seen.append(out))
    monkeypatch.chdir(tmp_path)
    assert cli.main(['evaluate', '--checkpoint', ship]) == 0
    assert seen == [os.path.join('runs', 'eval', 'aqm-antmaze-medium-navigate-cpu-long')]
    assert 'a shipped checkpoint, only read' in capsys.readouterr().out
    assert assess.default_out([ship]) == seen[0]
    cmp_, train, run_, ev = (tmp_path / n for n in ('cmp', 'train', 'run', 'ev'))
    for folder, marker in ((cmp_, 'compare.json'), (train, 'config.json'), (run_, 'run.json'), (ev, 'results.json')):
        folder.mkdir()
        (folder / marker).write_text('{"mine": 1}')
    (cmp_ / 'results.json').write_text('{"the": "table"}')
    (train / 'config.json').write_text(open(os.path.join(ship, 'config.json')).read())  # a readable training config
    (train / 'checkpoints').mkdir()
    before = {p: p.read_text() for p in tmp_path.rglob('*.json')}
    cases = [(['evaluate', '--checkpoint', ship, '--out', str(cmp_)], 'is a comparison'),  # the case
             (['evaluate', '--checkpoint', ship, '--out', str(train)], 'is a training run folder'),
             (['evaluate', '--checkpoint', ship, '--out', str(run_)], 'is a run folder'),
             (['evaluate', '--checkpoint', ship, '--out', os.path.join(ship, 'eval')], 'inside the shipped checkpoint'),
             (['evaluate', '--checkpoint', str(train), '--out', str(train / 'checkpoints' / 'x')],
              'lies inside the input'),
             (['evaluate', '--checkpoint', str(train), '--out', str(tmp_path)], 'holds the input'),
             (['compare', '--out', str(train)], 'is a training run folder'),
             (['compare', '--out', str(ev)], "is an evaluation's results"),
             (['run', '--out', str(cmp_)], 'is a comparison'),
             (['train', '--dataset', 'x.npz', '--out', str(cmp_)], 'is a comparison'),
             (['export', '--checkpoint', str(train), '--out', str(train / 'exp')], 'lies inside the input'),
             (['export', '--checkpoint', str(train), '--out', os.path.join(ship, 'x')], 'inside the shipped checkpoint')]
    for argv, says in cases:
        assert cli.main(argv) == 2, argv
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and says in err[0], (argv, err)
    assert {p: p.read_text() for p in tmp_path.rglob('*.json')} == before
    assert not (train / 'exp').exists() and not (train / 'checkpoints' / 'x').exists()
    # beside a checkpoint's checkpoints/ (its eval/) and an evaluation folder again: allowed
    seen.clear()
    assert cli.main(['evaluate', '--checkpoint', str(train), '--out', str(train / 'eval2')]) == 0
    assert cli.main(['evaluate', '--checkpoint', str(train), '--out', str(ev)]) == 0
    assert seen == [str(train / 'eval2'), str(ev)]


def test_compare_collects_in_the_physics_every_method_is_evaluated_in(tmp_path, monkeypatch):
    """compare's data are collected in the physics preset named for every method, by --physics-preset
    or by --set (protocol.)physics_preset; one method's own setting does not choose the data's."""
    from aqm_mjx import compare  # pylint: disable=import-outside-toplevel

    seen = []
    monkeypatch.setattr(compare, 'compare', lambda *a, collect_preset, **k: seen.append(collect_preset))
    cases = [([], 'ogbench'), (['--physics-preset', 'fast'], 'fast'),
             (['--set', 'protocol.physics_preset=newton-4'], 'newton-4'), (['--set', 'physics_preset=newton-2'],
                                                                            'newton-2'),
             (['--set', 'gcbc:physics_preset=fast'], 'ogbench')]
    for i, (argv, want) in enumerate(cases):
        assert cli.main(['compare', '--methods', 'gcbc', '--out', str(tmp_path / f'c{i}'), *argv]) == 0
        assert seen[-1] == want, argv
