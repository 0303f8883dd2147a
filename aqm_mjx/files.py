"""Small JSON and text files written atomically (a config beside a checkpoint, a run's summary, results)."""

from __future__ import annotations

import json
import os


class MissingFileError(FileNotFoundError):
    """A file a run folder should hold is not there; the message says which and why it matters."""


def write_json(path: str, obj: dict, makedirs: bool = False) -> None:
    """Atomic JSON write: the old file stays until the new one is complete."""
    if makedirs:
        os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    tmp = path + '.tmp'
    with open(tmp, 'w') as f:
        json.dump(obj, f, indent=1, sort_keys=True)
    os.replace(tmp, path)


def write_text(path: str, text: str) -> None:
    """Atomic text write (a table beside results)."""
    tmp = path + '.tmp'
    with open(tmp, 'w') as f:
        f.write(text)
    os.replace(tmp, path)


def read_json(path: str, what: str = 'a run folder written by aqm-mjx train') -> dict:
    if not os.path.exists(path):
        raise MissingFileError(f'{path}: no such file (is this {what}?)')
    with open(path) as f:
        return json.load(f)
