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

    COMPILING = 'compiling the program (first chunk)'

    def __init__(self, bar):
        self.bar = bar
        self.count, self.steps, self.shown, self.base = 0, 1, 0.0, 0.0
        self.calls = 0  # host callbacks received (the overhead benchmark and the tests read it)
        self.chunks = 0
        self.noted = False  # the bar says that the first chunk compiles, until its first callback

    def _note(self, text: str) -> None:
        if hasattr(self.bar, 'set_postfix_str'):
            self.bar.set_postfix_str(text, refresh=True)
        self.noted = bool(text)

    def start(self, count: int, steps: int) -> None:
        """A chunk of ``count`` items (episodes) of ``steps`` control steps each begins (the first
        one shows :data:`COMPILING` on the bar until it reports its first steps)."""
        if self.chunks == 0:
            self._note(self.COMPILING)
        self.chunks += 1
        self.count, self.steps, self.shown = int(count), max(int(steps), 1), 0.0
        # chunks end on whole items: the bar's position is an integer up to float error
        self.base = float(round(getattr(self.bar, 'n', 0.0) or 0.0))

    def _advance(self, to: float) -> None:
        """Move the bar to ``to`` items into the current chunk. With a tqdm bar the step is taken from
        the bar's own position, so float error does not add up over chunks, and never past its total
        (tqdm warns 'clamping frac to range [0, 1]' when it is)."""
        if self.bar is not None:
            n = getattr(self.bar, 'n', None)
            inc = to - self.shown if n is None else (self.base + to) - n
            total = getattr(self.bar, 'total', None)
            if n is not None and total is not None:
                inc = min(inc, total - n)
            if inc > 0:
                self.bar.update(inc)
        self.shown = to

    def __call__(self, done) -> None:
        self.calls += 1
        if self.noted:  # the program runs: it has compiled
            self._note('')
        target = self.count * min(int(done), self.steps) / self.steps
        if target > self.shown:
            self._advance(target)

    def finish(self) -> None:
        """The chunk ended: the bar stands exactly ``count`` items further than at :meth:`start`."""
        if self.noted:
            self._note('')
        self._advance(float(self.count))


class Hook:
    """A stable host callback for programs compiled once and run many times: it forwards to
    whatever target is set (a :class:`ChunkBar`, or None for silence), so a cached program can
    drive each run's own bar."""

    def __init__(self):
        self.target: Optional[Callable] = None

    def __call__(self, done) -> None:
        if self.target is not None:
            self.target(done)

