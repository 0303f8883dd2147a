"""Parity of our GAS learner with its public reference (``qortmdgh4141/GAS``, ``M_utils/agents/gas.py``)
on the same parameters and batches: both phases, the TDR's and the skill policy's.

    git clone https://github.com/qortmdgh4141/GAS /tmp/GAS             # or any checkout of it
    python benchmarks/parity/bench_parity_gas_agent.py --reference /tmp/GAS

The reference agent is built with its own ``GASAgent.create`` (widths 2 x 32, TDR 8-d, its other
settings as ours), our parameters and targets are written into its tree (every shape checked). For
each phase, on one batch the benchmark prints the loss of each module of both and the largest
relative difference of the gradients; then both take 5 updates on 5 further batches (reference
``tdr_update`` / ``critic_actor_update`` on a fresh agent, as GAS's two programs; ours
``learner.step`` at a step of that phase) and the largest difference of every parameter and
target is printed. The policy phase's batches carry the ``phi`` of the state, the next state and
the actor goal from the TDR's parameters, as GAS's ``GASDataset`` precomputes them; ours derives the
same from the states ahead of each source (the goal's offset given), and the random skills come
from the key the reference splits from its ``rng``. The control moves our skill value's expectile
by 0.05 and must disagree. (GAS's nodes and edges: ``bench_parity_gas.py``.)

The reference is imported from the copy given, never copied; ``distrax`` is stood in by the
Gaussian of ``bench_parity.py``. Exits 1 on a difference above ``--loss-tol`` (relative) or
``--param-tol`` (absolute).
"""

from __future__ import annotations

import os
import sys

import jax
import jax.numpy as jnp
import numpy as np

from aqm_mjx.data import goals
from aqm_mjx.learn import methods
from aqm_mjx.learn.baselines import gas

from bench_parity import (_flat, _gaussian_standin, _set_checked, check_gradients, check_losses, check_update,
                          reference_parser, rel, verdict)

HIDDEN, LATENT, OBS, ACT, B, W = (32, 32), 8, 29, 8, 64, 6
REF_NAMES = {'tdr': 'tdr_value', 'value': 'value', 'critic': 'critic', 'actor': 'actor'}


def import_reference(root: str):
    """The reference's ``M_utils.agents.gas`` (``root``: a checkout of qortmdgh4141/GAS)."""
    if not os.path.isdir(os.path.join(root, 'M_utils', 'agents')):
        raise SystemExit(f'{root}: no M_utils/agents: --reference must be a checkout of qortmdgh4141/GAS')
    distrax = _gaussian_standin()
    distrax.Distribution = object
    sys.modules.setdefault('distrax', distrax)
    sys.path.insert(0, root)
    from M_utils.agents import gas as ref  # pylint: disable=import-outside-toplevel,import-error
    return ref


def to_reference(state, ref_params) -> dict:
    """Our parameters and targets written into a copy of the reference's tree (shapes checked)."""
    from flax.core import unfreeze  # pylint: disable=import-outside-toplevel

    out = jax.tree.map(np.array, unfreeze(ref_params))
    for tree, prefix in ((state.params, 'modules_'), (state.target, 'modules_target_')):
        for path, leaf in _flat(tree):
            where = (prefix + REF_NAMES[path[0]],) + path[2:]
            _set_checked(out, where, np.asarray(leaf))
    return out


def batches(key, n: int, step: int, phi):
    """``n`` (reference dict, our GASBatch) pairs on the same arrays; a quarter of the TDR goals are the
    states. ``phi``: the TDR's ``obs [., D] -> [., L]`` (the reference's batches carry it precomputed)."""
    out = []
    for k in jax.random.split(key, n):
        ks = jax.random.split(k, 5)
        walk = jnp.cumsum(0.1 * jax.random.normal(ks[0], (B, W + 1, OBS)), axis=1) + jax.random.normal(ks[1], (B, 1, OBS))
        s, s1 = walk[:, 0], walk[:, 1]
        at_goal = (jnp.arange(B) % 4 == 0).astype(jnp.float32)
        g = jnp.where(at_goal[:, None] > 0, s, jax.random.normal(ks[2], (B, OBS)))
        a = jax.random.uniform(ks[3], (B, ACT), minval=-1, maxval=1)
        off = jax.random.randint(ks[4], (B,), 1, W + 1)  # the actor goal's offset (the geometric draw, far waysteps)
        gc = goals.GCBatch(observations=s, actions=a, next_observations=s1, value_goals=g, rewards=at_goal - 1.0,
                           masks=1.0 - at_goal, actor_goals=g, subgoals=g, low_goals=g,
                           index=jnp.zeros(B, jnp.int32),
                           **{f: jnp.zeros(B, jnp.int32) for f in ('value_goal_index', 'value_kind',
                                                                    'actor_goal_index', 'actor_kind', 'subgoal_index')})
        ours = gas.GASBatch(gc=gc, ahead=walk, end=jnp.full(B, 10_000, jnp.int32), geom=off,
                            step=jnp.int32(step))
        goal_obs = jnp.take_along_axis(walk, off[:, None, None], axis=1)[:, 0]
        ref = dict(observations=np.asarray(s), next_observations=np.asarray(s1), actions=np.asarray(a),
                   tdr_value_goals=np.asarray(g), tdr_rewards=np.asarray(at_goal - 1.0),
                   tdr_masks=np.asarray(1.0 - at_goal), phi_obs=np.asarray(phi(s)), phi_next_obs=np.asarray(phi(s1)),
                   phi_actor_goals=np.asarray(phi(goal_obs)))
        out.append((ref, ours))
    return out


