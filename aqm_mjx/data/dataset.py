"""Datasets: OGBench ``.npz`` files in and out and a device-resident dataset (goal-conditioned
batches are drawn from it by :mod:`aqm_mjx.data.goals`).

File format (OGBench's, written with ``np.savez_compressed``): ``observations [N, D]`` float32,
``actions [N, A]`` float32, ``terminals [N]`` bool (True at the last state of each trajectory),
optionally ``qpos [N, nq]`` and ``qvel [N, nv]``. As in ``ogbench.utils.load_dataset``, the last
state of a trajectory is not the source of a transition. Files are read with
``allow_pickle=False``; every problem found raises :class:`DatasetError` naming it.

On device the dataset is kept *compact*: all N states once, ``valid_index`` listing the states
that have a successor ``t + 1`` in the same trajectory, and ``traj_end[t]`` the index of the last state
of ``t``'s trajectory, which is what keeps every sampled goal inside its trajectory.
"""

from __future__ import annotations

import hashlib
import os
import tempfile
import zipfile
import zlib
from typing import Optional

import jax
import numpy as np
from flax import struct

REQUIRED = ('observations', 'actions', 'terminals')
OPTIONAL = ('qpos', 'qvel')


class DatasetError(ValueError):
    """A dataset file or array that cannot be used; the message says what is wrong."""


# ---------------------------------------------------------------------------------------------- files
def _check_real(a, key: str, name: str, bool_ok: bool = False) -> None:
    """Real numbers only: complex values would lose their imaginary part, strings and objects are no data."""
    dt = np.asarray(a).dtype
    if not (np.issubdtype(dt, np.floating) or np.issubdtype(dt, np.integer) or (bool_ok and dt == np.bool_)):
        raise DatasetError(f'{name}: {key} has dtype {dt}; expected real numbers (float or int'
                           f'{" or bool" if bool_ok else ""})')


def validate(data: dict, obs_size: Optional[int] = None, action_size: Optional[int] = None, name: str = 'dataset') -> None:
    """Check raw arrays in OGBench's file layout. Raises :class:`DatasetError`."""
    for k in REQUIRED:
        if k not in data:
            raise DatasetError(f'{name}: missing key {k!r} (found {sorted(data)})')
    for k in REQUIRED + OPTIONAL:
        if k in data and np.ndim(data[k]) == 0:
            raise DatasetError(f'{name}: {k} is a single value (a 0-d array); expected one row per state')
    obs, act, term = data['observations'], data['actions'], data['terminals']
    n = len(term)
    if n == 0:
        raise DatasetError(f'{name}: empty (0 states)')
    if obs.ndim != 2 or act.ndim != 2 or term.ndim != 1:
        raise DatasetError(f'{name}: expected observations [N, D], actions [N, A], terminals [N]; got shapes '
                           f'{obs.shape}, {act.shape}, {term.shape}')
    for k in REQUIRED + OPTIONAL:
        if k in data and len(data[k]) != n:
            raise DatasetError(f'{name}: {k} has {len(data[k])} rows but terminals has {n}')
    if obs_size is not None and obs.shape[1] != obs_size:
        raise DatasetError(f'{name}: observations are {obs.shape[1]}-d but the environment expects {obs_size}')
    if action_size is not None and act.shape[1] != action_size:
        raise DatasetError(f'{name}: actions are {act.shape[1]}-d but the environment expects {action_size}')
    _check_real(term, 'terminals', name, bool_ok=True)
    for k in ('observations', 'actions') + OPTIONAL:
        if k in data:
            a = data[k]
            _check_real(a, k, name)
            bad = ~np.isfinite(a)
            if bad.any():
                row = int(np.argwhere(bad)[0][0])
                raise DatasetError(f'{name}: {k} contains NaN or inf ({int(bad.sum())} values, first at row {row})')
    if not term.any():
        raise DatasetError(f'{name}: no trajectory end is marked (terminals is all False)')
    if not bool(term[-1]):
        raise DatasetError(f'{name}: the last state is not marked terminal; the final trajectory is cut')


def _declared(f, key: str) -> str:
    """What the ``.npy`` header of ``key`` in the open archive ``f`` declares (shape and type)."""
    try:
        with f.zip.open(key + '.npy') as member:
            version = np.lib.format.read_magic(member)
            read = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
            shape, _, dtype = read(member)
        return f'shape {shape} of {dtype} ({np.prod(shape, dtype=float) * dtype.itemsize / 2 ** 30:,.0f} GiB)'
    except Exception:  # pylint: disable=broad-except
        return 'an array'


