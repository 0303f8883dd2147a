"""Several processes as one JAX program: JAX's multi-controller runtime, started before any other
JAX call.

    processes.start('10.0.0.1:1234', num_processes=2, process_id=0)   # on every process, its own id
    processes.writer()                                                 # True on process 0 alone

Every process runs the same command; ``jax.devices()`` is then every process's devices. The
evaluation runs each process's share of the episode chunks and gathers the outcomes on every process
(``process_allgather``); ``collect`` runs chunk ``i`` on process ``i mod N`` and gathers them
(:func:`gather`); ``compare`` trains seed ``i`` on process ``i mod N``; ``train`` and ``run``
make one data-parallel run, the state replicated and each batch split over every device
(:func:`aqm_mjx.learn.fit.train`). Process 0 alone writes files. :func:`put_global`,
:func:`replicate`, :func:`fetch_global` and :func:`local_copy` move arrays between one process's
host and the devices of all of them.
On CPUs the collectives go through gloo (two processes of one machine, as the tests run it); on GPU
nodes through NCCL. With no argument, :func:`start` lets JAX detect the cluster (SLURM, Open MPI,
...); the launcher (``srun``, ``mpirun`` or a shell loop) is the user's: there is no scheduler here.
"""

from __future__ import annotations

import os
import socket
import sys
import time
from typing import Optional

TIMEOUT_S = 120  # how long a process waits for the coordinator and the others (AQM_MJX_PROCESS_TIMEOUT_S)


def start(coordinator: Optional[str] = None, num_processes: Optional[int] = None, process_id: Optional[int] = None,
          detect: bool = False, timeout_s: Optional[int] = None) -> tuple[int, int]:
    """Join the processes of one run; returns ``(process id, process count)``.

    Args:
        coordinator: ``HOST:PORT`` of process 0's coordination service (every process names the same).
        num_processes: how many processes take part.
        process_id: this process's id, ``0 .. num_processes - 1``.
        detect: none of the three given: let JAX read them from the cluster's environment (SLURM, ...).
        timeout_s: a process that cannot reach the coordinator, or whose partners do not all arrive,
            gives up after this long (default ``AQM_MJX_PROCESS_TIMEOUT_S`` or :data:`TIMEOUT_S`).
    Raises:
        ValueError: only some of the three given, or values out of range (before any JAX call).
        RuntimeError: the coordinator or a partner was not reached; the message names which process
            waited for what.
    """
    given = {'--coordinator': coordinator, '--num-processes': num_processes, '--process-id': process_id}
    if not detect and all(v is None for v in given.values()):
        return 0, 1
    if not detect:
        missing = [k for k, v in given.items() if v is None]
        if missing:
            raise ValueError(f'several processes need --coordinator, --num-processes and --process-id together; '
                             f'missing {", ".join(missing)}')
        if ':' not in str(coordinator) or not str(coordinator).rsplit(':', 1)[1].isdigit():
            raise ValueError(f'--coordinator {coordinator!r}: expected HOST:PORT, e.g. 127.0.0.1:12355')
        if int(num_processes) < 1 or not 0 <= int(process_id) < int(num_processes):
            raise ValueError(f'--process-id {process_id} of --num-processes {num_processes}: expected '
                             f'0 <= id < {num_processes}')
    import jax  # pylint: disable=import-outside-toplevel

    timeout_s = int(timeout_s or os.environ.get('AQM_MJX_PROCESS_TIMEOUT_S', TIMEOUT_S))
    if jax.config.jax_platforms in (None, '', 'cpu') or str(jax.config.jax_platforms).startswith('cpu'):
        jax.config.update('jax_cpu_collectives_implementation', 'gloo')  # CPU processes talk through gloo
    where = 'the cluster\'s coordinator' if detect else f'the coordinator {coordinator}'
    if not detect and int(process_id) != 0:  # XLA aborts the process when it cannot connect: look first
        _wait_for(str(coordinator), timeout_s, f'process {process_id} of {num_processes}')
    elif not detect:
        print(f'process 0 of {num_processes}: coordinating at {coordinator}; waiting up to {timeout_s} s for the '
              'others (XLA ends this process if they do not all come)', file=sys.stderr, flush=True)
    try:
        if detect:
            jax.distributed.initialize(initialization_timeout=timeout_s)
        else:
            jax.distributed.initialize(coordinator_address=coordinator, num_processes=int(num_processes),
                                       process_id=int(process_id), initialization_timeout=timeout_s)
    except Exception as e:  # pylint: disable=broad-except  (XLA's errors carry long status text)
        first = ' '.join(str(e).split())[:300]
        who = 'this process' if detect else f'process {process_id} of {num_processes}'
        raise RuntimeError(f'{who} could not join the run through {where} within {timeout_s} s ({first})') from None
    # the collectives' own connections now, while every process is here: gloo gives up on a partner that
    # comes more than 30 s after the first collective's other side (a process with no chunk to run)
    barrier('start')
    return jax.process_index(), jax.process_count()


