"""GAS (Baek et al., 2025, "Graph-Assisted Stitching") as its public code trains and runs it
(``qortmdgh4141/GAS``: ``M_utils/agents/gas.py``, ``O_utils/datasets.py``, ``construct_graph.py``,
``O_utils/evaluation.py``), in two phases of one run:

1. **TDR** (the first ``tdr_steps`` updates, half the run by default): a temporal distance representation ``phi``
   with ``V(s, g) = -||phi(s) - phi(g)||`` (two heads, :class:`~aqm_mjx.learn.networks.HilbertValue`)
   learned by implicit V-learning at expectile 0.999 on goals 62.5% later in the trajectory
   (geometric), 37.5% random, with a target copy (``pretrain_tdr.py``);
2. **skill policy** (the rest, ``phi`` fixed, a fresh Adam as GAS's second program): IQL's value
   (expectile 0.7) and twin critic on random unit skills ``z`` rewarded by ``(phi(s') - phi(s)) . z``,
   and a DDPG+BC actor (alpha 1) on the skill toward the actor goal ``s_{min(t + Geom(1 - discount),
   waystep(t))}``, ``waystep(t)`` the first later state of the trajectory ``H`` (``way_steps``) away
   in ``phi`` (``train_policy.py``).

GAS's map (:mod:`aqm_mjx.mapping.gas_nodes`: TE filtering, TD-aware clustering, edges within ``H``)
is built from every dataset state after training, and its agent (:mod:`aqm_mjx.agent.gas_rule`)
steers the skill policy toward the furthest node of the shortest path within ``H``.

Where this differs from the reference: the waystep is searched among the next ``waystep_window``
states of each sampled transition (GAS precomputes it over the whole trajectory); where none of
them is ``H`` away and the trajectory goes on, the window's last state stands in. A converged TDR's
distance grows about one unit per step, so at the default window, 2 H, that is rare; an
undertrained one's grows slower (``actor/waystep_in_window`` says how often the window held it).
Both phases run in one training loop, so a run checkpoints and resumes as any other method. Seeds
vmapped into one program (``aqm-mjx compare``) share their step (:func:`aqm_mjx.learn.fit.seeds_chunk`),
so the phase stays one branch there too: each update pays for its own phase only.
"""

from __future__ import annotations

import dataclasses
import types

import jax
import jax.numpy as jnp
import optax
from flax import struct

from aqm_mjx import config as cfg_lib
from aqm_mjx.data import goals
from aqm_mjx.interface import Agent, spec
from aqm_mjx.learn import distance as to_steps, losses, networks, policy
from aqm_mjx.learn.baselines import base
from aqm_mjx.learn.learner import Learner, option

POLICY = ('value', 'critic', 'actor')  # the skill policy's modules (phase 2); 'tdr' is phase 1's


