"""A training run's folder: what ``config.json`` records (method, config, shapes, the data's path and
fingerprint), the checks before a run continues in a folder (same method, config and data, and a
config.json that agrees with the checkpoints beside it), and :func:`load`, the trained method back.

    method, cfg, meta = folder.read_meta('runs/medium/train')
    folder.checkpoint_steps('runs/medium/train')        # [5000, 10000, ...]
"""

from __future__ import annotations

import json
import os
from typing import Any, NamedTuple, Optional

import jax
import numpy as np

from aqm_mjx import files
from aqm_mjx.data import dataset as ds_io
from aqm_mjx.learn import checkpoint as ckpt
from aqm_mjx.interface import Agent
from aqm_mjx.learn import methods
from aqm_mjx.learn.learner import Learner

FORMAT = 'aqm_mjx.train/1'


class Trained(NamedTuple):
    """A trained method: its entry, config, learner, state and where it came from."""

    method: str
    config: Any
    learner: Learner
    state: Any
    step: int
    meta: dict

    @property
    def params(self):
        return self.learner.params(self.state)

    @property
    def agent(self) -> Agent:
        return self.learner.agent(self.params)


def meta_of(method: str, cfg, obs_size: int, action_size: int, dataset_path: Optional[str],
            data_sha256: Optional[str] = None) -> dict:
    """What ``config.json`` (and every checkpoint) records of a run."""
    return dict(method=method, config=cfg.to_dict(), obs_size=int(obs_size), action_size=int(action_size),
                dataset=dataset_path, data_sha256=data_sha256, format=FORMAT)


def fingerprint(data: dict) -> str:
    """The training arrays' fingerprint (:func:`aqm_mjx.data.dataset.fingerprint`) that config.json records,
    of the arrays as a file read back holds them (``terminals`` as bool, whatever a caller's dict held:
    a run trained from a dict resumes with the file written from it)."""
    arrays = {k: data[k] for k in ('observations', 'actions', 'terminals') if k in data}
    if 'terminals' in arrays:
        arrays['terminals'] = np.asarray(arrays['terminals']).astype(bool)
    return ds_io.fingerprint(arrays)


def check_same_data(out: str, saved: dict, data_sha256: str, dataset_path: Optional[str]) -> None:
    """Refuse to resume the run in ``out`` (its ``config.json`` ``saved``) on other data: the
    fingerprint (:func:`aqm_mjx.data.dataset.fingerprint`) must match the one recorded; a run recorded
    before fingerprints must be given the same file."""
    given = dataset_path or 'the data given'
    if saved.get('data_sha256'):
        if saved['data_sha256'] != data_sha256:
            raise ValueError(f'{out} was trained on other data ({saved.get("dataset")}, sha256 '
                             f'{saved["data_sha256"][:16]}...) than {given} (sha256 {data_sha256[:16]}...): resume '
                             'it with its own dataset, or start a new --out')
    elif saved.get('dataset') and dataset_path and os.path.realpath(saved['dataset']) != os.path.realpath(dataset_path):
        raise ValueError(f'{out} was trained on {saved["dataset"]} (its config.json records no fingerprint to '
                         f'compare); resume it with that file, not {dataset_path}')


def check_resume_request(out: str, method: Optional[str], cfg) -> None:
    """Refuse a ``--resume`` whose options (method ``method``, config ``cfg`` built from the options
    given; None: not given) differ from the saved run's, naming every field; a larger ``steps``
    extends the run and is not a difference."""
    saved_method, saved_cfg, meta = read_meta(out)
    diff = []
    if method is not None and method != saved_method.name:
        diff.append(f'method: {saved_method.name!r} vs {method!r}')
    elif cfg is not None:
        a, b = saved_cfg.to_dict(), cfg.to_dict()
        diff += [f'{k}: {a.get(k)!r} vs {b.get(k)!r}' for k in sorted(set(a) | set(b))
                 if k != 'steps' and a.get(k) != b.get(k)]
    if diff:
        raise ValueError(f'--resume continues {out} with its saved settings; these options differ from them '
                         f'(saved vs given): {"; ".join(diff)}. Drop them to continue (--steps may extend it), '
                         'or start a new --out')


def read_meta(out: str) -> tuple[methods.Method, Any, dict]:
    """``(method entry, config, meta)`` of a run folder's ``config.json``; a damaged or edited file
    is an error that names the file and the field."""
    path = os.path.join(out, 'config.json')
    meta = files.read_json(path)
    return parse_meta(meta, path)


def parse_meta(meta, where: str) -> tuple[methods.Method, Any, dict]:
    if not isinstance(meta, dict):
        raise ValueError(f'{where}: expected a JSON object, not {type(meta).__name__}')
    missing = [k for k in ('config', 'obs_size', 'action_size') if k not in meta]
    if missing:
        raise ValueError(f'{where}: no {", ".join(map(repr, missing))} (is this a run folder written by aqm-mjx '
                         'train?)')
    for k in ('obs_size', 'action_size'):
        if isinstance(meta[k], bool) or not isinstance(meta[k], int) or meta[k] < 1:
            raise ValueError(f'{where}: {k} must be an integer >= 1; got {meta[k]!r}')
    try:
        method = methods.get(meta.get('method', 'aqm'))
        return method, method.from_dict(meta['config']), meta
    except (TypeError, ValueError) as e:
        raise ValueError(f'{where}: {e}') from None


