"""Every notebook executes headless at its small (`ci`) setting and draws its figures."""

from pathlib import Path

import nbformat
import pytest
from nbclient import NotebookClient

NOTEBOOKS = sorted((Path(__file__).resolve().parent.parent / 'notebooks').glob('*.ipynb'))
# The two slowest (about 1.5 minutes each) run with -m slow; their paths are in the default suite:
# one_program as tests/test_pipeline.py's seed vmap, evaluate_from_checkpoint as
# tests/test_evaluate.py's learned-agent CLI test.
SLOW = {'one_program', 'evaluate_from_checkpoint'}
CASES = [pytest.param(p, id=p.stem, marks=pytest.mark.slow) if p.stem in SLOW else pytest.param(p, id=p.stem)
         for p in NOTEBOOKS]


@pytest.mark.parametrize('path', CASES)
def test_notebook_runs(path, monkeypatch, tmp_path):
    monkeypatch.setenv('AQM_NOTEBOOK_SCALE', 'ci')
    monkeypatch.delenv('AQM_DATASET', raising=False)
    nb = nbformat.read(path, as_version=4)
    NotebookClient(nb, timeout=900, kernel_name='python3', resources={'metadata': {'path': str(tmp_path)}}).execute()
    outputs = [o for c in nb.cells if c.cell_type == 'code' for o in c.get('outputs', [])]
    assert not [o for o in outputs if o.get('output_type') == 'error']
    assert any('image/png' in o.get('data', {}) for o in outputs), 'no figure was drawn'


@pytest.mark.parametrize('path', NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_notebooks_are_committed_with_their_outputs(path):
    """What a repository page shows: every code cell executed in order, at least one figure, no error
    (`python notebooks/execute.py` writes them)."""
    nb = nbformat.read(path, as_version=4)
    code = [c for c in nb.cells if c.cell_type == 'code']
    assert [c.get('execution_count') for c in code] == list(range(1, len(code) + 1)), 'not executed in order'
    outputs = [o for c in code for o in c.get('outputs', [])]
    assert not [o for o in outputs if o.get('output_type') == 'error']
    assert any('image/png' in o.get('data', {}) for o in outputs), 'committed without its figures'
