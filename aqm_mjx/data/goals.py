"""Goal-conditioned batches drawn on device from a :class:`~aqm_mjx.data.dataset.Dataset`: one
sampler for every method, with per-method goal mixtures (OGBench's ``GCDataset`` and
``HGCDataset`` semantics).

    batch = sample(ds, key, 256, GoalSampling(p_trajectory=1.0, geometric=False))          # AQM
    batch = sample_gc(ds, key, 256, GCSampling(value=GoalSampling(0.2, 0.5, 0.3), actor=...))  # baselines

A goal is drawn from a mixture of the state itself (``p_current``), a later state of the same
trajectory (``p_trajectory``: offset ~ Geometric(1 - discount), or uniform over the rest of the
trajectory) and a uniformly random dataset state (``p_random``). Subgoals are ``s_{min(t + k, cap)}``:
the cap is the trajectory's end (``'end'``) or, for SAW and HIQL's high-level target, the goal's
own index when the goal lies on the trajectory (``'goal'``; a random goal falls back to the end).

Differences from OGBench's host-side sampler, on purpose: uniform trajectory goals are exactly
uniform over ``t + 1 .. end`` (OGBench rounds a continuous draw, which halves the weight of the two
ends), and every draw comes from an explicit key.

Several processes training one run (:func:`aqm_mjx.learn.fit.train` over JAX's multi-controller
runtime) split each batch over their devices: inside a mesh whose axis ``'batch'`` is set
(``jax.set_mesh``), :func:`spread` constrains a batch's leading axis to it, and XLA sums the gradients
across devices; without that mesh it changes nothing.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
from flax import struct

from aqm_mjx.data.dataset import Dataset

CURRENT, TRAJECTORY, RANDOM = 0, 1, 2
SUBGOAL_CAPS = ('end', 'goal')


@dataclasses.dataclass(frozen=True)
class GoalSampling:
    """A goal mixture (OGBench's GCDataset semantics) and the subgoal offset of AQM's sampler."""

    p_current: float = 0.0  # goal = the state itself
    p_trajectory: float = 1.0  # goal = a later state of the same trajectory
    p_random: float = 0.0  # goal = a uniformly random dataset state
    geometric: bool = True  # trajectory goals: offset ~ Geometric(1 - discount) (else uniform over the rest)
    discount: float = 0.99  # of the geometric offsets
    subgoal_offset: int = 25  # subgoal = state t + k, clamped at subgoal_cap
    subgoal_cap: str = 'end'  # 'end': the trajectory's end; 'goal': the goal's index (SAW; random goals: end)

    def __post_init__(self):
        ps = (self.p_current, self.p_trajectory, self.p_random)
        if min(ps) < 0 or abs(sum(ps) - 1.0) > 1e-6:
            raise ValueError(f'goal probabilities must be >= 0 and sum to 1; got {ps}')
        if not 0.0 < self.discount < 1.0:
            raise ValueError(f'discount must be in (0, 1); got {self.discount}')
        if self.subgoal_offset < 1:
            raise ValueError(f'subgoal_offset must be >= 1; got {self.subgoal_offset}')
        if self.subgoal_cap not in SUBGOAL_CAPS:
            raise ValueError(f'subgoal_cap must be one of {SUBGOAL_CAPS}; got {self.subgoal_cap!r}')


def spread(tree):
    """``tree``'s arrays with their leading (batch) axis split over the ``'batch'`` axis of the mesh in
    context (``jax.set_mesh``; data-parallel training), unchanged without one. Values do not change,
    only where XLA computes them."""
    mesh = jax.sharding.get_abstract_mesh()
    if mesh.empty or 'batch' not in mesh.axis_names:
        return tree
    return jax.tree.map(lambda x: jax.lax.with_sharding_constraint(x, jax.sharding.PartitionSpec('batch')), tree)


def goal_indices(keys, idx: jax.Array, end: jax.Array, n_states: int, cfg: GoalSampling):
    """Goal indices for sources ``idx [B]`` whose trajectories end at ``end [B]``.

    Args:
        keys: ``(kind, offset, random)`` keys.
    Returns:
        ``(goal [B] int32, kind [B] int32)``, kind 0 current, 1 trajectory, 2 random.
    """
    k_kind, k_off, k_rand = keys
    n = idx.shape[0]
    if cfg.geometric:
        off = jax.random.geometric(k_off, 1.0 - cfg.discount, (n,)).astype(jnp.int32)  # >= 1
        traj_goal = jnp.minimum(idx + off, end)
    else:
        u = jax.random.uniform(k_off, (n,))
        traj_goal = jnp.minimum(idx + 1 + jnp.floor(u * (end - idx)).astype(jnp.int32), end)
    rand_goal = jax.random.randint(k_rand, (n,), 0, n_states)
    kind = jax.random.choice(k_kind, 3, (n,), p=jnp.array([cfg.p_current, cfg.p_trajectory, cfg.p_random]))
    goal = jnp.where(kind == CURRENT, idx, jnp.where(kind == TRAJECTORY, traj_goal, rand_goal))
    return goal.astype(jnp.int32), kind.astype(jnp.int32)


def subgoal_indices(idx: jax.Array, end: jax.Array, k: int, goal=None, kind=None) -> jax.Array:
    """``min(t + k, cap)`` for ``idx, end [B]``: cap = ``end``, or with ``goal, kind [B]`` the goal's
    index unless it is a random goal (SAW's ``s_{min(t+k, goal index)}``, HIQL's high target)."""
    cap = end if goal is None else jnp.where(kind == RANDOM, end, goal)
    return jnp.minimum(idx + k, cap).astype(jnp.int32)


def sources(ds: Dataset, key: jax.Array, batch_size: int) -> jax.Array:
    """``[B]`` uniform transition sources (states with a successor in their trajectory)."""
    return ds.valid_index[jax.random.randint(key, (batch_size,), 0, ds.valid_index.shape[0])]


# ------------------------------------------------------------------------------------------ AQM
@struct.dataclass
class Batch:
    """A sampled batch; every field has a leading ``[B]``. ``*_index`` are dataset indices."""

    observations: jax.Array
    actions: jax.Array
    next_observations: jax.Array
    goals: jax.Array
    subgoals: jax.Array
    index: jax.Array
    goal_index: jax.Array
    subgoal_index: jax.Array
    goal_kind: jax.Array  # 0 current, 1 trajectory, 2 random


def sample(ds: Dataset, key: jax.Array, batch_size: int, cfg: GoalSampling = GoalSampling()) -> Batch:
    """Transitions with one goal each and the subgoal ``s_{min(t + k, cap)}`` (AQM's sampler; cap
    from ``cfg.subgoal_cap``); jittable (``batch_size`` and ``cfg`` static)."""
    k_idx, k_kind, k_off, k_rand = jax.random.split(key, 4)
    idx = sources(ds, k_idx, batch_size)
    end = ds.traj_end[idx]
    goal, kind = goal_indices((k_kind, k_off, k_rand), idx, end, ds.size, cfg)
    capped = cfg.subgoal_cap == 'goal'
    sub = subgoal_indices(idx, end, cfg.subgoal_offset, goal if capped else None, kind if capped else None)
    obs = ds.observations
    return spread(Batch(observations=obs[idx], actions=ds.actions[idx], next_observations=obs[idx + 1],
                        goals=obs[goal], subgoals=obs[sub], index=idx, goal_index=goal, subgoal_index=sub,
                        goal_kind=kind))


# ------------------------------------------------------------------------------ the OGBench family
@dataclasses.dataclass(frozen=True)
class GCSampling:
    """Value goals, actor goals and subgoals of one method (OGBench's ``value_p_*`` / ``actor_p_*``)."""

    value: GoalSampling = GoalSampling(p_current=0.2, p_trajectory=0.5, p_random=0.3)
    actor: GoalSampling = GoalSampling(p_trajectory=1.0, geometric=False)
    subgoal_offset: int = 25  # k of the subgoals
    subgoal_cap: str = 'goal'  # 'goal': s_{min(t+k, actor goal index)} (SAW, HIQL); 'end': trajectory end

    def __post_init__(self):
        if self.subgoal_offset < 1:
            raise ValueError(f'subgoal_offset must be >= 1; got {self.subgoal_offset}')
        if self.subgoal_cap not in SUBGOAL_CAPS:
            raise ValueError(f'subgoal_cap must be one of {SUBGOAL_CAPS}; got {self.subgoal_cap!r}')


@struct.dataclass
class GCBatch:
    """A batch for value and actor learning; every field has a leading ``[B]``.

    ``rewards`` and ``masks`` follow OGBench's ``gc_negative``: reward 0 and mask 0 where the value
    goal is the state itself, else reward -1 and mask 1.
    """

    observations: jax.Array  # [B, D]
    actions: jax.Array  # [B, A]
    next_observations: jax.Array  # [B, D]
    value_goals: jax.Array  # [B, D]
    rewards: jax.Array  # [B]
    masks: jax.Array  # [B]
    actor_goals: jax.Array  # [B, D]
    subgoals: jax.Array  # [B, D] s_{min(t + k, cap)}, cap from subgoal_cap and the actor goal
    low_goals: jax.Array  # [B, D] s_{min(t + k, end)} (HIQL's low-level goal)
    index: jax.Array  # int32 [B]
    value_goal_index: jax.Array
    value_kind: jax.Array
    actor_goal_index: jax.Array
    actor_kind: jax.Array
    subgoal_index: jax.Array


def sample_gc(ds: Dataset, key: jax.Array, batch_size: int, cfg: GCSampling = GCSampling()) -> GCBatch:
    """Transitions with a value goal, an actor goal and subgoals; jittable (``batch_size``, ``cfg`` static)."""
    k_idx, k_value, k_actor = jax.random.split(key, 3)
    idx = sources(ds, k_idx, batch_size)
    end = ds.traj_end[idx]
    vg, vk = goal_indices(jax.random.split(k_value, 3), idx, end, ds.size, cfg.value)
    ag, ak = goal_indices(jax.random.split(k_actor, 3), idx, end, ds.size, cfg.actor)
    capped = cfg.subgoal_cap == 'goal'
    sub = subgoal_indices(idx, end, cfg.subgoal_offset, ag if capped else None, ak if capped else None)
    low = subgoal_indices(idx, end, cfg.subgoal_offset)
    at_goal = (vg == idx).astype(jnp.float32)
    obs = ds.observations
    return spread(GCBatch(observations=obs[idx], actions=ds.actions[idx], next_observations=obs[idx + 1],
                          value_goals=obs[vg], rewards=at_goal - 1.0, masks=1.0 - at_goal, actor_goals=obs[ag],
                          subgoals=obs[sub], low_goals=obs[low], index=idx, value_goal_index=vg, value_kind=vk,
                          actor_goal_index=ag, actor_kind=ak, subgoal_index=sub))
