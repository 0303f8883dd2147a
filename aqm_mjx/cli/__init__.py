"""Command line: ``aqm-mjx {run,collect,train,evaluate,compare,merge,methods,render,envs}``.

``run`` is the whole pipeline (collect -> train -> keypoints -> evaluate); the other commands are
its stages, or tools. :mod:`aqm_mjx.cli.options` declares the options, :mod:`aqm_mjx.cli.commands`
connects them to the package; this module runs one command and turns its errors into one line.
"""

from __future__ import annotations

import os
import sys

# Loading a cached CPU executable makes XLA log E-level "Target machine feature +prefer-no-gather is
# not supported" lines listing ~150 CPU features (tuning flags differ, the code runs). Quiet XLA's C++
# log unless the user chose a level. XLA reads the level once, when jaxlib loads (a command imports it
# after parsing its arguments; the parser reads cli/catalog.json and imports no JAX), so it is set
# here, before anything else. Python-side errors are unaffected.
os.environ.setdefault('TF_CPP_MIN_LOG_LEVEL', '3')

from aqm_mjx.cli.commands import (collect_episodes_of, collect_physics_of, enable_compile_cache,  # noqa: E402,F401
                                  run_config)
from aqm_mjx.cli.options import build_parser  # noqa: E402


def _one_line(err: BaseException) -> str:
    """An error as the one line the user reads: an OS error as ``path: reason``."""
    if isinstance(err, OSError) and err.strerror and err.filename:
        return f'{err.filename}: {err.strerror}'
    text = ' '.join(str(err).split())
    return text or type(err).__name__


def _leave_processes(code: int) -> None:
    """With several processes (:mod:`aqm_mjx.processes`), end this one now with ``code``: JAX's own exit
    would wait at its shutdown barrier for partners that may be gone, then abort with a stack trace."""
    jax = sys.modules.get('jax')  # (a command that never imported JAX started no processes)
    if jax is not None and jax.distributed.is_initialized():
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)  # pylint: disable=protected-access


def main(argv=None):
    a = build_parser().parse_args(argv)
    from aqm_mjx import files  # pylint: disable=import-outside-toplevel

    files.COMMAND[:] = ['aqm-mjx'] + list(sys.argv[1:] if argv is None else argv)  # provenance and lock files
    try:
        return a.fn(a)
    except BrokenPipeError:  # the reader went away (`aqm-mjx envs | head`): nothing to say to it
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    except (ValueError, TypeError, OSError, RuntimeError) as err:
        print(f'aqm-mjx: error: {_one_line(err)}', file=sys.stderr)
        _leave_processes(2)
        return 2
    except KeyboardInterrupt:
        # files are written atomically and checkpoints are complete or absent: nothing half-written
        again = ('the same command with --resume' if a.cmd == 'train' and not getattr(a, 'resume', False)
                 else 'the same command again')
        print(f'\naqm-mjx {a.cmd}: interrupted. Run {again} to resume (training continues from its last '
              'checkpoint; finished stages are not redone).', file=sys.stderr)
        return 130