def _wait_for(coordinator: str, timeout_s: float, who: str) -> None:
    """Return once ``HOST:PORT`` accepts a connection; a :class:`RuntimeError` naming it after
    ``timeout_s``."""
    host, port = coordinator.rsplit(':', 1)
    end = time.monotonic() + timeout_s
    while True:
        try:
            with socket.create_connection((host.strip('[]'), int(port)), timeout=2.0):
                return
        except OSError as e:
            if time.monotonic() >= end:
                raise RuntimeError(f'{who} could not join the run through the coordinator {coordinator} within '
                                   f'{timeout_s:g} s ({e.strerror or e}): is process 0 running, and is the '
                                   'address its?') from None
            time.sleep(0.5)


def count() -> int:
    """Processes in the run (1 without :func:`start`)."""
    import jax  # pylint: disable=import-outside-toplevel

    return jax.process_count()


def writer() -> bool:
    """Whether this process writes the run's files (process 0)."""
    import jax  # pylint: disable=import-outside-toplevel

    return jax.process_index() == 0


def barrier(name: str) -> None:
    """Wait until every process of the run reaches the barrier ``name`` (nothing with one process).
    A partner that ended meanwhile is :func:`lost`'s :class:`RuntimeError`, naming the barrier."""
    import jax  # pylint: disable=import-outside-toplevel

    if jax.process_count() == 1:
        return
    from jax.experimental import multihost_utils  # pylint: disable=import-outside-toplevel

    try:
        multihost_utils.sync_global_devices(name)
    except Exception as e:  # pylint: disable=broad-except  (XLA's and gloo's errors carry long status text)
        raise lost(f'waiting for the others at {name!r}', e) from None


def lost(what: str, e: BaseException) -> RuntimeError:
    """One line for a collective that failed because a partner ended (XLA's and gloo's long status
    text cut to its first 300 characters), saying what this process was doing and, of two, which
    partner it lost. With more, gloo's error does not say which ended (the coordination service
    learns it only at its heartbeat timeout, tens of seconds later): the line says "a partner"."""
    import jax  # pylint: disable=import-outside-toplevel

    me, n = jax.process_index(), jax.process_count()
    other = f'process {1 - me}' if n == 2 else 'a partner'
    return RuntimeError(f'process {me} of {n} lost {other} while {what} ({" ".join(str(e).split())[:300]}); run the '
                        'same command again on every process to resume')


