"""Named physics settings: each reaches the compiled model and the evaluation's program; a name outside
the fidelity study is refused with one line."""

import dataclasses
import json
import subprocess
import sys

import mujoco
import pytest

from aqm_mjx import cli, envs
from aqm_mjx.envs import physics
from aqm_mjx.envs.locomaze import PhysicsOptions


@pytest.mark.parametrize('name', ['ogbench', 'fast', 'newton-1-caps8', 'euler'])
def test_a_preset_reaches_the_compiled_model(name):
    """MuJoCo's model and MJX's (what the jitted step closes over) hold the preset's integrator, dt,
    solver iterations and contact caps; the control step stays 0.1 s."""
    p = physics.get(name)
    env = envs.make('antmaze-medium', physics=name)
    for opt in (env.mj_model.opt, env.mjx_model.opt):
        assert int(opt.iterations) == p.iterations and int(opt.ls_iterations) == p.ls_iterations
        assert int(opt.integrator) == int({'rk4': mujoco.mjtIntegrator.mjINT_RK4,
                                           'euler': mujoco.mjtIntegrator.mjINT_EULER,
                                           'implicitfast': mujoco.mjtIntegrator.mjINT_IMPLICITFAST}[p.integrator])
    assert env.frame_skip == p.substeps
    assert env.frame_skip * float(env.mj_model.opt.timestep) == pytest.approx(0.1, abs=1e-12)
    assert float(env.mjx_model.opt.timestep) == pytest.approx(env.mj_model.opt.timestep, rel=1e-6)  # float32
    numeric = {env.mj_model.numeric(i).name: env.mj_model.numeric(i).data[0] for i in range(env.mj_model.nnumeric)}
    assert (numeric['max_geom_pairs'], numeric['max_contact_points']) == p.contact_caps


def test_ogbench_is_ogbenchs_own_physics_bit_for_bit():
    """The default is OGBench's ant.xml: RK4, dt exactly 0.02 (not 0.1 / 5 in floating point), Newton 100/50."""
    env = envs.make('antmaze-medium')
    assert env.physics == physics.get('ogbench') == PhysicsOptions()
    assert env.mj_model.opt.timestep == 0.02 and env.frame_skip == 5
    assert (env.mj_model.opt.iterations, env.mj_model.opt.ls_iterations) == (100, 50)
    assert physics.name_of(env.physics) == 'ogbench' and physics.name_of(physics.get('fast')) == 'fast'


def test_fast_is_a_row_of_the_study_and_differs_from_ogbench():
    assert physics.FAST_ROW in physics.STUDY and physics.PRESETS['fast'] == physics.STUDY[physics.FAST_ROW]
    assert physics.PRESETS['fast'] != physics.PRESETS['ogbench']


def test_with_physics_rebuilds_only_when_the_settings_differ():
    env = envs.make('antmaze-medium', max_episode_steps=77, terminate_at_goal=False)
    assert envs.with_physics(env, 'ogbench') is env
    fast = envs.with_physics(env, 'fast')
    assert fast.physics == physics.get('fast') and fast.max_episode_steps == 77 and not fast.terminate_at_goal


def test_the_evaluation_program_steps_the_protocols_physics(monkeypatch):
    """``protocol.physics_preset`` is what make_program hands the rollout (the env it compiles)."""
    from aqm_mjx.evaluation import evaluate

    seen = {}

    def fake_rollout(env, agent, cfg, steps, progress=None):
        seen['physics'] = env.physics
        return lambda *args: None

    monkeypatch.setattr(evaluate, 'make_rollout', fake_rollout)
    env = envs.make('antmaze-medium')
    evaluate.make_program(env, None, None, 5, physics='fast')
    assert seen['physics'] == physics.get('fast')
    evaluate.make_program(env, None, None, 5)  # None: the env's own
    assert seen['physics'] == physics.get('ogbench')


def test_an_unknown_setting_is_refused_with_one_line(capsys):
    from aqm_mjx.data import collect
    from aqm_mjx.evaluation.protocol import ProtocolConfig

    with pytest.raises(ValueError, match=r"unknown physics preset 'turbo'; expected one of ogbench, .*fast"):
        envs.make('antmaze-medium', physics='turbo')
    with pytest.raises(ValueError, match="physics_preset 'turbo'"):
        ProtocolConfig(physics_preset='turbo')
    with pytest.raises(ValueError, match="unknown physics preset 'turbo'"):
        collect.CollectConfig(physics_preset='turbo').resolved()
    with pytest.raises(ValueError, match='substeps must be an integer >= 1'):
        PhysicsOptions(substeps=0)
    for argv in (['collect', '--out', 'x.npz', '--physics-preset', 'turbo'],
                 ['evaluate', '--checkpoint', 'x', '--physics-preset', 'turbo'],
                 ['run', '--physics-preset', 'turbo'],
                 ['compare', '--physics-preset', 'turbo']):
        with pytest.raises(SystemExit) as e:
            cli.main(argv)
        assert e.value.code == 2
        err = capsys.readouterr().err
        assert "invalid choice: 'turbo'" in err and 'fast' in err, argv


