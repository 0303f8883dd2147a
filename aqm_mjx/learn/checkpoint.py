"""Orbax checkpoints of a training state, with the run's config as JSON beside it.

Layout of a run folder::

    DIR/config.json            the run's config (also inside every checkpoint)
    DIR/metrics.jsonl          one JSON object per logged step
    DIR/checkpoints/<step>/    Orbax: ``state`` (every array needed to continue) and ``config``

A checkpoint Orbax did not finish is never listed (it writes to a temporary name first). Every save
records a digest of the state's bytes (CRC-32 per array) beside its config; a restore checks that
every floating array is finite and that the bytes read give the digest saved (damaged bytes that
still decode, e.g. flipped bits in a data file, fail it). One that is listed but cannot be read or
fails that check is skipped for the previous one with one warning line; a resuming run also moves it
aside to ``DIR/checkpoints_unreadable/<step>`` (kept, not deleted) so that training
can write that step again. Orbax's own log lines and background-thread output during a restore are
kept from the terminal: its errors reach the user as one line each.
"""

from __future__ import annotations

import contextlib
import logging
import os
import shutil
import sys
import tempfile
import threading
import warnings
from typing import Any, Optional

import zlib

import jax
import jax.numpy as jnp
import numpy as np
import orbax.checkpoint as ocp

DIGEST_KEY = 'state_digest'  # the saved config's field holding the state's digest


def state_digest(state: Any) -> str:
    """CRC-32 of every array of ``state`` in tree order (``'crc32:HEX'``): what a restore compares."""
    crc = 0
    for x in jax.tree.leaves(state):
        if jnp.issubdtype(jnp.result_type(x), jax.dtypes.prng_key):
            x = jax.random.key_data(x)
        a = np.ascontiguousarray(np.asarray(x))
        crc = zlib.crc32(a.dtype.str.encode() + str(a.shape).encode(), crc)
        crc = zlib.crc32(a.tobytes(), crc)
    return f'crc32:{crc:08x}'


def finite_leaves(state, seeds: Optional[int] = None) -> dict:
    """``{path: bool}`` per floating leaf of ``state`` (``[S]`` with ``seeds``: every leaf stacked on
    a leading seed axis): True where all its values are finite. Jittable."""
    out = {}
    for path, x in jax.tree_util.tree_flatten_with_path(state)[0]:
        if jnp.issubdtype(x.dtype, jnp.inexact):
            ok = jnp.isfinite(x)
            out[jax.tree_util.keystr(path)] = ok.all() if seeds is None else ok.reshape(seeds, -1).all(1)
    return out


def state_faults(state: Any, config: dict) -> list[str]:
    """What is wrong with a restored ``state`` against the ``config`` saved with it: floating arrays
    with non-finite values (by path), and a digest that differs from the one saved (checkpoints
    written before digests were saved are checked for finiteness alone). Empty when it is sound."""
    faults = []
    bad = [p for p, ok in jax.device_get(finite_leaves(state)).items() if not ok]
    if bad:
        faults.append(f'non-finite values in {", ".join(bad[:3])}{" and more" if len(bad) > 3 else ""}')
    saved = config.get(DIGEST_KEY)
    if saved is not None and saved != state_digest(state):
        faults.append(f'its arrays do not match the digest saved with them ({saved}): damaged bytes')
    return faults


class CheckpointError(RuntimeError):
    """No usable checkpoint in a run folder."""


def _manager(directory: str, keep: Optional[int] = None, create: bool = True) -> ocp.CheckpointManager:
    # a writer (create=True, under the run folder's lock) removes what a killed save left behind. Every
    # manager is this process's alone: a run folder has one writer, and with several processes
    # (aqm_mjx.processes) each trains its own seeds and reads any checkpoint without waiting for the others
    pid = jax.process_index()
    alone = ocp.options.MultiprocessingOptions(primary_host=pid, active_processes={pid},
                                               barrier_sync_key_prefix=f'process_{pid}')
    root = os.path.abspath(os.path.join(directory, 'checkpoints'))
    if create:  # (Orbax creates it only for managers of every process)
        os.makedirs(root, exist_ok=True)
    opts = ocp.CheckpointManagerOptions(max_to_keep=keep, create=False, cleanup_tmp_directories=create,
                                        enable_async_checkpointing=False,  # saves end (or fail) before returning
                                        multiprocessing_options=alone)
    handlers = {'state': ocp.StandardCheckpointHandler(multiprocessing_options=alone),
                'config': ocp.JsonCheckpointHandler(multiprocessing_options=alone)}
    return ocp.CheckpointManager(root, options=opts, item_handlers=handlers)


