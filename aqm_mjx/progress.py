"""Progress you can watch while a jitted chunk runs: a host callback every few dozen control steps.

Inside a program (a ``lax.scan`` over control steps), :func:`tick` calls ``hook(t)`` on the host
after every ``every``-th step and after the last one (``jax.debug.callback`` under a ``lax.cond``
whose predicate depends on the step alone, so that under ``vmap`` it stays one call per step, not
one per environment). On the host, a :class:`ChunkBar` turns those calls into a tqdm bar that
advances inside each chunk:

    bar = ChunkBar(tqdm(total=n_episodes, unit='ep'))
    program = make_rollout(..., progress=bar)         # the hook is compiled into the program
    bar.start(count=256, steps=1000)                  # before each call: the chunk's episodes
    out = program(...)                                # the bar moves every `every` steps
    bar.finish()                                      # exactly `count` further on

A hook's calls may arrive out of order or several times (one per device when the batch is
sharded); the bar only moves forward, to the furthest step reported.
"""

from __future__ import annotations

from typing import Callable, Optional

import jax

EVERY = 50  # control steps between host callbacks
# fractional items while a chunk runs: the count with one decimal
BAR_FORMAT = '{l_bar}{bar}| {n:.1f}/{total_fmt} [{elapsed}<{remaining}, {rate_fmt}{postfix}]'


def tick(hook: Optional[Callable[[jax.Array], None]], t: jax.Array, steps: int, every: int = EVERY) -> None:
    """In a scan body at step ``t`` (0-based, not batched) of ``steps``: call ``hook(t + 1)`` on the
    host after every ``every``-th step and after the last. Nothing when ``hook`` is None."""
    if hook is None:
        return
    done = t + 1
    jax.lax.cond((done % every == 0) | (done == steps), lambda d: jax.debug.callback(hook, d), lambda d: None, done)


class ChunkBar:
    """A host hook that advances a tqdm-like ``bar`` (``update(n)``, ``refresh()``) in proportion to
    the steps done by the current chunk of ``count`` items."""

    def __init__(self, bar):
        self.bar = bar
        self.count, self.steps, self.shown = 0, 1, 0.0
        self.calls = 0  # host callbacks received (the overhead benchmark and the tests read it)

    def start(self, count: int, steps: int) -> None:
        """A chunk of ``count`` items (episodes) of ``steps`` control steps each begins."""
        self.count, self.steps, self.shown = int(count), max(int(steps), 1), 0.0

    def __call__(self, done) -> None:
        self.calls += 1
        target = self.count * min(int(done), self.steps) / self.steps
        if target > self.shown and self.bar is not None:
            self.bar.update(target - self.shown)
            self.shown = target

    def finish(self) -> None:
        """The chunk ended: the bar stands exactly ``count`` items further than at :meth:`start`."""
        if self.bar is not None and self.count > self.shown:
            self.bar.update(self.count - self.shown)
        self.shown = float(self.count)


class Hook:
    """A stable host callback for programs compiled once and run many times: it forwards to
    whatever target is set (a :class:`ChunkBar`, or None for silence), so a cached program can
    drive each run's own bar."""

    def __init__(self):
        self.target: Optional[Callable] = None

    def __call__(self, done) -> None:
        if self.target is not None:
            self.target(done)