def meta_differences(a: dict, b: dict, ignore: tuple = ('steps',)) -> list[str]:
    """Fields in which two run metas (``config.json`` and a checkpoint's) differ, as
    ``'field: A vs B'`` (the config's fields flattened beside method and shapes)."""
    def flat(m):
        cfg = parse_meta(m, 'meta')[1].to_dict()
        return {'method': m.get('method', 'aqm'), 'obs_size': m['obs_size'], 'action_size': m['action_size'], **cfg}

    fa, fb = flat(a), flat(b)
    return [f'{k}: {fa.get(k)!r} vs {fb.get(k)!r}' for k in sorted(set(fa) | set(fb))
            if k not in ignore and fa.get(k) != fb.get(k)]


def check_resumable(out: str, method: str, cfg, obs_size: int, action_size: int) -> None:
    """Refuse to continue the run in ``out`` under another config: every differing field is named.
    A larger ``steps`` extends the run; a smaller one than its newest checkpoint is refused. Does
    nothing when ``out`` holds no checkpoint."""
    done = checkpoint_steps(out)
    if not done:
        return
    _, _, meta = read_meta(out)
    diff = meta_differences(meta, meta_of(method, cfg, obs_size, action_size, None))
    if diff:
        raise ValueError(f'{out} holds a run with other settings (saved vs asked): {"; ".join(diff)}. Choose '
                         f'another --out, or drop the changes to continue it')
    if cfg.steps < max(done):
        raise ValueError(f'{out} is trained to step {max(done)}, past the {cfg.steps} asked for; ask for '
                         f'at least {max(done)} updates (train --steps, run --set train.steps) or choose another --out')


def check_against_checkpoint(out: str, meta: dict, saver: ckpt.Checkpointer, step: Optional[int] = None) -> None:
    """Refuse a ``config.json`` that disagrees with the config saved inside checkpoint ``step``
    (default: the newest), naming every differing field. A checkpoint whose config cannot be read
    is left to :meth:`~aqm_mjx.learn.checkpoint.Checkpointer.restore` (it falls back)."""
    steps = saver.steps() if step is None else [step]
    if not steps:
        return
    try:
        saved = saver.saved_meta(steps[-1])
    except Exception:  # pylint: disable=broad-except  (a torn checkpoint: restore decides)
        return
    diff = meta_differences(meta, saved)
    if diff:
        raise ValueError(f'{out}/config.json disagrees with the config saved in checkpoint {steps[-1]} '
                         f'(config.json vs checkpoint): {"; ".join(diff)}. Was config.json edited? The '
                         'checkpoint\'s copy is what the parameters were trained with')


def trim_metrics(path: str, step: int) -> None:
    """Keep the metric lines up to ``step`` (a resumed run re-logs what came after its checkpoint)."""
    if not os.path.exists(path):
        return
    def keep(line: str) -> bool:
        try:
            return json.loads(line).get('step', 0) <= step
        except ValueError:  # a line torn by a kill during its write
            return False

    lines = [ln for ln in files.read_lines(path, "a run's metrics, one JSON object a line") if ln.strip() and keep(ln)]
    files.write_text(path, ''.join(lines))


def checkpoint_steps(out: str) -> list[int]:
    """Steps of the finished checkpoints in a run folder (empty when there is none)."""
    if not os.path.isdir(os.path.join(out, 'checkpoints')):
        return []
    saver = ckpt.Checkpointer(out, keep=None, create=False)
    try:
        return saver.steps()
    finally:
        saver.close()


def load(out: str, step: Optional[int] = None, log=print) -> Trained:
    """A run folder for evaluation: its ``config.json`` and the newest readable checkpoint (one whose
    arrays are finite and match the digest saved with them; a newer one that is not is named in a
    warning line). Raises :class:`~aqm_mjx.learn.checkpoint.CheckpointError` when none is."""
    method, cfg, meta = read_meta(out)
    writer = files.writer_of(out)
    if writer:  # its checkpoints come and go (keep) while they are read
        log(f'warning: {out} is being trained by another process ({files.describe_writer(writer)}); reading its '
            'newest checkpoint now')
    saver = ckpt.Checkpointer(out, keep=None, create=False)
    try:
        check_against_checkpoint(out, meta, saver, step)
        learner = method.make(cfg, meta['obs_size'], meta['action_size'])
        template = learner.init(jax.random.PRNGKey(0))
        quiet_log = (lambda *_: None) if writer else log  # a step the writer deleted is not damage
        s, state, _ = saver.restore(template, step=step, log=quiet_log)  # non-finite or damaged: the previous one
    except ckpt.CheckpointError as e:
        if writer:
            raise ckpt.CheckpointError(f'no checkpoint of {out} could be read while another process trains into '
                                       f'it ({files.describe_writer(writer)}): wait for it to end, or copy the '
                                       'folder and evaluate the copy') from None
        raise
    finally:
        saver.close()
    return Trained(method.name, cfg, learner, state, s, meta)
