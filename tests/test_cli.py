"""The package imports silently and the CLI's cheap commands work and fail clearly."""

import subprocess
import sys

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


def test_unknown_env_is_a_clear_error(capsys):
    assert cli.main(['render', '--env', 'antmaze-huge']) == 2
    assert "unknown environment 'antmaze-huge'" in capsys.readouterr().err


def test_keypoint_maps_picture(tmp_path, capsys):
    png = tmp_path / 'kp.png'
    assert cli.main(['render', '--env', 'antmaze-medium', '--deltas', '4', '8', '--out', str(png)]) == 0
    out = capsys.readouterr().out
    assert out.count('1 component(s)') == 2 and png.stat().st_size > 10000
