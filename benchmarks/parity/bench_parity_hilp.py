"""Parity of our HILP with its public reference (``seohongpark/HILP``, ``hilp_gcrl/src/agents/hilp.py``)
on the same parameters and the same batches.

    git clone https://github.com/seohongpark/HILP /tmp/HILP           # or any checkout of it
    python benchmarks/parity/bench_parity_hilp.py --reference /tmp/HILP

The reference agent is built with its own ``create_learner`` (widths 3 x 32, latent 8, its other
settings as ours), our parameters are written into its tree (module by module; every shape is
checked), and on one batch the benchmark prints the total loss and each module's loss of both, and
the largest relative difference of the gradients; then both take 5 updates on 5 further batches
(reference ``agent.update(batch)``, ours ``learner.step(state, batch, key)``, Adam 3e-4, Polyak
0.005) and the largest difference of every parameter and target is printed. The random directions
come from the same key: the reference draws them from ``split(agent.rng)[1]``, which ours is given.
The control moves our latent policy's expectile by 0.05 and must disagree.

The reference is imported from the copy given, never copied; ``distrax`` is stood in by the Gaussian
of ``bench_parity.py``, ``jaxrl_m.vision`` (image encoders, unused here) by an empty module, and
``jax.tree_map`` (gone from JAX 0.10) by ``jax.tree.map``; its Adam state is rebuilt on its frozen
parameter tree (with flax 0.12 the two trees differ in type and its first update fails). Exits 1 on a difference above
``--loss-tol`` (relative) or ``--param-tol`` (absolute).
"""

from __future__ import annotations

import os
import sys
import types

import jax
import jax.numpy as jnp
import numpy as np

from aqm_mjx.data import goals
from aqm_mjx.learn import methods

from bench_parity import (_flat, _gaussian_standin, _set_checked, check_gradients, check_losses, check_update,
                          reference_parser, rel, verdict)

HIDDEN, LATENT, OBS, ACT, B = (32, 32, 32), 8, 29, 8, 64
# our (module, first path part) -> the reference's module and the path before the layer names
MODULES = {('value', 'phi_net'): ('networks_value', ('phi', 'VmapLayerNormMLP_0')),
           ('skill_critic', 'value_net'): ('networks_skill_critic', ('critic_net', 'VmapLayerNormMLP_0')),
           ('skill_value', 'value_net'): ('networks_skill_value', ('value_net', 'LayerNormMLP_0'))}
TARGETS = {'value': 'networks_target_value', 'skill_critic': 'networks_skill_target_critic'}


def import_reference(root: str):
    """The reference's ``src.agents.hilp`` with its ``jaxrl_m`` (``root``: a checkout, or its ``hilp_gcrl``)."""
    base = root if os.path.isdir(os.path.join(root, 'jaxrl_m')) else os.path.join(root, 'hilp_gcrl')
    if not os.path.isdir(os.path.join(base, 'src', 'agents')):
        raise SystemExit(f'{root}: no hilp_gcrl/src/agents: --reference must be a checkout of seohongpark/HILP')
    if not hasattr(jax, 'tree_map'):
        jax.tree_map = jax.tree.map
    distrax = _gaussian_standin()
    distrax.Distribution = object
    sys.modules.setdefault('distrax', distrax)
    vision = types.ModuleType('jaxrl_m.vision')
    vision.encoders = {}
    sys.modules['jaxrl_m.vision'] = vision
    sys.path.insert(0, base)
    from src.agents import hilp as ref  # pylint: disable=import-outside-toplevel,import-error
    return ref


def _ref_path(module: str, rest: tuple, target: bool = False) -> tuple:
    """Where our leaf ``(module, 'params', *rest)`` lives in the reference's tree."""
    if module == 'actor':
        if rest[0] == 'actor_net':
            return ('networks_skill_actor', 'MLP_0', rest[1].replace('Dense_', 'layers_')) + rest[2:]
        return ('networks_skill_actor',) + (('Dense_0',) + rest[1:] if rest[0] == 'mean_net' else rest)
    name, prefix = MODULES[(module, rest[0])]
    return ((TARGETS[module] if target else name),) + prefix + rest[1:]


def to_reference(state, ref_params) -> dict:
    """Our parameters and targets written into a copy of the reference's tree (shapes checked)."""
    from flax.core import unfreeze  # pylint: disable=import-outside-toplevel

    out = jax.tree.map(np.array, unfreeze(ref_params))
    for tree, target in ((state.params, False), (state.target, True)):
        for path, leaf in _flat(tree):
            where = _ref_path(path[0], path[2:], target)
            _set_checked(out, where, np.asarray(leaf))
    return out


