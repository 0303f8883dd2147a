"""What every benchmark prints last: where it ran, and (with ``--out``) its rows as JSON."""

from __future__ import annotations

import json
import os
import platform

import jax


def _cpu_model() -> str:
    try:
        with open('/proc/cpuinfo') as f:
            return next((line.split(':', 1)[1].strip() for line in f if line.startswith('model name')), platform.processor())
    except OSError:
        return platform.processor()


def finish(rows: list, out: str | None) -> None:
    """Print the machine line; write ``{'meta': ..., 'rows': rows}`` to ``out`` when given."""
    meta = dict(backend=jax.default_backend(), device=str(jax.devices()[0]), device_kind=jax.devices()[0].device_kind,
                cpu_count=os.cpu_count(), cpu=_cpu_model(), machine=platform.machine(), jax=jax.__version__)
    print(json.dumps(meta))
    if out:
        with open(out, 'w') as f:
            json.dump(dict(meta=meta, rows=rows), f, indent=1)
