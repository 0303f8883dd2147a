"""How much memory a command's batch needs, estimated before anything is compiled or allocated.

A batch that cannot fit is refused up front with the option to lower named, instead of failing
after minutes of compilation with an allocator's traceback (``std::bad_alloc``,
``_ArrayMemoryError``). The estimates are coarse upper bounds (a small factor over the arrays
the command holds at once); they catch sizes that are wrong by orders of magnitude, not the last
10%.
"""

from __future__ import annotations

import dataclasses
import os
from typing import Optional

#: headroom over the arrays a jitted step holds (its inputs, outputs and temporaries)
FACTOR = 4


class MemoryEstimateError(ValueError):
    """A batch that will not fit in memory; the message names the option to lower."""


def available() -> tuple[int, str]:
    """``(bytes, where)``: memory available to the default JAX device (its allocator's limit on an
    accelerator, the host's available memory on a CPU)."""
    import jax  # pylint: disable=import-outside-toplevel

    dev = jax.devices()[0]
    if dev.platform != 'cpu':
        stats = dev.memory_stats() or {}
        if stats.get('bytes_limit'):
            return int(stats['bytes_limit']) - int(stats.get('bytes_in_use', 0)), f'{dev.platform} device'
    return host_available(), 'host'


def host_available() -> int:
    """Bytes of host memory available (``MemAvailable``; free pages where /proc/meminfo is absent)."""
    try:
        with open('/proc/meminfo') as f:
            for line in f:
                if line.startswith('MemAvailable:'):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return os.sysconf('SC_AVPHYS_PAGES') * os.sysconf('SC_PAGE_SIZE')


def check(need_bytes: float, what: str, option: str, where: Optional[tuple[int, str]] = None) -> None:
    """Refuse ``what`` when ``need_bytes`` exceed the memory available, naming ``option``."""
    free, place = where or available()
    if need_bytes > free:
        raise MemoryEstimateError(f'{what} needs about {_size(need_bytes)} of {place} memory; {_size(free)} are '
                                  f'available: lower {option}')


def _size(n: float) -> str:
    return f'{n / 2 ** 30:.1f} GiB' if n >= 2 ** 30 else f'{n / 2 ** 20:.0f} MiB'


_STATE_BYTES: dict = {}  # (environment name, physics) -> bytes of one state (a trace takes about 2 s)


def env_state_bytes(env) -> int:
    """Bytes of one environment's state (traced, not run: :func:`jax.eval_shape` of its reset; once
    per environment name, so that every checkpoint or method of one environment reuses it)."""
    import jax  # pylint: disable=import-outside-toplevel
    import jax.numpy as jnp  # pylint: disable=import-outside-toplevel

    name = (getattr(env, 'name', None) or id(env), getattr(env, 'physics', None))  # contact caps size a state
    if name not in _STATE_BYTES:
        shapes = jax.eval_shape(env.reset, jax.random.PRNGKey(0), jnp.int32(1))
        _STATE_BYTES[name] = int(sum(x.size * x.dtype.itemsize for x in jax.tree.leaves(shapes)))
    return _STATE_BYTES[name]


#: the largest chunk an automatic choice makes (past it a GPU's throughput no longer grows, RESULTS 7.3)
MAX_AUTO_ENVS = 65536


def fitting_envs(env, where: Optional[tuple[int, str]] = None, cap: int = MAX_AUTO_ENVS) -> int:
    """The environments per evaluation chunk that the memory estimate allows (``protocol.envs = 0``):
    the largest power of two whose states, with :data:`FACTOR` headroom twice over (the agent's
    state and the step's temporaries beside the environments'), fit in the memory available, at
    most ``cap``."""
    free, _ = where or available()
    per_env = env_state_bytes(env) * FACTOR * 2
    n = max(1, int(free // per_env))
    return int(min(cap, 1 << (n.bit_length() - 1)))


def training_bytes(cfg, obs_size: int, action_size: int, method=None) -> int:
    """One update: activations per sample, every MLP width in the config (fields named ``*hidden*``)
    and the inputs, forward and backward, for a few networks; with ``method`` (its registry entry)
    also the training state (parameters and optimiser moments, from :func:`jax.eval_shape` of its
    ``init``: traced, nothing allocated), twice (the new state beside the old), and every layer's
    output width, so that a size field (``n_components``, ``latent``, ...) is counted too."""
    widths = sum(sum(v) for f in dataclasses.fields(cfg) if 'hidden' in f.name
                 for v in [getattr(cfg, f.name)] if isinstance(v, tuple))
    state = 0
    if method is not None:
        state, outputs = learner_state(method, cfg, obs_size, action_size)
        widths += outputs
    return int(FACTOR * (2 * state + 4 * 2 * cfg.batch_size * (widths + 3 * obs_size + action_size) * 4))


def learner_state(method, cfg, obs_size: int, action_size: int) -> tuple[int, int]:
    """``(bytes, output widths)`` of a method's training state: the bytes of every array of its
    ``init`` and the summed last dimension of its 2-d arrays (a dense layer's outputs), traced with
    :func:`jax.eval_shape`."""
    import jax  # pylint: disable=import-outside-toplevel

    learner = method.make(cfg, obs_size, action_size)
    leaves = jax.tree.leaves(jax.eval_shape(learner.init, jax.random.PRNGKey(0)))
    return (int(sum(x.size * x.dtype.itemsize for x in leaves)),
            int(sum(x.shape[-1] for x in leaves if len(x.shape) == 2)))


def size_fields(cfg) -> list[str]:
    """The fields of a training config that size its networks (widths and integer sizes), as
    ``--set`` names: what to lower when an update does not fit."""
    loop = {'steps', 'batch_size', 'updates_per_call', 'log_every', 'checkpoint_every', 'keep', 'seed'}
    return [f.name for f in dataclasses.fields(cfg) if f.name not in loop
            and (('hidden' in f.name and isinstance(getattr(cfg, f.name), tuple))
                 or f.name in ('n_components', 'component_size', 'latent', 'rep_dim'))]


def check_training(method, cfg, obs_size: int, action_size: int, seeds: int = 1) -> None:
    """Refuse a training run whose update (``seeds`` of them vmapped) cannot fit, naming the batch and
    the config's size fields, before the data are read or anything is compiled."""
    need = seeds * training_bytes(cfg, obs_size, action_size, method)
    what = f'an update of batch {cfg.batch_size:,} with its networks' + (f' for {seeds} seeds' if seeds > 1 else '')
    check(need, what, '--set batch_size or a network size (--set ' + ', '.join(size_fields(cfg)) + ')'
          + (' or --seeds' if seeds > 1 else ''))
