"""Orbax checkpoints of a training state, with the run's config as JSON beside it.

Layout of a run folder::

    DIR/config.json            the run's config (also inside every checkpoint)
    DIR/metrics.jsonl          one JSON object per logged step
    DIR/checkpoints/<step>/    Orbax: ``state`` (every array needed to continue) and ``config``

A checkpoint Orbax did not finish is never listed (it writes to a temporary name first); one that
is listed but cannot be read is skipped for the previous one, with a warning.
"""

from __future__ import annotations

import os
import warnings
from typing import Any, Optional

import orbax.checkpoint as ocp


class CheckpointError(RuntimeError):
    """No usable checkpoint in a run folder."""


def _manager(directory: str, keep: Optional[int] = None, create: bool = True) -> ocp.CheckpointManager:
    opts = ocp.CheckpointManagerOptions(max_to_keep=keep, create=create)
    return ocp.CheckpointManager(os.path.abspath(os.path.join(directory, 'checkpoints')), options=opts)


class Checkpointer:
    """Save and restore ``(state pytree, config dict)`` pairs under ``DIR/checkpoints``."""

    def __init__(self, directory: str, keep: Optional[int] = 3, create: bool = True):
        self.directory = directory
        self._mngr = _manager(directory, keep, create)

    def steps(self) -> list[int]:
        return sorted(self._mngr.all_steps())

    def save(self, step: int, state: Any, config: dict) -> None:
        """Write checkpoint ``step`` and wait until it is complete on disk."""
        self._mngr.save(int(step), args=ocp.args.Composite(state=ocp.args.StandardSave(state),
                                                           config=ocp.args.JsonSave(config)), force=True)
        self._mngr.wait_until_finished()

    def restore(self, template: Any, step: Optional[int] = None, log=print) -> tuple[int, Any, dict]:
        """Restore ``step`` (default: the newest readable one) into the structure of ``template``.

        Returns:
            (step, state, config). Raises :class:`CheckpointError` when none can be read.
        """
        candidates = [int(step)] if step is not None else self.steps()[::-1]
        if not candidates:
            raise CheckpointError(f'no checkpoint in {os.path.join(self.directory, "checkpoints")}')
        errors = []
        for s in candidates:
            try:
                out = self._mngr.restore(s, args=ocp.args.Composite(state=ocp.args.StandardRestore(template),
                                                                    config=ocp.args.JsonRestore()))
            except Exception as e:  # pylint: disable=broad-except  (any unreadable checkpoint: try the previous)
                msg = f'checkpoint {s} in {self.directory} is unreadable ({type(e).__name__}: {str(e)[:200]})'
                errors.append(msg)
                if step is None:
                    warnings.warn(msg + '; falling back to the previous one', RuntimeWarning, stacklevel=2)
                    log(f'warning: {msg}; falling back to the previous one')
                continue
            return s, out['state'], dict(out['config'])
        raise CheckpointError('; '.join(errors))

    def close(self):
        self._mngr.close()