def fresh(ref_agent, state):
    """The reference agent with our parameters and a fresh Adam state on them (a plain dict: its
    target update writes into the tree)."""
    params = jax.tree.map(jnp.asarray, to_reference(state, ref_agent.network.params))
    net = ref_agent.network.replace(params=params, opt_state=ref_agent.network.tx.init(params))
    return ref_agent.replace(network=net), params


def phase(name, ref, agent, learner, state, data, a, rows) -> bool:
    """One phase's loss, gradients and 5 updates against the reference; True when all agree."""
    agent, params = fresh(agent, state)
    ok = True
    ref_batch, our_batch = data[0]
    key = jax.random.split(jax.random.split(agent.rng)[1])[0]  # what the reference's loss draws its skills from
    if name == 'tdr':
        ref_loss = lambda q: agent.total_tdr_value_loss(dict(ref_batch), q)  # noqa: E731
        keys = [('tdr', 'tdr value/value_loss', 'tdr/loss')]
    else:
        ref_loss = lambda q: agent.total_critic_actor_loss(dict(ref_batch), q, rng=jax.random.split(agent.rng)[1])  # noqa: E731
        keys = [('value', 'value/value_loss', 'value/loss'), ('critic', 'critic/critic_loss', 'critic/loss'),
                ('actor', 'actor/actor_loss', 'actor/loss')]
    (l_ref, info_ref), g_ref = jax.value_and_grad(ref_loss, has_aux=True)(params)
    loss_fn = learner.tdr_loss if name == 'tdr' else learner.policy_loss
    (l_ours, info_ours), g_ours = jax.value_and_grad(loss_fn, has_aux=True)(state.params, state.target, our_batch, key)
    pairs = [('total', l_ref, l_ours)] + [(what, info_ref[kr], info_ours[ko]) for what, kr, ko in keys]
    ok &= check_losses(pairs, a.loss_tol, rows, prefix=f'{name}/')
    ok &= check_gradients(g_ref, to_reference(state.replace(params=g_ours), params), a.loss_tol, rows,
                          prefix=f'{name}/')
    step = jax.jit(learner.step)
    for i, (rb, ob) in enumerate(data[1:], 1):
        key = jax.random.split(jax.random.split(agent.rng)[1])[0]
        agent, _ = (agent.tdr_update if name == 'tdr' else agent.critic_actor_update)(dict(rb))
        state, _ = step(state, ob, key)
        ok &= check_update(i, dict(agent.network.params), to_reference(state, params), a.param_tol, rows,
                           prefix=f'{name}/')
    return ok, l_ref


def main() -> int:
    a = reference_parser(__doc__, 'qortmdgh4141/GAS').parse_args()
    ref = import_reference(a.reference)
    m = methods.get('gas')
    cfg = m.preset('ci', env='antmaze-medium', value_hidden=HIDDEN, actor_hidden=HIDDEN, latent=LATENT,
                   waystep_window=W, steps=100)
    learner = gas.parts(cfg, OBS, ACT)
    state = learner.init(jax.random.PRNGKey(0))
    rc = ref.get_config()
    rc.update(tdr_value_hidden_dims=HIDDEN, value_hidden_dims=HIDDEN, actor_hidden_dims=HIDDEN, tdr_dim=LATENT,
              discount=cfg.discount, tdr_expectile=cfg.tdr_expectile, expectile=cfg.expectile, alpha=cfg.alpha,
              lr=cfg.lr, tau=cfg.tau, way_steps=cfg.way_steps)
    agent = ref.GASAgent.create(0, np.zeros((1, OBS), np.float32), np.zeros((1, ACT), np.float32), dict(rc))
    rows = []
    print(f'{"phase/loss":14} {"reference":>12} {"ours":>12} {"rel diff":>9}')
    phi = jax.jit(lambda o: learner.phi(state.params, o))
    ok_t, _ = phase('tdr', ref, agent, learner, state.replace(step=jnp.int32(0)),
                    batches(jax.random.PRNGKey(1), 6, 0, phi), a, rows)
    policy_data = batches(jax.random.PRNGKey(2), 6, cfg.tdr_steps, phi)
    ok_p, l_ref = phase('policy', ref, agent, learner, state.replace(step=jnp.int32(cfg.tdr_steps)), policy_data, a,
                        rows)
    ok = ok_t and ok_p
    # CONTROL: the skill value's expectile moved by 0.05 must disagree with the reference's policy loss
    moved = gas.parts(cfg.__class__(**{**cfg.to_dict(), 'expectile': cfg.expectile + 0.05}), OBS, ACT)
    key = jax.random.split(jax.random.split(agent.rng)[1])[0]
    l_moved, _ = moved.policy_loss(state.params, state.target, policy_data[0][1], key)
    control = rel(l_ref, l_moved) <= a.loss_tol
    rows.append(dict(what='control', reference=float(l_ref), ours_moved=float(l_moved)))
    return verdict(ok, control, a, rows, '5 updates of each phase', 'skill value expectile + 0.05')


if __name__ == '__main__':
    sys.exit(main())
