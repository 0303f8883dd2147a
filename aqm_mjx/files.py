"""Small JSON and text files written atomically (a config beside a checkpoint, a run's summary,
results), and the one-writer lock of a run folder."""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import shutil
import socket
import sys
import tempfile
import time
from typing import Optional


COMMAND: list = []  # the aqm-mjx command line being run (set by cli.main; empty: sys.argv)


def _command() -> str:
    return ' '.join(COMMAND or ['aqm-mjx'] + sys.argv[1:])


# the libraries whose versions a result records (installed distribution names)
LIBRARIES = ('jax', 'jaxlib', 'mujoco', 'mujoco-mjx', 'flax', 'optax', 'orbax-checkpoint', 'numpy', 'ogbench')


def library_versions() -> dict:
    """``{distribution: version}`` of :data:`LIBRARIES` (``None`` for one not installed)."""
    from importlib import metadata  # pylint: disable=import-outside-toplevel

    out = {}
    for name in LIBRARIES:
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            out[name] = None
    return out


def provenance() -> dict:
    """What produced a result: the package version, the git commit of the checkout it runs from
    (``None`` outside one; ``+dirty`` with uncommitted changes), the command line, the host, the
    versions of the libraries it ran on (:data:`LIBRARIES`) and JAX's device (kind and count)."""
    import platform  # pylint: disable=import-outside-toplevel
    import subprocess  # pylint: disable=import-outside-toplevel

    import jax  # pylint: disable=import-outside-toplevel

    import aqm_mjx  # pylint: disable=import-outside-toplevel

    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    commit = None
    try:
        head = subprocess.run(['git', '-C', root, 'rev-parse', 'HEAD'], capture_output=True, text=True, timeout=10)
        if head.returncode == 0:
            dirty = subprocess.run(['git', '-C', root, 'status', '--porcelain', '--untracked-files=no'],
                                   capture_output=True, text=True, timeout=10).stdout.strip()
            commit = head.stdout.strip() + ('+dirty' if dirty else '')
    except (OSError, subprocess.SubprocessError):
        pass
    return dict(version=aqm_mjx.__version__, commit=commit, command=_command(),
                host=socket.gethostname(), machine=platform.machine(), processor=platform.processor() or None,
                python=platform.python_version(), libraries=library_versions(),
                device=dict(backend=jax.default_backend(), kind=jax.devices()[0].device_kind,
                            count=jax.device_count()))


class MissingFileError(FileNotFoundError):
    """A file a run folder should hold is not there; the message says which and why it matters."""


class OutputError(OSError):
    """An output that cannot be written (read-only, not a folder, no space); the message says which."""


def write_json(path: str, obj: dict, makedirs: bool = False) -> None:
    """Atomic JSON write: the old file stays until the new one is complete."""
    if makedirs:
        os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    write_text(path, json.dumps(obj, indent=1, sort_keys=True))


def write_text(path: str, text: str) -> None:
    """Atomic text write: the old file stays until the new one is complete, and a failed write
    (disk full, read-only) leaves no temporary file behind."""
    tmp = path + '.tmp'
    try:
        with open(tmp, 'w') as f:
            f.write(text)
        os.replace(tmp, path)
    except BaseException as e:
        if os.path.exists(tmp):
            os.remove(tmp)
        if isinstance(e, OSError) and not isinstance(e, OutputError):
            raise OutputError(f'cannot write {path}: {e.strerror or e}') from None
        raise


def _existing_parent(path: str) -> str:
    path = os.path.abspath(path)
    while not os.path.exists(path):
        path = os.path.dirname(path)
    return path


def check_writable(folder: str, need_bytes: int = 0, what: str = 'the output') -> None:
    """Before minutes of work: ``folder`` can be created and written, with about ``need_bytes`` free.

    Raises :class:`OutputError` naming the folder and the reason (a file in the way, read-only or
    no permission, too little space)."""
    parent = _existing_parent(folder)
    if not os.path.isdir(parent):
        raise OutputError(f'cannot write to {folder}: {parent} is a file, not a folder')
    try:
        fd, probe = tempfile.mkstemp(dir=parent, prefix='.aqm-mjx-probe-')
        os.close(fd)
        os.remove(probe)
    except OSError as e:
        raise OutputError(f'cannot write to {folder}: {e.strerror or e} ({parent})') from None
    free = shutil.disk_usage(parent).free
    if need_bytes > free:
        raise OutputError(f'{what} needs about {need_bytes / 2 ** 20:.1f} MiB in {folder}; only '
                          f'{free / 2 ** 20:.1f} MiB are free there')


