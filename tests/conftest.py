"""Shared test helpers, and one compilation cache for the session.

The suite compiles many identical programs (the same env step, rollout or training chunk at the
same shapes in several tests): a persistent JAX compilation cache in a fresh folder per session,
shared by the pytest-xdist workers, compiles each once. ``AQM_TEST_COMPILE_CACHE=0`` turns it off
(every program compiled in its test, as before). Nothing outlives the session: the folder is removed
at its end.
"""

import os
import shutil
import subprocess
import sys
import tempfile

import pytest

CACHE_ENV = 'AQM_TEST_JAX_CACHE'  # the session's cache folder, set by the first process, inherited by workers


def pytest_configure(config):
    if os.environ.get('AQM_TEST_COMPILE_CACHE', '1') == '0':
        return
    if not os.environ.get(CACHE_ENV):
        os.environ[CACHE_ENV] = tempfile.mkdtemp(prefix='aqm_test_jax_cache_')
        config._aqm_cache_owner = True  # pylint: disable=protected-access
    import jax  # pylint: disable=import-outside-toplevel

    jax.config.update('jax_compilation_cache_dir', os.environ[CACHE_ENV])
    jax.config.update('jax_persistent_cache_min_compile_time_secs', 1.0)


def pytest_unconfigure(config):
    if getattr(config, '_aqm_cache_owner', False):
        shutil.rmtree(os.environ.pop(CACHE_ENV), ignore_errors=True)


@pytest.fixture
def no_compile_cache():
    """Compile in this test even when the session's cache holds the program (tests that count compilations)."""
    import jax  # pylint: disable=import-outside-toplevel

    before = jax.config.jax_enable_compilation_cache
    jax.config.update('jax_enable_compilation_cache', False)
    yield
    jax.config.update('jax_enable_compilation_cache', before)


@pytest.fixture
def two_device_python(tmp_path):
    """Run a script in a fresh Python with two host CPU devices
    (``XLA_FLAGS=--xla_force_host_platform_device_count=2``): ``run(source, test_file) -> stdout``.
    The script gets ``test_file`` as ``sys.argv[1]`` (to import helpers from its folder); a failure
    shows the end of its stderr."""

    def run(source: str, test_file: str) -> str:
        script = tmp_path / 'two_devices.py'
        script.write_text(source)
        env = dict(os.environ, XLA_FLAGS='--xla_force_host_platform_device_count=2', JAX_PLATFORMS='cpu')
        p = subprocess.run([sys.executable, str(script), test_file], capture_output=True, text=True, env=env,
                           timeout=900)
        assert p.returncode == 0, p.stderr[-3000:]
        return p.stdout

    return run


@pytest.fixture(scope='session')
def one_way_grid_walks():
    """The calibration set-up: a 5 x 5 grid whose column 2 is one-way except in row 4, 400 random
    walks of 40 steps on it, and the exact shortest-path steps between its cells.
    Returns ``(dataset dict, truth [25, 25])``."""
    from aqm_mjx.data import synthetic  # pylint: disable=import-outside-toplevel

    grid = synthetic.one_way_grid(5, one_way_column=2, open_rows=(4,))
    return synthetic.grid_walks(grid, episodes=400, steps=40, seed=0), synthetic.shortest_steps(grid)


@pytest.fixture
def point_model(tmp_path):
    """``train(method, steps) -> folder``: a ``ci`` model of ``method`` trained ``steps`` updates on 30
    point-maze walks of 60 steps, written as ``tmp_path/pointmaze-medium-navigate.npz`` (the run's
    dataset), into ``tmp_path/method``."""
    import numpy as np  # pylint: disable=import-outside-toplevel

    from aqm_mjx.data import synthetic  # pylint: disable=import-outside-toplevel
    from aqm_mjx.learn import fit, methods  # pylint: disable=import-outside-toplevel

    data = synthetic.point_walks(n_traj=30, t_len=60)
    path = str(tmp_path / 'pointmaze-medium-navigate.npz')
    np.savez(path, **data)

    def train(method: str, steps: int) -> str:
        cfg = methods.get(method).preset('ci', env='pointmaze-medium', steps=steps)
        fit.train(method, cfg, data, str(tmp_path / method), progress=False, log=lambda *_: None, dataset_path=path)
        return str(tmp_path / method)

    return train