def gather(tree, what: str):
    """Every process's ``tree`` of host arrays, stacked: each leaf ``[processes, ...]``, on every
    process (each process passes the same shapes; booleans travel as bytes and come back as
    booleans). With one process, each leaf with a leading axis of 1. ``what``: what this process was
    doing, for the one line of :func:`lost` when a partner ended."""
    import jax  # pylint: disable=import-outside-toplevel
    import numpy as np  # pylint: disable=import-outside-toplevel

    tree = jax.tree.map(np.asarray, tree)
    if jax.process_count() == 1:
        return jax.tree.map(lambda x: x[None], tree)
    from jax.experimental import multihost_utils  # pylint: disable=import-outside-toplevel

    sent = jax.tree.map(lambda x: x.astype(np.uint8) if x.dtype == bool else x, tree)
    try:
        got = multihost_utils.process_allgather(sent)
    except Exception as e:  # pylint: disable=broad-except  (XLA's and gloo's errors carry long status text)
        raise lost(what, e) from None
    return jax.tree.map(lambda g, x: np.asarray(g).astype(x.dtype), got, tree)


def from_writer(tree, what: str):
    """Process 0's ``tree`` (host or replicated arrays) as host arrays on every process; the others
    pass a template of the same shapes and dtypes. With one process, ``tree``'s host copy."""
    import jax  # pylint: disable=import-outside-toplevel

    if jax.process_count() == 1:
        return local_copy(tree)
    from jax.experimental import multihost_utils  # pylint: disable=import-outside-toplevel

    try:
        return multihost_utils.broadcast_one_to_all(local_copy(tree))
    except Exception as e:  # pylint: disable=broad-except
        raise lost(f'receiving {what} from process 0', e) from None


def share(n: int) -> list[int]:
    """This process's items of ``n`` split over the processes, item ``i`` to process ``i mod count``
    (every item with one process alone: all of them)."""
    import jax  # pylint: disable=import-outside-toplevel

    return [i for i in range(n) if i % jax.process_count() == jax.process_index()]


def check_backend(backend: str) -> None:
    """Refuse OGBench's host-stepped environments (``backend='ogbench'``) when several processes run."""
    import jax  # pylint: disable=import-outside-toplevel

    if backend == 'ogbench' and jax.process_count() > 1:
        raise ValueError("several processes evaluate in MJX, each running its share of the episodes on its own "
                         "devices; drop --backend ogbench (OGBench's environments step on one host)")


# ------------------------------------------------------------------ arrays over every process's devices
def put_global(x, sharding):
    """A global array from one host array that every process holds (single- and multi-host)."""
    import jax  # pylint: disable=import-outside-toplevel
    import numpy as np  # pylint: disable=import-outside-toplevel

    x = np.asarray(x)
    return jax.make_array_from_callback(x.shape, sharding, lambda index: x[index])


def replicate(tree, sharding):
    """``tree``'s arrays replicated on ``sharding``'s devices: ``device_put`` in one process; with
    several, each leaf built from this process's host copy (every process holds the same values),
    since one process cannot place arrays on another's devices."""
    import jax  # pylint: disable=import-outside-toplevel
    import numpy as np  # pylint: disable=import-outside-toplevel

    if jax.process_count() == 1:
        return jax.device_put(tree, sharding)
    return jax.tree.map(lambda x: put_global(np.asarray(x), sharding), tree)


def fetch_global(x):
    """A (sharded) array as one host array on every process."""
    import jax  # pylint: disable=import-outside-toplevel
    import numpy as np  # pylint: disable=import-outside-toplevel

    if jax.process_count() > 1:
        from jax.experimental import multihost_utils  # pylint: disable=import-outside-toplevel

        return np.asarray(multihost_utils.process_allgather(x, tiled=True))
    return np.asarray(jax.device_get(x))


def local_copy(tree):
    """Host arrays of a pytree of replicated global arrays: this process's own replica of each leaf
    (no communication; every process holds the same values). Host and single-process arrays pass
    through ``device_get``."""
    import jax  # pylint: disable=import-outside-toplevel
    import numpy as np  # pylint: disable=import-outside-toplevel

    if jax.process_count() == 1:  # one batched transfer, as before several processes existed
        return jax.device_get(tree)

    def one(x):
        if isinstance(x, jax.Array) and not x.is_fully_addressable:
            return np.asarray(x.addressable_data(0))
        return np.asarray(jax.device_get(x))

    return jax.tree.map(one, tree)