def read_ogbench(path: str, obs_size: Optional[int] = None, action_size: Optional[int] = None,
                 add_info: bool = True) -> dict:
    """Read an OGBench ``.npz`` file as numpy arrays (one read, no extra copies).

    Args:
        path: the ``.npz`` file.
        obs_size, action_size: expected widths (e.g. ``env.obs_size``), checked when given.
        add_info: also read ``qpos``/``qvel`` when present.
    Returns:
        dict with ``observations`` float32 ``[N, D]``, ``actions`` float32 ``[N, A]``,
        ``terminals`` bool ``[N]`` (and ``qpos``, ``qvel``).
    """
    if not os.path.exists(path):
        raise DatasetError(f'{path}: no such file')
    if os.path.isdir(path):
        raise DatasetError(f'{path}: a folder, not an .npz file')
    try:
        with open(path, 'rb') as fh:
            head = fh.read(4)
    except OSError as e:
        raise DatasetError(f'{path}: cannot be read ({e.strerror or e})') from None
    if not head:
        raise DatasetError(f'{path}: empty file (0 bytes); was it cut short while being written or copied?')
    if head not in (b'PK\x03\x04', b'PK\x05\x06'):
        raise DatasetError(f'{path}: not an .npz archive (a zip file starts with PK; this one starts with {head!r})')
    try:
        f = np.load(path, allow_pickle=False)
    except (zipfile.BadZipFile, OSError, ValueError, EOFError) as e:
        raise DatasetError(f'{path}: damaged .npz archive ({type(e).__name__}: {e})') from None
    if not isinstance(f, np.lib.npyio.NpzFile):
        raise DatasetError(f'{path}: expected an .npz archive of named arrays, got a single array')
    out = {}
    with f:
        keys = REQUIRED + (OPTIONAL if add_info else ())
        for k in keys:
            if k not in f.files:
                if k in REQUIRED:
                    raise DatasetError(f'{path}: missing key {k!r} (found {sorted(f.files)})')
                continue
            try:
                a = f[k]
            except ValueError as e:
                if 'pickle' in str(e):  # object arrays need pickle, which we never allow
                    raise DatasetError(f'{path}: {k} is an object array (it would need pickle to load); '
                                       'save plain numeric arrays') from None
                raise DatasetError(f'{path}: {k} is damaged ({e})') from None
            except (zipfile.BadZipFile, zlib.error, EOFError, OSError) as e:  # flipped or missing bytes
                raise DatasetError(f'{path}: {k} is damaged ({type(e).__name__}: {e})') from None
            except MemoryError:  # a header declaring more than the machine holds (damaged, or not a dataset)
                raise DatasetError(f'{path}: {k} declares {_declared(f, k)}, more than this machine\'s memory '
                                   'holds; is the file damaged?') from None
            _check_real(a, k, path, bool_ok=k == 'terminals')
            a = a.astype(bool if k == 'terminals' else np.float32, copy=False)
            out[k] = a
    validate(out, obs_size, action_size, name=path)
    return out


def write_ogbench(path: str, data: dict) -> None:
    """Write arrays as an OGBench ``.npz`` (terminals as bool). Atomic: a failure never leaves a
    partial file, and an existing file is replaced only once the new one is complete."""
    validate(data, name=path)
    arrays = {k: np.asarray(data[k]) for k in REQUIRED + OPTIONAL if k in data}
    arrays['terminals'] = arrays['terminals'].astype(bool)
    for k in ('observations', 'actions') + OPTIONAL:
        if k in arrays:
            arrays[k] = arrays[k].astype(np.float32, copy=False)
    folder = os.path.dirname(os.path.abspath(path))
    os.makedirs(folder, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=folder, suffix='.npz.tmp')
    try:
        with os.fdopen(fd, 'wb') as fh:
            np.savez_compressed(fh, **arrays)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # as open() would create it (mkstemp makes 0600)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.remove(tmp)
        raise