class Checkpointer:
    """Save and restore ``(state pytree, config dict)`` pairs under ``DIR/checkpoints``."""

    def __init__(self, directory: str, keep: Optional[int] = 3, create: bool = True):
        self.directory = directory
        self._failed = False
        with quiet():
            self._mngr = _manager(directory, keep, create)

    def steps(self) -> list[int]:
        with quiet():
            return sorted(self._mngr.all_steps())

    def save(self, step: int, state: Any, config: dict) -> None:
        """Write checkpoint ``step`` and wait until it is complete on disk. A failed write (disk
        full, read-only) leaves no temporary folder behind and raises :class:`CheckpointError`
        with one line saying why; the checkpoints already there are untouched."""
        state = jax.device_get(state)  # host arrays: what one process of several may save alone
        config = dict(config, **{DIGEST_KEY: state_digest(state)})
        try:
            with quiet():
                self._mngr.save(int(step), args=ocp.args.Composite(state=ocp.args.StandardSave(state),
                                                                   config=ocp.args.JsonSave(config)), force=True)
                self._mngr.wait_until_finished()
        except KeyboardInterrupt:  # Ctrl-C mid-save: no half checkpoint, no Orbax traceback after the hint
            self._failed = True
            _silence_leftovers()
            self._remove_partial()
            raise
        except Exception as e:  # pylint: disable=broad-except  (Orbax and TensorStore raise many kinds)
            self._failed = True
            _silence_leftovers()
            with quiet():
                try:
                    self._mngr.wait_until_finished()
                except Exception:  # pylint: disable=broad-except
                    pass
            self._remove_partial()
            raise CheckpointError(f'cannot write checkpoint {step} in {self.directory}/checkpoints: '
                                  f'{one_line(e)}') from None

    def _remove_partial(self) -> None:
        """Delete the temporary folders of unfinished saves (only a writer, under the folder's lock)."""
        root = os.path.join(self.directory, 'checkpoints')
        for name in os.listdir(root) if os.path.isdir(root) else []:
            if '.orbax-checkpoint-tmp' in name:
                shutil.rmtree(os.path.join(root, name), ignore_errors=True)

    def saved_meta(self, step: int) -> dict:
        """The config saved inside checkpoint ``step`` (without reading its arrays)."""
        with quiet():
            out = self._mngr.restore(int(step), args=ocp.args.Composite(config=ocp.args.JsonRestore()))
        return dict(out['config'])

    def restore(self, template: Any, step: Optional[int] = None, log=print,
                set_aside: bool = False) -> tuple[int, Any, dict]:
        """Restore ``step`` (default: the newest readable one) into the structure of ``template``.

        A checkpoint that reads but fails :func:`state_faults` (non-finite values, bytes that do not
        give the digest saved) counts as unreadable.

        Args:
            set_aside: move each unreadable checkpoint newer than the one restored to
                ``DIR/checkpoints_unreadable/`` (a resuming writer; readers leave the folder alone).
        Returns:
            (step, state, config). Raises :class:`CheckpointError` when none can be read.
        """
        candidates = [int(step)] if step is not None else self.steps()[::-1]
        if not candidates:
            raise CheckpointError(f'no checkpoint in {os.path.join(self.directory, "checkpoints")}')
        errors = []
        _quiet_restore_leftovers()  # before a failure's callbacks can report
        host = jax.tree.map(lambda x: np.zeros(np.shape(x), jnp.result_type(x)), template)
        for s in candidates:
            try:
                with quiet():  # read as host arrays (any process may read any checkpoint), then put on the device
                    out = self._mngr.restore(s, args=ocp.args.Composite(state=ocp.args.StandardRestore(host),
                                                                        config=ocp.args.JsonRestore()))
                out = dict(out, state=jax.tree.map(jnp.asarray, out['state']))
                faults = state_faults(out['state'], dict(out['config']))
                if faults:
                    raise CheckpointError(f'it fails its check: {"; ".join(faults)}')
            except Exception as e:  # pylint: disable=broad-except  (any unreadable checkpoint: try the previous)
                why = str(e) if isinstance(e, CheckpointError) else one_line(e)
                msg = f'checkpoint {s} in {self.directory} is unreadable ({why})'
                errors.append(msg)
                if step is None:
                    if set_aside:
                        msg += f'; moved to {self.set_aside(s)}'
                    log(f'warning: {msg}; trying the previous one')
                continue
            return s, out['state'], dict(out['config'])
        raise CheckpointError('; '.join(errors))

    def set_aside(self, step: int) -> str:
        """Move checkpoint ``step`` out of the manager's folder (a new name if one is taken)."""
        dest_dir = os.path.join(self.directory, 'checkpoints_unreadable')
        os.makedirs(dest_dir, exist_ok=True)
        dest, k = os.path.join(dest_dir, str(step)), 1
        while os.path.exists(dest):
            dest, k = os.path.join(dest_dir, f'{step}.{k}'), k + 1
        shutil.move(os.path.join(self.directory, 'checkpoints', str(step)), dest)
        with quiet():
            self._mngr.reload()
        return dest

    def close(self):
        """Release the manager; after a failed save, whatever Orbax still raises is dropped (the
        failure was already reported)."""
        with quiet():
            try:
                self._mngr.close()
            except Exception:  # pylint: disable=broad-except
                if not self._failed:
                    raise
        if self._failed:  # Orbax's threads may have gone on writing after the failure was caught
            self._remove_partial()