def test_the_preset_is_recorded_in_the_run_config():
    from aqm_mjx import pipeline

    cfg = pipeline.RunConfig.preset('ci', env='antmaze-medium').with_overrides(['protocol.physics_preset=fast'])
    d = cfg.to_dict()
    assert d['protocol']['physics_preset'] == 'fast'
    assert pipeline.RunConfig.from_dict(json.loads(json.dumps(d))).protocol.physics_preset == 'fast'
    assert dataclasses.replace(cfg.protocol, physics_preset='ogbench').physics_preset == 'ogbench'


@pytest.mark.slow
def test_the_study_script_runs_at_tiny_sizes(tmp_path):
    """benchmarks/experiments/physics_fidelity.py --tiny: the cost and open-loop parts, two settings,
    a row each with finite figures (the script's own test; its closed loop is the slow tier's)."""
    out = subprocess.run([sys.executable, 'benchmarks/experiments/physics_fidelity.py', '--tiny', '--parts', 'openloop', '--host-row',
                          '--settings', 'ogbench', 'fast', '--out', str(tmp_path)], capture_output=True, text=True,
                         cwd=str(__import__('pathlib').Path(__file__).parents[1]), timeout=900)
    assert out.returncode == 0, out.stderr[-3000:]
    rows = json.loads((tmp_path / 'fidelity.json').read_text())['rows']
    assert [r['setting'] for r in rows] == ['host float32 start', 'ogbench', 'fast']
    for r in rows:
        assert r['episodes'] == 2 and 0 <= r['gap_10']['median'] <= r['gap_10']['max'] < 5
    assert '## open loop' in (tmp_path / 'fidelity.md').read_text()


def test_the_compilation_cache_is_the_documented_folder(tmp_path):
    """Commands cache compiled programs in README's folder, and JAX_COMPILATION_CACHE_DIR overrides it."""
    import pathlib

    from aqm_mjx.cli import commands

    readme = (pathlib.Path(__file__).parents[1] / 'README.md').read_text()
    assert f'`{commands.CACHE_DIR}`' in readme and 'JAX_COMPILATION_CACHE_DIR' in readme
    code = ('import jax; from aqm_mjx.cli import commands; commands.enable_compile_cache(); '
            'print(jax.config.jax_compilation_cache_dir)')
    env = {k: v for k, v in __import__('os').environ.items() if k != 'JAX_COMPILATION_CACHE_DIR'}
    home = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True, check=True,
                          env=dict(env, HOME=str(tmp_path))).stdout.strip()
    assert home == str(tmp_path / '.cache' / 'aqm_mjx' / 'jax')
    chosen = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True, check=True,
                            env=dict(env, JAX_COMPILATION_CACHE_DIR=str(tmp_path / 'mine'))).stdout.strip()
    assert chosen == str(tmp_path / 'mine')


def test_an_automatic_chunk_fits_the_memory_estimate():
    """protocol.envs = 0: the largest power of two whose states (x FACTOR x 2) fit, capped at 65,536;
    by hand with 1 GiB available and a state of s bytes: 2^floor(log2(2^30 / (8 s)))."""
    import math

    from aqm_mjx import memory
    from aqm_mjx.evaluation.protocol import ProtocolConfig

    env = envs.make('antmaze-medium', physics='fast')
    s = memory.env_state_bytes(env)
    n = memory.fitting_envs(env, where=(2 ** 30, 'host'))
    assert n == 2 ** math.floor(math.log2(2 ** 30 / (memory.FACTOR * 2 * s)))
    assert n * s * memory.FACTOR * 2 <= 2 ** 30 < 2 * n * s * memory.FACTOR * 2
    assert memory.fitting_envs(env, where=(2 ** 50, 'gpu')) == memory.MAX_AUTO_ENVS
    assert memory.fitting_envs(env, where=(10, 'tiny')) == 1
    assert ProtocolConfig(envs=0).envs == 0
    with pytest.raises(ValueError, match='envs must be an integer >= 0'):
        ProtocolConfig(envs=-1)
    # a state's size depends on its physics (contact caps): the estimate is kept per physics
    assert memory.env_state_bytes(envs.make('antmaze-medium', physics='newton-1-caps8')) < s


@pytest.mark.slow
def test_the_device_script_runs_on_a_cpu_at_tiny_sizes(tmp_path):
    """benchmarks/throughput/device_physics.sh with TINY=1: every step writes its output, the closed loop
    its table (minutes of compiling on a CPU: the slow tier)."""
    import os
    import pathlib

    root = pathlib.Path(__file__).parents[1]
    env = dict(os.environ, TINY='1', OUT=str(tmp_path), PY=sys.executable, JAX_COMPILATION_CACHE_DIR=str(tmp_path / 'c'))
    out = subprocess.run(['bash', 'benchmarks/throughput/device_physics.sh'], capture_output=True, text=True,
                         cwd=str(root), env=env, timeout=3000)
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]
    for name in ('env_ogbench.json', 'env_fast.json', 'agent_ogbench.json', 'agent_fast.json',
                 'closed/fidelity.json'):
        assert (tmp_path / name).stat().st_size > 100, name
    assert '| mjx fast | aqm |' in (tmp_path / 'closed.txt').read_text()
    assert '== done' in out.stdout