def fingerprint(data: dict) -> str:
    """The SHA-256 (hex) of a dataset's arrays: over the names in sorted order, each name, dtype,
    shape and C-order bytes. Two files hold the same data exactly when their fingerprints agree,
    whatever their compression or key order; ``aqm-mjx compare`` records it and refuses a folder
    whose data changed under it."""
    h = hashlib.sha256()
    for k in sorted(data):
        a = np.ascontiguousarray(np.asarray(data[k]))
        h.update(f'{k}\0{a.dtype.str}\0{a.shape}\0'.encode())
        h.update(a.tobytes())
    return h.hexdigest()


def val_path(path: str) -> str:
    """OGBench's validation twin: ``x.npz`` -> ``x-val.npz``."""
    return path[:-4] + '-val.npz' if path.endswith('.npz') else path + '-val'


def transitions(data: dict) -> dict:
    """``ogbench.utils.load_dataset(compact_dataset=False)``'s view of raw arrays (for checks)."""
    term = data['terminals'].astype(np.float32)
    ob_mask = (1.0 - term).astype(bool)
    next_mask = np.concatenate([[False], ob_mask[:-1]])
    new_term = np.concatenate([term[1:], [1.0]])
    return dict(observations=data['observations'][ob_mask], actions=data['actions'][ob_mask],
                next_observations=data['observations'][next_mask], terminals=new_term[ob_mask].astype(np.float32))


# ---------------------------------------------------------------------------------------------- device
@struct.dataclass
class Dataset:
    """A compact dataset on device.

    Attributes:
        observations: ``[N, D]`` every state once.
        actions: ``[N, A]`` (the last state's action has no successor and is never sampled).
        traj_end: int32 ``[N]`` index of the last state of ``t``'s trajectory.
        valid_index: int32 ``[M]`` transition sources: the states whose ``t + 1`` is the next state of
            the same trajectory (every state but the last of each trajectory).
    """

    observations: jax.Array
    actions: jax.Array
    traj_end: jax.Array
    valid_index: jax.Array

    @property
    def size(self) -> int:
        return int(self.observations.shape[0])


def trajectory_ends(terminals) -> np.ndarray:
    """int32 ``[N]``: for each state, the index of the last state of its trajectory (``terminals [N]``,
    the last state terminal, as :func:`validate` checks)."""
    ends = np.flatnonzero(np.asarray(terminals).astype(bool, copy=False))
    return ends[np.searchsorted(ends, np.arange(len(terminals)))].astype(np.int32)


def to_device(data: dict, device=None) -> Dataset:
    """Put raw arrays (from :func:`read_ogbench` or a collector) on device, one copy each."""
    validate(data)
    term = np.asarray(data['terminals']).astype(bool, copy=False)
    traj_end = trajectory_ends(term)
    sources = np.flatnonzero(~term).astype(np.int32)
    if len(sources) == 0:
        raise DatasetError('dataset has no transitions (every state is a trajectory end)')
    put = (lambda a: jax.device_put(a, device)) if device is not None else jax.device_put
    return Dataset(observations=put(np.asarray(data['observations'], np.float32)),
                   actions=put(np.asarray(data['actions'], np.float32)), traj_end=put(traj_end),
                   valid_index=put(sources))


def infer_env(path: str) -> tuple[str, Optional[str]]:
    """``.../antmaze-large-navigate-v0.npz`` -> ``('antmaze-large', 'navigate')`` (OGBench's file names)."""
    from aqm_mjx.envs import parse_name  # pylint: disable=import-outside-toplevel

    base = os.path.basename(path)
    parts = (base[:-4] if base.endswith('.npz') else base).split('-')
    name = '-'.join(parts[:2])
    try:
        parse_name(name)
    except ValueError:
        raise ValueError(f'cannot infer the environment from {path!r}; pass --env (e.g. antmaze-medium)') from None
    style = parts[2] if len(parts) > 2 and parts[2] in ('navigate', 'stitch', 'explore') else None
    return name, style


def check_env_name(path: str, env_name: str) -> None:
    """Refuse a file whose OGBench name says another maze than ``env_name``
    (``pointmaze-medium-navigate-v0.npz`` with ``--env pointmaze-large``); a file named otherwise
    is not judged by its name."""
    try:
        named, _ = infer_env(path)
    except ValueError:
        return
    if named != env_name:
        raise DatasetError(f'{path} is named for {named}, not {env_name}: pass --env {named} (or rename the file '
                           'if its name is wrong)')
