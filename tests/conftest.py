"""Shared test helpers."""

import os
import subprocess
import sys

import pytest


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
