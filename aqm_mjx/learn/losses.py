"""Every method's losses as pure functions of network outputs: AQM's (the paper's QRL objective and
multiplier, Q-AWR, Q-SAW) and the baselines' (OGBench's ``impls/agents`` and SAW's
``impls/agents/saw.py`` were read for their definitions; none of their code is here). The weighted
policy losses are shared: Q-AWR and every AWR actor are :func:`awr_loss`, Q-SAW and SAW's bootstrap
term :func:`weighted_kl_loss`. The baselines' return ``(loss, info)`` with namespaced info keys; the
tests recompute every one by hand on tiny inputs.

Value conventions (OGBench's ``gc_negative``): reward -1 per step and 0 at the goal, mask 0 at the
goal, so ``V(s, g)`` is about minus the discounted steps to ``g``. Two-head ensembles have a leading
``[2]`` axis.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import optax


# ------------------------------------------------------------------------------ weighted policies
def advantage_weight(adv: jax.Array, temperature: float, clip: float) -> jax.Array:
    """``min(exp(temperature * adv), clip)``, computed without overflow."""
    return jnp.exp(jnp.minimum(temperature * adv, math.log(clip)))


def awr_loss(logp: jax.Array, adv: jax.Array, temperature: float, clip: float):
    """Advantage-weighted regression (the paper's Q-AWR, eq. 5; OGBench's AWR actors):
    ``-mean(w * logp)`` with ``w = min(exp(temperature * adv), clip)`` held fixed; ``logp, adv [B]``.
    Returns ``(loss, weights [B])``."""
    w = advantage_weight(jax.lax.stop_gradient(adv), temperature, clip)
    return -jnp.mean(w * logp), w


def weighted_kl_loss(divergence: jax.Array, adv: jax.Array, temperature: float, clip: float):
    """Advantage-weighted distillation (the paper's Q-SAW, eq. 6; SAW's bootstrap term):
    ``mean(w * divergence)`` with ``w`` as in :func:`awr_loss`; ``divergence, adv [B]``.
    Returns ``(loss, weights [B])``."""
    w = advantage_weight(jax.lax.stop_gradient(adv), temperature, clip)
    return jnp.mean(w * divergence), w


# -------------------------------------------------------------------------------------- baselines


def expectile_loss(adv: jax.Array, diff: jax.Array, expectile: float) -> jax.Array:
    """``|expectile - 1(adv < 0)| * diff^2`` elementwise (IQL's asymmetric square)."""
    return jnp.where(adv >= 0, expectile, 1.0 - expectile) * jnp.square(diff)


def ivl_value_loss(v: jax.Array, v_target: jax.Array, next_v_target: jax.Array, rewards: jax.Array,
                   masks: jax.Array, discount: float, expectile: float, prefix: str = 'value'):
    """Implicit V-learning (GCIVL, HIQL, SAW): an expectile regression of V on its own bootstrap.

    The advantage that picks the expectile side comes from the target network, the regressed
    difference from the online one (double-DQN style): with ``q_i = r + discount * m * V'_i(s', g)``,
    ``adv = r + discount * m * min_i V'_i(s', g) - mean_i V'_i(s, g)`` and
    ``loss = sum_i mean(expectile_loss(adv, q_i - V_i(s, g)))``.

    Args:
        v: ``[2, B]`` online heads at (s, g); v_target, next_v_target: ``[2, B]`` target heads at
        (s, g) and (s', g); rewards, masks: ``[B]``.
    """
    q_heads = rewards + discount * masks * next_v_target
    adv = rewards + discount * masks * jnp.min(next_v_target, axis=0) - jnp.mean(v_target, axis=0)
    loss = jnp.sum(jnp.mean(expectile_loss(adv, q_heads - v, expectile), axis=-1))
    v_bar = jnp.mean(v, axis=0)  # statistics of the heads' mean, as OGBench logs them
    return loss, {f'{prefix}/loss': loss, f'{prefix}/v_mean': jnp.mean(v_bar), f'{prefix}/v_min': jnp.min(v_bar),
                  f'{prefix}/v_max': jnp.max(v_bar), f'{prefix}/adv_mean': jnp.mean(adv)}


def iql_value_loss(q_target: jax.Array, v: jax.Array, expectile: float):
    """IQL's V: ``mean(expectile_loss(q - v, q - v))`` with ``q = min_i Q'_i(s, a, g)``; ``q_target [2, B], v [B]``."""
    q = jnp.min(q_target, axis=0)
    loss = jnp.mean(expectile_loss(q - v, q - v, expectile))
    return loss, {'value/loss': loss, 'value/v_mean': jnp.mean(v)}


def iql_critic_loss(q: jax.Array, next_v: jax.Array, rewards: jax.Array, masks: jax.Array, discount: float):
    """IQL's Q: ``mean(sum_i (Q_i(s, a, g) - (r + discount * m * V(s', g)))^2)``; ``q [2, B]``, the rest ``[B]``."""
    target = rewards + discount * masks * next_v
    loss = jnp.mean(jnp.sum(jnp.square(q - target), axis=0))
    return loss, {'critic/loss': loss, 'critic/q_mean': jnp.mean(target)}


def awr_actor_loss(log_prob: jax.Array, adv: jax.Array, alpha: float, clip: float = 100.0, prefix: str = 'actor'):
    """AWR: ``-mean(min(exp(alpha * adv), clip) * log_prob)``, weights held fixed; ``log_prob, adv [B]``."""
    loss, w = awr_loss(log_prob, adv, alpha, clip)
    return loss, {f'{prefix}/loss': loss, f'{prefix}/adv_mean': jnp.mean(adv), f'{prefix}/weight_mean': jnp.mean(w),
                  f'{prefix}/log_prob': jnp.mean(log_prob)}


def ddpgbc_actor_loss(q: jax.Array, log_prob: jax.Array, alpha: float, prefix: str = 'actor'):
    """DDPG+BC: ``-mean(q) / stop_grad(mean|q| + 1e-6) - alpha * mean(log_prob)``.

    Args:
        q: ``[2, B]`` (the minimum over heads is taken) or ``[B]``: Q at the actor's own clipped mean
            action; log_prob: ``[B]`` of the dataset's actions under the actor.
    """
    if q.ndim == 2:
        q = jnp.min(q, axis=0)
    q_loss = -jnp.mean(q) / jax.lax.stop_gradient(jnp.mean(jnp.abs(q)) + 1e-6)
    bc_loss = -alpha * jnp.mean(log_prob)
    loss = q_loss + bc_loss
    return loss, {f'{prefix}/loss': loss, f'{prefix}/q_loss': q_loss, f'{prefix}/bc_loss': bc_loss,
                  f'{prefix}/q_mean': jnp.mean(q), f'{prefix}/log_prob': jnp.mean(log_prob)}


def contrastive_logits(phi: jax.Array, psi: jax.Array) -> jax.Array:
    """``[E, B, L]`` x ``[E, B, L]`` -> ``[B, B, E]`` logits ``phi_i . psi_j / sqrt(L)`` per head."""
    return jnp.einsum('eik,ejk->ije', phi, psi) / jnp.sqrt(phi.shape[-1])


def infonce_loss(phi: jax.Array, psi: jax.Array, prefix: str = 'critic'):
    """CRL's contrastive loss: binary cross-entropy of every (state-action i, goal j) logit with
    label ``i == j`` (the positive pairs on the diagonal), averaged over pairs and heads."""
    logits = contrastive_logits(phi, psi)
    labels = jnp.eye(logits.shape[0])[..., None]
    loss = jnp.mean(optax.sigmoid_binary_cross_entropy(logits, jnp.broadcast_to(labels, logits.shape)))
    mean_logits = jnp.mean(logits, axis=-1)
    eye = labels[..., 0]
    return loss, {f'{prefix}/loss': loss,
                  f'{prefix}/accuracy': jnp.mean(jnp.argmax(mean_logits, axis=1) == jnp.arange(logits.shape[0])),
                  f'{prefix}/logits_pos': jnp.sum(mean_logits * eye) / jnp.sum(eye),
                  f'{prefix}/logits_neg': jnp.sum(mean_logits * (1 - eye)) / jnp.sum(1 - eye)}


def qrl_value_loss(d_neg: jax.Array, d_pos: jax.Array, lam: jax.Array, eps: float):
    """OGBench's flat QRL: push random pairs apart, keep transitions within one step.

    ``d_neg_loss = mean(100 softplus(5 - d_neg / 100))``, ``d_pos_loss = mean(relu(d_pos - 1)^2)``;
    the value loss is ``d_neg_loss + stop_grad(lam) * d_pos_loss`` and the multiplier's
    ``lam * (eps - stop_grad(d_pos_loss))``; returns their sum. ``d_neg, d_pos [B]``, ``lam []`` (> 0).
    """
    d_neg_loss = jnp.mean(100.0 * jax.nn.softplus(5.0 - d_neg / 100.0))
    d_pos_loss = jnp.mean(jnp.square(jax.nn.relu(d_pos - 1.0)))
    value_loss = d_neg_loss + jax.lax.stop_gradient(lam) * d_pos_loss
    lam_loss = lam * (eps - jax.lax.stop_gradient(d_pos_loss))
    loss = value_loss + lam_loss
    return loss, {'value/loss': value_loss, 'value/d_neg_mean': jnp.mean(d_neg), 'value/d_pos_mean': jnp.mean(d_pos),
                  'value/d_pos_loss': d_pos_loss, 'value/lambda': lam, 'lambda/loss': lam_loss}


def dynamics_loss(d_forward: jax.Array, d_backward: jax.Array):
    """QRL's latent dynamics: ``mean(d(z', z_hat) + d(z_hat, z')) / 2``; both ``[B]``."""
    loss = jnp.mean(d_forward + d_backward) / 2.0
    return loss, {'dynamics/loss': loss}


def waypoint_loss(mean_main: jax.Array, mean_sub: jax.Array, adv: jax.Array, alpha: float, clip: float = 100.0):
    """SAW's bootstrap term: ``mean(min(exp(alpha * adv), clip) * sum((mu_main - stop_grad(mu_sub))^2))``.

    With unit std this is twice ``KL(pi_sub || pi_main)``; SAW's reference writes it this way and we
    keep its scale. ``mean_* [B, A]``, ``adv [B]`` = V(w, g) - V(s, g).
    """
    sq = jnp.sum(jnp.square(mean_main - jax.lax.stop_gradient(mean_sub)), axis=-1)
    loss, _ = weighted_kl_loss(sq, adv, alpha, clip)
    return loss, {'waypoint/loss': loss, 'waypoint/kl': jnp.mean(sq), 'waypoint/adv_mean': jnp.mean(adv)}


# -------------------------------------------------------------------- AQM's quasimetric (QRL)
def push_term(d: jax.Array, offset: float, scale: float) -> jax.Array:
    """``-omega(d) = softplus(scale * (offset - d)) / scale`` (paper eq. 4 and Appendix 10)."""
    return jax.nn.softplus(scale * (offset - d)) / scale


def constraint_violation(d_pos: jax.Array, epsilon: float) -> jax.Array:
    """``relu(d(s, s') - 1)^2 - epsilon^2`` per transition: ``[B] -> [B]`` (<= 0 where it holds on average)."""
    return jnp.square(jax.nn.relu(d_pos - 1.0)) - epsilon ** 2


def qrl_loss(d_pos: jax.Array, d_goal: jax.Array, lam: jax.Array, epsilon: float, offset: float, scale: float):
    """The quasimetric's QRL objective (paper eq. 3-4, Algorithm 1 lines 4-8).

    Args:
        d_pos: ``[B]`` d(s, s') on transitions; d_goal: ``[B]`` d(s, g) on sampled goals.
        lam: the Lagrange multiplier (>= 0), held fixed here.
        epsilon: slack of the local constraint; offset, scale: m and s of omega (Table 5).
    Returns:
        ``(mean(stop_grad(lam) * close + push), info)`` with ``close`` from :func:`constraint_violation`.
    """
    close = constraint_violation(d_pos, epsilon)
    push = push_term(d_goal, offset, scale)
    loss = jnp.mean(jax.lax.stop_gradient(lam) * close + push)
    info = {'qrl/close': jnp.mean(close), 'qrl/push': jnp.mean(push), 'qrl/lambda': lam,
            'qrl/d_pos_mean': jnp.mean(d_pos), 'qrl/d_goal_mean': jnp.mean(d_goal)}
    return loss, info


def lambda_loss(d_pos: jax.Array, lam: jax.Array, epsilon: float):
    """The multiplier's objective (Algorithm 1 lines 9-10): ``-lam * stop_grad(mean(close))``, whose
    gradient ascends on the constraint violation. ``d_pos [B]``. Returns ``(loss, info)``."""
    violation = jax.lax.stop_gradient(jnp.mean(constraint_violation(d_pos, epsilon)))
    return -lam * violation, {'lambda/violation': violation}
