"""Execute the notebooks in place, so that they are committed with their outputs.

    python notebooks/execute.py                        # every notebook at its default scale (cpu)
    python notebooks/execute.py replanning --scale gpu

Each runs from ``notebooks/`` (their default checkpoint is ``../checkpoints/...``) with
``AQM_NOTEBOOK_SCALE`` set; the time each took is printed. ``tests/test_notebooks.py`` runs them at
the ``ci`` scale without writing them.
"""

from __future__ import annotations

import argparse
import base64
import os
import time
from pathlib import Path

import nbformat
from nbclient import NotebookClient

HERE = Path(__file__).resolve().parent


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    p.add_argument('names', nargs='*', help='notebook names without .ipynb (default: all)')
    p.add_argument('--scale', default='cpu', choices=('ci', 'cpu', 'gpu'))
    p.add_argument('--timeout', type=int, default=3600, help='seconds per cell')
    p.add_argument('--figures', default=None, help="also write each notebook's last figure as FIGURES/NAME.png")
    a = p.parse_args()
    paths = [HERE / f'{n}.ipynb' for n in a.names] or sorted(HERE.glob('*.ipynb'))
    os.environ['AQM_NOTEBOOK_SCALE'] = a.scale
    for path in paths:
        nb = nbformat.read(path, as_version=4)
        t0 = time.perf_counter()
        NotebookClient(nb, timeout=a.timeout, kernel_name='python3', resources={'metadata': {'path': str(HERE)}}).execute()
        nbformat.write(nb, path)
        if a.figures:
            pngs = [o['data']['image/png'] for c in nb.cells if c.cell_type == 'code' for o in c.get('outputs', [])
                    if 'image/png' in o.get('data', {})]
            if pngs:
                os.makedirs(a.figures, exist_ok=True)
                with open(os.path.join(a.figures, f'{path.stem}.png'), 'wb') as f:
                    f.write(base64.b64decode(pngs[-1]))
        print(f'{path.name}: executed at scale {a.scale} in {time.perf_counter() - t0:.0f} s')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