@dataclasses.dataclass(frozen=True)
class GASConfig(base.BaselineConfig):
    """GAS's settings on AntMaze navigate and stitch (its README's commands): TDR 32-d, expectiles
    0.999 (TDR) and 0.7 (skill value), alpha 1 (0.01 on explore), ``H`` 8, TE threshold 0.99,
    discount 0.99 (0.995 on giant: ``--set train.discount=0.995``)."""

    latent: int = option(32, "phi's width (GAS's tdr_dim)")
    tdr_expectile: float = option(0.999, "the TDR's IVL expectile")
    expectile: float = option(0.7, "the skill value's IQL expectile")
    alpha: float = option(1.0, 'DDPG+BC: the BC coefficient (0.01 on explore data)')
    way_steps: int = option(8, "H_TD: the waystep distance, TE filtering's step, node radius H/2, edge and subgoal "
                            "radius (phi's units: control steps)")
    te_threshold: float = option(0.99, 'TE filtering: the cosine below which a dataset state is dropped')
    max_nodes: int = option(4096, 'static bound on the graph nodes (a state that needs more joins its nearest)')
    tdr_steps: int = option(0, "updates of the TDR phase before the skill policy's (GAS: 1M + 1M); 0: half the "
                            "run's steps, fixed when the config is made (a resumed or extended run keeps it)")
    waystep_window: int = option(16, "states after each sampled one searched for its waystep (2 H; phase 2 runs at "
                                 "a third of phase 1's speed at 24 on a 2-core CPU, at 0.8 at 1)")
    value_p_current: float = option(0.0, 'TDR goals: P(the state itself)')
    value_p_trajectory: float = option(0.625, 'TDR goals: P(a later state of the trajectory)')
    value_p_random: float = option(0.375, 'TDR goals: P(a random dataset state)')

    PRESET_OVERRIDES = {'ci': {'latent': 8, 'max_nodes': 256, 'waystep_window': 8}}

    @classmethod
    def from_dict(cls, d: dict):
        """A saved config; one written when the phase boundary was a share of the run
        (``tdr_fraction``) reads back as the same boundary in updates (``tdr_steps``)."""
        if isinstance(d, dict) and 'tdr_fraction' in d and 'tdr_steps' not in d:
            d = dict(d)
            frac, steps = d.pop('tdr_fraction'), d.get('steps', 0)
            if not (isinstance(frac, (int, float)) and 0 < frac < 1 and isinstance(steps, int) and steps > 1):
                raise ValueError(f'tdr_fraction must be in (0, 1) with steps > 1; got {frac!r} and steps {steps!r}')
            d['tdr_steps'] = min(max(1, round(steps * frac)), steps - 1)
        return cfg_lib.from_dict(cls, d)

    def __post_init__(self):
        super().__post_init__()
        if self.tdr_steps < 0:
            raise ValueError(f'tdr_steps must be >= 0 (0: half the steps); got {self.tdr_steps}')
        if self.tdr_steps == 0:
            object.__setattr__(self, 'tdr_steps', max(1, self.steps // 2))
        if self.way_steps < 1:
            raise ValueError(f'way_steps must be an integer >= 1; got {self.way_steps}')
        if not -1.0 <= self.te_threshold <= 1.0:
            raise ValueError(f'te_threshold is a cosine, in [-1, 1]; got {self.te_threshold}')
        for name in ('max_nodes', 'waystep_window'):
            if getattr(self, name) < 1:
                raise ValueError(f'{name} must be >= 1; got {getattr(self, name)}')


@struct.dataclass
class GASBatch:
    """A GAS update's batch: the baselines' :class:`~aqm_mjx.data.goals.GCBatch` (TDR goals as value
    goals), each source's next states for the waystep search and its geometric offset, the update's step."""

    gc: goals.GCBatch
    ahead: jax.Array  # [B, W + 1, D] s_{min(t + k, end)}, k = 0..W
    end: jax.Array  # int32 [B] the trajectory's last index
    geom: jax.Array  # int32 [B] Geometric(1 - discount) offsets (>= 1)
    step: jax.Array  # int32 [] the update's index (which phase)


def sample(ds, key: jax.Array, cfg: GASConfig, step: jax.Array) -> GASBatch:
    """GAS's batch from a :class:`~aqm_mjx.data.dataset.Dataset` (jittable)."""
    k_gc, k_geom = jax.random.split(key)
    gc = goals.sample_gc(ds, k_gc, cfg.batch_size, cfg.sampling)
    end = ds.traj_end[gc.index]
    ahead = jnp.minimum(gc.index[:, None] + jnp.arange(cfg.waystep_window + 1), end[:, None])
    geom = jax.random.geometric(k_geom, 1.0 - cfg.discount, (cfg.batch_size,)).astype(jnp.int32)
    return GASBatch(gc=gc, ahead=ds.observations[ahead], end=end, geom=geom, step=jnp.asarray(step, jnp.int32))


def skill(phi_s: jax.Array, target: jax.Array) -> jax.Array:
    """GAS's skill: ``(target - phi(s)) / (||target - phi(s)|| + 1e-10)``, ``[..., L]``."""
    v = target - phi_s
    return v / (jnp.linalg.norm(v, axis=-1, keepdims=True) + 1e-10)


def actor_goal_offsets(f: jax.Array, index: jax.Array, end: jax.Array, geom: jax.Array, way_steps: float):
    """``(offset [B], found [B])``: the actor goal's offset ``min(geom, waystep)`` from each source, with
    ``f [B, W + 1, L]`` the embeddings of ``s_{t..t+W}`` (clamped at the trajectory's end). The waystep
    is the first ``k`` with ``||f_k - f_0|| >= way_steps`` within the trajectory; else the trajectory's
    end when the window reaches it, the window's last state otherwise (``found`` False)."""
    w = f.shape[1] - 1
    k = jnp.arange(w + 1)
    inside = index[:, None] + k[None, :] <= end[:, None]
    far = (jnp.linalg.norm(f - f[:, :1], axis=-1) >= way_steps) & inside
    any_far = jnp.any(far, axis=1)
    way = jnp.where(any_far, jnp.argmax(far, axis=1), jnp.minimum(w, end - index))
    return jnp.minimum(geom, way).astype(jnp.int32), any_far | (index + w >= end)


def make(cfg: GASConfig, obs_size: int, action_size: int) -> Learner:
    """GAS's :class:`~aqm_mjx.learn.learner.Learner` (:func:`parts` has its pieces one by one)."""
    return parts(cfg, obs_size, action_size).learner


def parts(cfg: GASConfig, obs_size: int, action_size: int) -> types.SimpleNamespace:
    """GAS's pieces: ``phi(params, obs [B, D]) -> [B, L]``, ``tdr_loss`` and ``policy_loss`` (each
    ``(params, target, GASBatch, key) -> (loss, info)``), ``init``, ``step`` and the ``learner``."""
    tdr = networks.HilbertValue(cfg.value_hidden, cfg.latent, cfg.layer_norm)
    value = networks.Value(cfg.value_hidden, cfg.layer_norm, heads=1)
    critic = networks.Value(cfg.value_hidden, cfg.layer_norm, heads=2)
    actor = networks.Actor(cfg.actor_hidden, action_size, cfg.const_std)
    tx = optax.adam(cfg.lr)
    tdr_steps = cfg.tdr_steps
    x, z0, a0 = jnp.zeros((1, obs_size)), jnp.zeros((1, cfg.latent)), jnp.zeros((1, action_size))

    def phi(p, obs):
        return tdr.apply(p['tdr'], obs, method='phi')

    def init_params(key):
        k = jax.random.split(key, 4)
        return {'tdr': tdr.init(k[0], x, x), 'value': value.init(k[1], x, z0), 'critic': critic.init(k[2], x, z0, a0),
                'actor': actor.init(k[3], x, z0)}

    def tdr_loss(params, target, batch: GASBatch, key):
        """Phase 1: GAS's ``tdr_value_loss`` (OGBench's GCIVL value on the Hilbert heads)."""
        del key
        b = batch.gc
        held = {'tdr': target['tdr']}

        def heads(p, obs, goal):
            return tdr.apply(p['tdr'], obs, goal)

        return losses.ivl_value_loss(heads(params, b.observations, b.value_goals),
                                     heads(held, b.observations, b.value_goals),
                                     heads(held, b.next_observations, b.value_goals), b.rewards, b.masks,
                                     cfg.discount, cfg.tdr_expectile, prefix='tdr')

    def policy_loss(params, target, batch: GASBatch, key):
        """Phase 2: GAS's ``total_critic_actor_loss`` with ``phi`` fixed."""
        b = batch.gc
        fixed = jax.lax.stop_gradient(params)
        n, w1, d = batch.ahead.shape
        f = phi(fixed, batch.ahead.reshape(n * w1, d)).reshape(n, w1, -1)
        phi_s, phi_s1 = f[:, 0], f[:, 1]  # s_{t+1} is the source's next state (sources are never a trajectory's end)
        s, s1, act = b.observations, b.next_observations, b.actions
        z = jax.random.normal(key, phi_s.shape)
        z = z / (jnp.linalg.norm(z, axis=1, keepdims=True) + 1e-10)
        r = jnp.sum((phi_s1 - phi_s) * z, axis=1)
        l_v, v_info = losses.iql_value_loss(critic.apply(target['critic'], s, z, act), value.apply(params['value'], s, z),
                                            cfg.expectile)
        l_q, q_info = losses.iql_critic_loss(critic.apply(params['critic'], s, z, act), value.apply(fixed['value'], s1, z),
                                             r, jnp.ones_like(r), cfg.discount)
        off, found = actor_goal_offsets(f, b.index, batch.end, batch.geom, cfg.way_steps)
        z_actor = skill(phi_s, jnp.take_along_axis(f, off[:, None, None], axis=1)[:, 0])
        mean, log_std = actor.apply(params['actor'], s, z_actor)
        q = critic.apply(fixed['critic'], s, z_actor, jnp.clip(mean, -1.0, 1.0))
        l_a, a_info = losses.ddpgbc_actor_loss(q, policy.log_prob(mean, log_std, act), cfg.alpha)
        return l_v + l_q + l_a, {**v_info, **q_info, **a_info, 'actor/mse': jnp.mean(jnp.square(mean - act)),
                                 'actor/waystep_in_window': jnp.mean(found.astype(jnp.float32)),
                                 'skill/reward_mean': jnp.mean(r)}

    def init(key):
        k_params, k_run = jax.random.split(key)
        params = init_params(k_params)
        return base.State(step=jnp.zeros((), jnp.int32), key=k_run, params=params,
                          target={n: jax.tree.map(jnp.copy, params[n]) for n in ('tdr', 'critic')},
                          opt={'tdr': tx.init({'tdr': params['tdr']}), 'policy': tx.init({n: params[n] for n in POLICY})})

    def phase_step(loss_fn, names, group, targets):
        """One Adam step of the modules ``names`` on ``loss_fn``, with the optimiser state ``group`` (each
        phase has its own, as GAS's two programs), the ``targets`` moved towards the parameters first."""

        def run(state: base.State, batch: GASBatch, k_loss):
            sub = {n: state.params[n] for n in names}
            (_, info), grads = jax.value_and_grad(
                lambda q: loss_fn({**state.params, **q}, state.target, batch, k_loss), has_aux=True)(sub)
            updates, opt = tx.update(grads, state.opt[group], sub)
            target = {**state.target, **{n: base.polyak(state.params[n], state.target[n], cfg.tau) for n in targets}}
            return state.replace(step=state.step + 1, params={**state.params, **optax.apply_updates(sub, updates)},
                                 target=target, opt={**state.opt, group: opt}), info

        return run

    tdr_phase = phase_step(tdr_loss, ('tdr',), 'tdr', ('tdr',))
    policy_phase = phase_step(policy_loss, POLICY, 'policy', ('critic',))

    def with_all(info_fn, *args):
        """``info_fn``'s (state, info) with every metric of both phases (zeros for the other's)."""
        shapes = {**jax.eval_shape(tdr_phase, *args)[1], **jax.eval_shape(policy_phase, *args)[1]}
        state, info = info_fn(*args)
        full = {k: jnp.zeros(v.shape, v.dtype) for k, v in shapes.items()}
        return state, {**full, **info, 'phase': jnp.float32(info_fn is policy_phase)}

    def step(state: base.State, batch: GASBatch, k_loss):
        """One update of the phase ``state.step`` is in."""
        return jax.lax.cond(state.step < tdr_steps, lambda *a: with_all(tdr_phase, *a),
                            lambda *a: with_all(policy_phase, *a), state, batch, k_loss)

    def update(state: base.State, ds):
        key, k_batch, k_loss = jax.random.split(state.key, 3)
        state, info = step(state, sample(ds, k_batch, cfg, state.step), k_loss)
        return state.replace(key=key), info

    def loss(params, target, batch: GASBatch, key):
        """The loss the update at ``batch.step`` differentiates (its phase's)."""
        return jax.lax.cond(batch.step < tdr_steps, lambda: tdr_loss(params, target, batch, key)[0],
                            lambda: policy_loss(params, target, batch, key)[0]), {}

    def encode(p, obs):
        return phi(p, obs[None])[0]

    def dist(p, u, v):
        del p
        return jnp.linalg.norm(u - v)

    def steer(p, obs, phi_s, target):
        """The skill policy's mean toward latent ``target`` from ``obs`` (``phi_s = phi(obs)``)."""
        return actor.apply(p['actor'], obs, skill(phi_s, target))[0]

    def controller(p, obs, goal, t, key):
        """GAS's policy aimed at the goal itself (the flat row)."""
        del t, key
        return steer(p, obs, encode(p, obs), encode(p, goal))

    # GAS's map (every state: aqm_mjx.mapping.gas_nodes) and rule (aqm_mjx.agent.gas_rule), resolved there
    mapper = spec('gas', way_steps=cfg.way_steps, te_threshold=cfg.te_threshold, max_nodes=cfg.max_nodes)
    rule = spec('gas', horizon=float(cfg.way_steps))

    def agent(aux=None) -> Agent:
        return Agent(encode, dist, controller, aux, rule=rule, mapper=mapper, skill=steer)

    def params_of(state):
        return state.params

    learner = Learner(config=cfg, init=init, update=update, params=params_of, agent=agent,
                      modules={'tdr': tdr, 'value': value, 'critic': critic, 'actor': actor}, loss=loss, step=step,
                      distance=to_steps.of_hilbert(encode, cfg.discount, 'log_gamma(1 - (1 - gamma) ||psi(s) - psi(g)||) '
                                                   'of its TDR value'))
    return types.SimpleNamespace(phi=phi, tdr_loss=tdr_loss, policy_loss=policy_loss, init=init, step=step,
                                 learner=learner)


METHODS = (base.Method('gas', GASConfig, make, summary='GAS: TDR graph (TE filter, TD-aware clusters), skill policy '
                       'toward the furthest path node within H',
                       style_defaults={'explore': {'alpha': 0.01}},
                       progress={'tdr/loss': 'tdr', 'critic/loss': 'critic', 'actor/loss': 'actor', 'phase': 'phase'}),)
