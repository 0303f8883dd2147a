"""Budgets in the controller's own time: what the leg log of an evaluation says about how long the
agent really takes per leg, and the budget settings that cut a traversable leg at a chosen rate.

Every completed leg of an episode is logged by the agent (:data:`aqm_mjx.agent.rules.MAX_LEGS` per
episode) as ``(d, steps, longest stall, kind)``: the quasimetric's length of the leg, the control
steps the controller took to reach its keypoint, the longest run of steps without progress in d on
it, and whether it was a start leg, a keypoint edge or a goal leg. From the legs of a calibration
pass (the no-pruning agent on the training layout, between cells no evaluation task uses; it never
cuts, so every leg it completes is a traversable one) the rules are calibrated at a false-alarm
rate ``q``:

- the fixed budget ``(1 + kappa) d`` on every leg: ``kappa = quantile_{1-q}(steps / d) - 1``;
- the paper's rule, the same on keypoint edges alone: ``kappa_edges``, that quantile over them;
- the stall rule: ``patience = quantile_{1-q}(longest stall)``, or, with a stall scale ``C > 0``,
  ``patience = C quantile_0.9(longest stall)``: a multiple of how long the controller typically
  stalls, the way the paper's budget is a multiple of d. The tail quantile moves by about 100%
  across calibration keys (long stalls come in bunches from a few episodes); the 90th percentile
  by about 20% (RESULTS.md, section 3.2).

so that a fraction ``q`` of the traversable legs seen would have been cut (with a stall scale, the
rate follows from ``C`` instead). Legs the agent never
finishes (it got stuck, or the episode ended) are not in the log, so the rate is a lower bound.

    legs = calibration.legs_of(results, agent='no-pruning', layout='base')
    calibration.calibrate(legs, false_alarm=0.02)   # {'kappa': ..., 'patience': ..., 'legs': n, ...}

:func:`calibrate` and :func:`budget` (the AQM row's kappa or patience from a calibration, rounded)
are written in ``jax.numpy``: they also run inside a jitted program on the ``legs [E, MAX_LEGS, 3]``
output of a rollout. ``ProtocolConfig.calibrate`` ('fixed' or 'stall') makes every evaluation path do
this before it evaluates (:func:`aqm_mjx.evaluation.evaluate.calibration_pass` on the host,
:func:`aqm_mjx.pipeline.make_run` inside the one-program run).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from aqm_mjx.agent.rules import LEG_EDGE, stall_kappa
from aqm_mjx.evaluation.protocol import CALIBRATE as RULES
from aqm_mjx.evaluation.protocol import NO_PRUNING

QUANTILES = (0.5, 0.9, 0.95, 0.99)


def valid(legs) -> jnp.ndarray:
    """``bool [...]``: which rows of ``legs [..., F]`` hold a logged leg (unused slots are -1 padded;
    a leg of zero length is dropped, its ratio being undefined)."""
    legs = jnp.asarray(legs)
    return (legs[..., 1] >= 0) & (legs[..., 0] > 0) & jnp.isfinite(legs[..., 0])


def calibrate(legs, false_alarm: float = 0.02, rows=None, stall_scale: float = 0.0) -> dict:
    """The budget settings that cut a fraction ``false_alarm`` of the legs in ``legs [..., 4]``.

    Args:
        legs: ``(d, steps, longest stall[, kind])`` per leg, any leading shape (e.g. ``[E, MAX_LEGS,
            4]``), -1 padded. Without the kind column every leg counts as a keypoint edge.
        false_alarm: the fraction of (traversable) legs that the settings would cut, in (0, 1).
        rows: optional ``bool`` mask over the leading axes: which legs to use (e.g. the no-pruning
            rows of an episode table).
        stall_scale: > 0: the stall rule's patience is this multiple of the 90th percentile of the
            longest stall (``false_alarm`` then sets the kappas alone); 0: its ``1 - false_alarm``
            quantile.
    Returns:
        ``{'kappa', 'kappa_edges', 'patience', 'legs', 'edges', 'ratio_q', 'stall_q'}``: the fixed
        rule's slack over every leg and over keypoint edges alone (the paper's rule), the stall
        rule's patience, the number of legs and of keypoint edges used, and the quantiles
        :data:`QUANTILES` of steps / d and of the longest stall (NaN when no leg was logged). Jittable.
    """
    if not 0.0 < false_alarm < 1.0:
        raise ValueError(f'false_alarm must be in (0, 1); got {false_alarm}')
    if not (isinstance(stall_scale, (int, float)) and math.isfinite(stall_scale) and stall_scale >= 0):
        raise ValueError(f'stall_scale must be a finite number >= 0 (0: the false-alarm quantile); got {stall_scale!r}')
    legs = jnp.asarray(legs, jnp.float32)
    if legs.size == 0:  # no leg at all (shapes are static, so this is a trace-time check): NaN, as for no valid one
        legs, rows = jnp.full((1, 3), -1.0), None
    if legs.shape[-1] == 3:  # a log without kinds: every leg a keypoint edge
        legs = jnp.concatenate([legs, jnp.full(legs.shape[:-1] + (1,), float(LEG_EDGE))], -1)
    ok = valid(legs)
    if rows is not None:
        r = jnp.asarray(rows, bool)
        ok = ok & r.reshape(r.shape + (1,) * (ok.ndim - r.ndim))
    ratio = jnp.where(ok, legs[..., 1] / jnp.where(ok, legs[..., 0], 1.0), jnp.nan).reshape(-1)
    stall = jnp.where(ok, legs[..., 2], jnp.nan).reshape(-1)
    qs = jnp.asarray(QUANTILES + (1.0 - false_alarm,), jnp.float32)
    r_q, s_q = jnp.nanquantile(ratio, qs), jnp.nanquantile(stall, qs)
    edge = ok & (legs[..., 3] == LEG_EDGE)
    e_q = jnp.nanquantile(jnp.where(edge.reshape(-1), ratio, jnp.nan), 1.0 - false_alarm)
    patience = stall_scale * s_q[QUANTILES.index(0.9)] if stall_scale > 0 else s_q[-1]
    return dict(kappa=jnp.maximum(r_q[-1] - 1.0, 0.0), kappa_edges=jnp.maximum(e_q - 1.0, 0.0),
                patience=jnp.maximum(patience, 1.0), legs=jnp.sum(ok).astype(jnp.int32),
                edges=jnp.sum(edge).astype(jnp.int32), ratio_q=r_q[:-1], stall_q=s_q[:-1])


def budget(cal: dict, rule: str, kappa, patience) -> tuple[jax.Array, jax.Array]:
    """``(kappa, patience)`` of the AQM agent after calibration ``cal`` (from :func:`calibrate`).

    ``rule``: ``'fixed'``: the calibrated kappa rounded to 0.01, patience 0 (the paper's rule);
    ``'stall'``: the calibrated patience rounded to a whole step, ``kappa`` kept (1 where it is inf,
    which would unbudget the legs); ``'none'``, or a calibration without a single leg (NaN): the given
    ``kappa`` and ``patience``. Jittable (``rule`` static); the same arithmetic on the host and
    inside the one-program run.
    """
    if rule not in RULES:
        raise ValueError(f'unknown calibration rule {rule!r}; expected one of {", ".join(RULES)}')
    kappa, patience = jnp.float32(kappa), jnp.float32(patience)
    if rule == 'fixed':
        k = jnp.round(cal['kappa'], 2)
        ok = jnp.isfinite(k)
        return jnp.where(ok, k, kappa), jnp.where(ok, 0.0, patience).astype(jnp.float32)
    if rule == 'stall':
        p = jnp.round(cal['patience'])
        ok = jnp.isfinite(p)
        return (jnp.where(ok, stall_kappa(kappa), kappa).astype(jnp.float32),
                jnp.where(ok, p, patience).astype(jnp.float32))
    return kappa, patience


def row_budgets(cal: dict, kappa, patience) -> dict:
    """``{kind: (kappa, patience)}`` for every kind of calibrated row (``protocol.Row.calibrated``)
    from calibration ``cal``: ``'fixed'`` and ``'stall'`` as :func:`budget` gives them for the AQM
    row's ``kappa`` and ``patience``, ``'paper'`` the keypoint-edge kappa rounded to 0.01 (patience 0;
    the given ``kappa`` when no edge was logged). Jittable; :func:`aqm_mjx.evaluation.protocol.table_inputs`
    applies them."""
    k = jnp.round(cal['kappa_edges'], 2)
    paper = (jnp.where(jnp.isfinite(k), k, jnp.float32(kappa)).astype(jnp.float32), jnp.float32(0.0))
    return dict(fixed=budget(cal, 'fixed', kappa, patience), stall=budget(cal, 'stall', kappa, patience), paper=paper)


def legs_of(results, agent: str, layout=None) -> np.ndarray:
    """``[N, F]`` the logged legs of one agent's episodes (on one layout, or on all) of an
    :class:`~aqm_mjx.evaluation.evaluate.Results`."""
    if agent not in results.agents:
        raise ValueError(f'no agent {agent!r} in these results (they hold {results.agents})')
    rows = results.table.agent == results.agents.index(agent)
    if layout is not None:
        if layout not in results.variants:
            raise ValueError(f'no layout {layout!r} in these results (they hold {results.variants})')
        rows &= results.table.variant == results.variants.index(layout)
    legs = np.asarray(results.legs)[rows]
    legs = legs.reshape(-1, legs.shape[-1])
    return legs[np.asarray(valid(legs))]


def report(results, false_alarm: float = 0.02) -> dict:
    """``{agent: {layout: {...}}}`` for ``results.json``: per agent and layout, the legs logged, the
    quantiles of steps / d and of the longest stall and, for the rows that never prune (the
    calibration pass: ``no-pruning``), the settings :func:`calibrate` gives at ``false_alarm``."""
    out = {}
    for a in results.agents:
        out[a] = {}
        for v in results.variants:
            legs = legs_of(results, a, v)
            if not len(legs):
                continue
            c = {k: np.asarray(x).tolist() for k, x in calibrate(legs, false_alarm).items()}
            row = dict(legs=int(c['legs']), steps_per_d={f'q{int(100 * q)}': r for q, r in zip(QUANTILES, c['ratio_q'])},
                       longest_stall={f'q{int(100 * q)}': r for q, r in zip(QUANTILES, c['stall_q'])})
            if a == NO_PRUNING:
                row['calibrated'] = dict(false_alarm=false_alarm, kappa=c['kappa'], patience=c['patience'])
            out[a][v] = row
    return out