def batches(key, n: int):
    """``n`` (reference dict, our GCBatch) pairs on the same arrays; a quarter of the goals are the states."""
    out = []
    for k in jax.random.split(key, n):
        ks = jax.random.split(k, 4)
        s = jax.random.normal(ks[0], (B, OBS))
        s1 = s + 0.1 * jax.random.normal(ks[1], (B, OBS))
        at_goal = (jnp.arange(B) % 4 == 0).astype(jnp.float32)
        g = jnp.where(at_goal[:, None] > 0, s, jax.random.normal(ks[2], (B, OBS)))
        a = jax.random.uniform(ks[3], (B, ACT), minval=-1, maxval=1)
        ref = dict(observations=np.asarray(s), next_observations=np.asarray(s1), goals=np.asarray(g),
                   rewards=np.asarray(at_goal), actions=np.asarray(a), masks=np.asarray(1.0 - at_goal))
        ours = goals.GCBatch(observations=s, actions=a, next_observations=s1, value_goals=g, rewards=at_goal - 1.0,
                             masks=1.0 - at_goal, actor_goals=g, subgoals=g, low_goals=g,
                             **{f: jnp.zeros(B, jnp.int32) for f in ('index', 'value_goal_index', 'value_kind',
                                                                      'actor_goal_index', 'actor_kind', 'subgoal_index')})
        out.append((ref, ours))
    return out


def main() -> int:
    a = reference_parser(__doc__, 'seohongpark/HILP').parse_args()
    ref = import_reference(a.reference)
    m = methods.get('hilp')
    cfg = m.preset('ci', env='antmaze-medium', value_hidden=HIDDEN, actor_hidden=HIDDEN, latent=LATENT)
    learner = m.make(cfg, OBS, ACT)
    state = learner.init(jax.random.PRNGKey(0))
    agent = ref.create_learner(0, np.zeros((1, OBS), np.float32), np.zeros((1, ACT), np.float32), lr=cfg.lr,
                               value_hidden_dims=HIDDEN, actor_hidden_dims=HIDDEN, discount=cfg.discount, tau=cfg.tau,
                               expectile=cfg.expectile, use_layer_norm=1, skill_dim=LATENT,
                               skill_expectile=cfg.skill_expectile, skill_temperature=cfg.skill_temperature,
                               skill_discount=cfg.skill_discount)
    from flax.core import freeze  # pylint: disable=import-outside-toplevel

    params = freeze(to_reference(state, agent.network.params))
    # the Adam state is built again on the frozen tree: with flax 0.12 the reference's init returns a plain
    # dict, its create_learner freezes the parameters after building Adam's state on the dict, and the two
    # trees no longer match in its first update
    agent = agent.replace(network=agent.network.replace(params=params, opt_state=agent.network.tx.init(params)))
    data = batches(jax.random.PRNGKey(1), 6)
    rows, ok = [], True

    # the loss and its gradients on one batch, with the reference's own random directions
    ref_batch, our_batch = data[0]
    skill_key = key0 = jax.random.split(agent.rng)[1]
    (l_ref, info_ref), g_ref = jax.value_and_grad(lambda q: ref.loss_fn(q, agent, dict(ref_batch)), has_aux=True)(params)
    (l_ours, info_ours), g_ours = jax.value_and_grad(learner.loss, has_aux=True)(state.params, state.target, our_batch,
                                                                                skill_key)
    pairs = [('total', l_ref, l_ours), ('value', info_ref['value/value_loss'], info_ours['value/loss']),
             ('skill_value', info_ref['skill_value/value_loss'], info_ours['skill_value/loss']),
             ('skill_critic', info_ref['skill_critic/critic_loss'], info_ours['skill_critic/loss']),
             ('skill_actor', info_ref['skill_actor/actor_loss'], info_ours['skill_actor/loss'])]
    print(f'{"loss":14} {"reference":>12} {"ours":>12} {"rel diff":>9}')
    ok &= check_losses(pairs, a.loss_tol, rows)
    ok &= check_gradients(g_ref, to_reference(state.replace(params=g_ours, target=state.target), params), a.loss_tol,
                          rows)

    # 5 updates on 5 further batches
    step = jax.jit(learner.step)
    for i, (rb, ob) in enumerate(data[1:], 1):
        skill_key = jax.random.split(agent.rng)[1]
        agent, _ = agent.update(dict(rb))
        state, _ = step(state, ob, skill_key)
        ok &= check_update(i, dict(agent.network.params), to_reference(state, params), a.param_tol, rows)

    # CONTROL: ours with the latent policy's expectile moved by 0.05 must disagree with the reference's loss
    moved = m.make(cfg.__class__(**{**cfg.to_dict(), 'skill_expectile': cfg.skill_expectile + 0.05}), OBS, ACT)
    start = learner.init(jax.random.PRNGKey(0))
    l_moved, _ = moved.loss(start.params, start.target, our_batch, key0)
    control = rel(l_ref, l_moved) <= a.loss_tol
    rows.append(dict(what='control', reference=float(l_ref), ours_moved=float(l_moved)))
    return verdict(ok, control, a, rows, '5 updates', 'skill expectile + 0.05')


if __name__ == '__main__':
    sys.exit(main())
