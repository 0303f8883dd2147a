"""AQM's policy objectives (paper section 4.4, eq. 5-6, Table 4), each ``(loss, info)``.

All hold the quasimetric fixed: the advantages come from distances computed outside the policy's
gradient, and the weights ``min(exp(temperature * advantage), clip)`` are stop-gradient. The losses
are the shared library's (:mod:`aqm_mjx.learn.losses`: ``awr_loss``, ``weighted_kl_loss``), the same
that the baselines' AWR actors and SAW's bootstrap term use.

- ``saw``: Q-AWR target policy on subgoals plus the Q-SAW main policy distilled from it;
- ``awr``: Q-AWR on the goal (the paper's flat ablation);
- ``bc``: behaviour cloning on the goal.

:data:`OBJECTIVES` maps the names to the functions. Each takes ``run(params, goal [B, D]) ->
(mean [B, A], log_std [B, A])`` (the policy applied to the batch's states), the policy parameters
``{'target', 'main'}``, the batch (actions, goals, subgoals), the distances of
:func:`advantage_distances` and the weight settings.
"""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp

from aqm_mjx.learn.losses import awr_loss, weighted_kl_loss
from aqm_mjx.learn.policy import kl, log_prob


def advantage_distances(dist: Callable, zs, zs1, zw, zg) -> dict:
    """The five distances the objectives read, from latents ``[B, L]`` of s, s', the subgoal w and
    the goal g: ``sw = d(s, w)``, ``s1w = d(s', w)``, ``sg = d(s, g)``, ``s1g = d(s', g)``,
    ``wg = d(w, g)``, each ``[B]``."""
    return dict(sw=dist(zs, zw), s1w=dist(zs1, zw), sg=dist(zs, zg), s1g=dist(zs1, zg), wg=dist(zw, zg))


def _main_info(loss, weights, mean, actions, clip) -> dict:
    return {'policy/main_loss': loss, 'policy/main_weight': jnp.mean(weights),
            'policy/main_weight_clipped': jnp.mean(weights >= clip * (1 - 1e-6)),
            'policy/main_mse': jnp.mean(jnp.square(mean - actions))}


def saw_objective(run: Callable, params: dict, batch, d: dict, temperature: float, clip: float):
    """Q-AWR target ``pi_sub(a | s, w)`` with advantage ``d(s, w) - d(s', w)``, and Q-SAW main
    ``pi(a | s, g)``: ``w * KL(pi(.|s, g) || stop_grad(pi_sub(.|s, w)))`` with advantage
    ``d(s, g) - d(w, g)``."""
    mu_m, ls_m = run(params['main'], batch.goals)
    mu_t, ls_t = run(params['target'], batch.subgoals)
    lt, wt = awr_loss(log_prob(mu_t, ls_t, batch.actions), d['sw'] - d['s1w'], temperature, clip)
    k = kl(mu_m, ls_m, jax.lax.stop_gradient(mu_t), jax.lax.stop_gradient(ls_t))
    lm, wm = weighted_kl_loss(k, d['sg'] - d['wg'], temperature, clip)
    info = {'policy/target_loss': lt, 'policy/target_weight': jnp.mean(wt), 'policy/kl': jnp.mean(k),
            'policy/target_mse': jnp.mean(jnp.square(mu_t - batch.actions))}
    return lt + lm, {**info, **_main_info(lm, wm, mu_m, batch.actions, clip)}


def awr_objective(run: Callable, params: dict, batch, d: dict, temperature: float, clip: float):
    """Q-AWR on the goal: ``-w * log pi(a | s, g)`` with advantage ``d(s, g) - d(s', g)``."""
    mu_m, ls_m = run(params['main'], batch.goals)
    lm, wm = awr_loss(log_prob(mu_m, ls_m, batch.actions), d['sg'] - d['s1g'], temperature, clip)
    return lm, _main_info(lm, wm, mu_m, batch.actions, clip)


def bc_objective(run: Callable, params: dict, batch, d: dict, temperature: float, clip: float):
    """Behaviour cloning on the goal: ``-log pi(a | s, g)`` (distances and weights unused)."""
    del d, temperature
    mu_m, ls_m = run(params['main'], batch.goals)
    lm = -jnp.mean(log_prob(mu_m, ls_m, batch.actions))
    return lm, _main_info(lm, jnp.ones(mu_m.shape[:1]), mu_m, batch.actions, clip)


OBJECTIVES = {'saw': saw_objective, 'awr': awr_objective, 'bc': bc_objective}