def one_line(err: BaseException, limit: int = 200) -> str:
    """``Type: first line of the message`` (Orbax and TensorStore errors run over many lines)."""
    text = str(err).strip().splitlines()
    return f'{type(err).__name__}: {text[0][:limit] if text else ""}'


def _quiet_restore_leftovers() -> None:
    """Keep what a failed restore leaves behind off the terminal from now on (every restore calls this
    first): TensorStore callbacks that, from their own threads and after Orbax closed its event loop,
    report ``RuntimeError: Event loop is closed`` as unraisable (ten lines a callback, interleaved),
    and the ``asyncio`` logger's "Task exception was never retrieved" for Orbax's abandoned reads (this
    package runs no event loop of its own). Every other report reaches the hooks as before."""
    logging.getLogger('asyncio').setLevel(logging.CRITICAL + 1)
    if getattr(sys.unraisablehook, 'drops_closed_loop', False):
        return
    before_unraisable, before_except = sys.unraisablehook, sys.excepthook

    def closed_loop(value) -> bool:
        return isinstance(value, RuntimeError) and str(value) == 'Event loop is closed'

    def unraisable(u):
        if not closed_loop(u.exc_value):
            before_unraisable(u)

    def excepthook(kind, value, tb):
        if not closed_loop(value):
            before_except(kind, value, tb)

    unraisable.drops_closed_loop = True
    sys.unraisablehook, sys.excepthook = unraisable, excepthook


def _silence_leftovers() -> None:
    """After a failed save Orbax's worker threads and futures can still fail later (``Event loop is
    closed``, ``Future exception was never retrieved``): the run is stopping with its own one-line
    error, so those reports are dropped from then on."""
    logging.getLogger('asyncio').setLevel(logging.CRITICAL + 1)
    logging.getLogger('absl').setLevel(logging.CRITICAL + 1)
    threading.excepthook = lambda args: None
    sys.unraisablehook = lambda unraisable: None  # 'Exception ignored in: ...' from their event loops
    warnings.filterwarnings('ignore', message='coroutine .* was never awaited', category=RuntimeWarning)


@contextlib.contextmanager
def quiet():
    """Keep Orbax's and TensorStore's output off the terminal for the duration: absl/orbax log
    records, exceptions printed by background threads, and what C++ writes to file descriptor 2.
    The caller turns any exception into its own one-line message."""
    loggers = [logging.getLogger(n) for n in ('absl', 'orbax', 'jax._src.distributed')]
    levels = [lg.level for lg in loggers]
    hook = threading.excepthook
    try:
        sys.stderr.flush()
        saved_fd = os.dup(2)
    except (OSError, ValueError):
        saved_fd = None
    sink = tempfile.TemporaryFile() if saved_fd is not None else None
    try:
        for lg in loggers:
            lg.setLevel(logging.CRITICAL + 1)
        threading.excepthook = lambda args: None
        if sink is not None:
            os.dup2(sink.fileno(), 2)
        yield
    finally:
        if saved_fd is not None:
            os.dup2(saved_fd, 2)
            os.close(saved_fd)
            sink.close()
        threading.excepthook = hook
        for lg, lv in zip(loggers, levels):
            lg.setLevel(lv)