# what a folder is, by the file that marks it (the first found names it)
KINDS = {'compare.json': 'a comparison (aqm-mjx compare)', 'run.json': 'a run folder (aqm-mjx run)',
         'map_states.npz': 'a shipped or exported checkpoint (aqm-mjx export)',
         'config.json': 'a training run folder (aqm-mjx train)', 'results.json': "an evaluation's results"}
SHIPPED = 'map_states.npz'


def kind_of(folder: str) -> Optional[str]:
    """The marker file of :data:`KINDS` that ``folder`` holds (None: none, or no folder)."""
    if not os.path.isdir(folder):
        return None
    return next((k for k in KINDS if os.path.exists(os.path.join(folder, k))), None)


def shipped_above(path: str) -> Optional[str]:
    """The shipped or exported checkpoint that ``path`` is or lies inside, if any."""
    p = os.path.realpath(path)
    while True:
        if os.path.exists(os.path.join(p, SHIPPED)):
            return p
        up = os.path.dirname(p)
        if up == p:
            return None
        p = up


def check_output(out: str, kind: str, inputs=(), inside_ok=()) -> None:
    """One rule for every command's output folder, before any work: ``out`` is not an input, does not
    hold one and does not lie inside one (except under a folder of ``inside_ok``, e.g. a checkpoint's
    ``eval/``); it is not in a shipped or exported checkpoint; and an existing ``out`` is empty or of
    the command's own ``kind`` (a key of :data:`KINDS`: what the command writes there), never a
    comparison, run or evaluation of another command whose files would be replaced or mixed.
    Raises :class:`OutputError` naming the folder and what it is."""
    for i in inputs:
        if inside(i, out):
            raise OutputError(f'--out {out} is or holds the input {i}: write the output to a folder outside it')
        if inside(out, i) and not any(inside(out, ok) for ok in inside_ok):
            raise OutputError(f'--out {out} lies inside the input {i}: write the output to a folder outside it')
    ship = shipped_above(out)
    if ship is not None:
        raise OutputError(f'--out {out} lies inside the shipped checkpoint {ship}, which is only read: write the '
                          'output to a folder outside it (e.g. under runs/)')
    found = kind_of(out)
    if found is not None and found != kind:
        raise OutputError(f'--out {out} is {KINDS[found]}; its files would be replaced or mixed with '
                          f'{KINDS[kind].split(" (")[0]}: choose another folder')


class BadFileError(ValueError):
    """A file the command reads is damaged or is not what it should be; the message names it."""


def read_lines(path: str, what: str = 'JSON lines') -> list[str]:
    """The lines of a text file (UTF-8); one that is not text is a :class:`BadFileError` naming it."""
    try:
        with open(path, encoding='utf-8') as f:
            return f.readlines()
    except UnicodeDecodeError as e:
        raise BadFileError(f'{path} is not text ({what} expected; byte {e.start} cannot be read as UTF-8): '
                           'was it damaged or replaced? Move it away to go on without it') from None


def read_json(path: str, what: str = 'a run folder written by aqm-mjx train') -> dict:
    """The JSON object in ``path``, opened read-only.

    Raises :class:`MissingFileError` when it is absent, :class:`BadFileError` naming the file when
    it is not valid JSON (truncated, edited by hand) or not a JSON object."""
    if not os.path.exists(path):
        raise MissingFileError(f'{path}: no such file (is this {what}?)')
    try:
        with open(path, 'rb') as f:
            obj = json.loads(f.read().decode('utf-8'))
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise BadFileError(f'{path} is not valid JSON ({e}); it is damaged or truncated (is this {what}?)') from None
    if not isinstance(obj, dict):
        raise BadFileError(f'{path} holds a JSON {type(obj).__name__}, not the object {what} writes')
    return obj


def inside(path: str, folder: str) -> bool:
    """Whether ``path`` is ``folder`` or lies under it, once both are resolved (symbolic links
    followed, however the paths are spelled)."""
    p, f = os.path.realpath(path), os.path.realpath(folder)
    return p == f or os.path.commonpath([p, f]) == f


LOCK_NAME = '.aqm-mjx.lock'
_HELD: dict[str, list] = {}  # folder -> [open lock file, depth]: a process may take its own lock again


class LockedError(RuntimeError):
    """A run folder is being written by another process; the message names it."""


@contextlib.contextmanager
def run_lock(folder: str):
    """Hold ``FOLDER/.aqm-mjx.lock`` for the duration: one writer per run folder.

    The lock is an ``flock`` on that file, which the kernel releases when its holder ends in any
    way (``kill -9`` included), so a crashed run never leaves a folder stuck; the file itself
    says who holds it (pid, host, command, since when) for the message a second writer gets. The
    same process may enter the lock again (a pipeline that trains inside its run folder).
    Raises :class:`LockedError` at once when another process holds it.
    """
    created = not os.path.exists(folder)
    check_writable(folder)
    os.makedirs(folder, exist_ok=True)
    key = os.path.realpath(folder)
    if key in _HELD:
        _HELD[key][1] += 1
        try:
            yield
        finally:
            _HELD[key][1] -= 1
        return
    path = os.path.join(folder, LOCK_NAME)
    f = open(path, 'a+')  # pylint: disable=consider-using-with  (held until the block ends)
    try:
        fcntl.flock(f.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        f.seek(0)
        try:
            who = json.loads(f.read() or '{}')
        except ValueError:
            who = {}
        f.close()
        raise LockedError(f'{folder} is in use by another aqm-mjx process ({describe_writer(who)}); '
                          f'wait for it to end or stop it, or choose another --out') from None
    try:
        f.seek(0)
        f.truncate()
        f.write(json.dumps(dict(pid=os.getpid(), host=socket.gethostname(),
                                command=_command(), since=time.strftime('%Y-%m-%d %H:%M:%S'))))
        f.flush()
    except OSError as e:  # a full disk: not even the lock's few bytes fit
        _release(f, folder, path, created)
        raise OutputError(f'cannot write to {folder}: {e.strerror or e}') from None
    _HELD[key] = [f, 1]
    try:
        yield
    finally:
        del _HELD[key]
        _release(f, folder, path, created)


def writer_of(folder: str) -> Optional[dict]:
    """Who holds ``folder``'s lock (``{'pid', 'host', 'command', 'since'}``) when another process is
    writing into it; None when nobody is (or this process is). Creates nothing."""
    path = os.path.join(folder, LOCK_NAME)
    if os.path.realpath(folder) in _HELD or not os.path.exists(path):
        return None
    try:
        with open(path) as f:
            try:
                fcntl.flock(f.fileno(), fcntl.LOCK_SH | fcntl.LOCK_NB)
            except BlockingIOError:
                try:
                    return json.loads(f.read() or '{}') or {'pid': '?'}
                except ValueError:
                    return {'pid': '?'}
            fcntl.flock(f.fileno(), fcntl.LOCK_UN)
    except OSError:
        return None
    return None


def describe_writer(who: dict) -> str:
    """``pid P on HOST, `COMMAND` since T`` of :func:`writer_of`."""
    return f'pid {who.get("pid", "?")} on {who.get("host", "?")}, `{who.get("command", "?")}` since {who.get("since", "?")}'


def _holds_nothing(folder: str) -> bool:
    """Whether ``folder`` holds only the lock, empty files and empty folders (a run that wrote nothing)."""
    for root, _, names in os.walk(folder):
        for n in names:
            p = os.path.join(root, n)
            if not (n == LOCK_NAME and root == folder) and (os.path.islink(p) or os.path.getsize(p) > 0):
                return False
    return True


def _release(f, folder: str, path: str, created: bool) -> None:
    """Unlock; a folder this lock created and nothing was written into is removed (no empty run folder)."""
    try:
        if created and _holds_nothing(folder):
            shutil.rmtree(folder, ignore_errors=True)
    finally:
        try:
            fcntl.flock(f.fileno(), fcntl.LOCK_UN)
        finally:
            try:
                f.close()
            except OSError:  # the unwritten lock line of a full disk
                pass
