"""Episodes of the AQM agent, vectorised: physics, encoder, the agent's rules (:mod:`.rules`) and
the controller in one jitted program, ``lax.scan`` over control steps and ``vmap`` over
environments, with no host round trip per step.

    run = make_rollout(env, agent, AgentConfig(), steps=1000)
    out = jax.jit(run)(agent.aux, graph, episode_inputs(episode_keys(key, ids), task_ids, grids, kappa, use_graph))

Each environment carries its own task, walls, budget slack, budget rule, parallel cuts and whether
it uses the graph, so ablations (no pruning: ``kappa = inf``; the flat policy: ``use_graph = False``;
the stall rule: ``patience > 0``; the paper's rule: ``edges_only``, ``cut_slack = 0``) and shifted
layouts are rows of one batch.
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple, Optional

import jax
import jax.numpy as jnp
import numpy as np

from aqm_mjx.agent.rules import (LEG_FIELDS, MAX_CUTS, MAX_LEGS, AgentConfig, agent_init, agent_step, follow,
                                  keep_last_route, reenters, redirect, replan)
from aqm_mjx.agent import planners
from aqm_mjx.interface import Agent, Decide
from aqm_mjx.progress import EVERY, tick
from aqm_mjx.mapping.graph import Graph


class EpisodeInputs(NamedTuple):
    """Per-environment inputs of a rollout; a leading ``[B]`` on every field."""

    keys: jax.Array  # uint32 [B, 2, 2]: (reset, action) keys
    task_ids: jax.Array  # int32 [B]: OGBench task ids (1-based)
    grids: jax.Array  # int8 [B, H, W]: each environment's maze
    kappa: jax.Array  # float32 [B]: budget slack (inf: no pruning)
    use_graph: jax.Array  # bool [B]: False: the flat policy
    patience: jax.Array  # float32 [B]: 0 the fixed budget (1 + kappa) d; > 0 the stall rule's patience
    edges_only: jax.Array  # bool [B]: budget keypoint edges alone (the paper's rule), not start and goal legs
    cut_slack: jax.Array  # float32 [B]: parallel cuts (0: the overrun edge alone); read when AgentConfig.cut_slack > 0
    cells: jax.Array  # int32 [B, 4]: start and goal cells (i, j, i, j) of task-0 episodes (calibration)


def episode_keys(key: jax.Array, ids) -> jax.Array:
    """``[E, 2, 2]`` (reset, action) keys, episode ``i`` from ``fold_in(key, ids[i])``: an episode's
    keys depend on its id alone, not on the batch, the chunking or the number of devices."""
    return jax.vmap(lambda i: jax.random.split(jax.random.fold_in(key, i), 2))(jnp.asarray(ids, jnp.int32))


def episode_inputs(keys, task_ids, grids, kappa, use_graph, patience=0.0, edges_only=False, cut_slack=0.0,
                   cells=None) -> EpisodeInputs:
    """:class:`EpisodeInputs` with fixed dtypes (uint32, int32, int8, float32, bool, float32, bool,
    float32, int32), so that new tasks, seeds, walls, kappas or rules never change the compiled
    signature. ``grids`` may be one ``[H, W]`` maze, ``kappa``, ``use_graph``, ``patience``,
    ``edges_only`` and ``cut_slack`` scalars: they are broadcast. ``cells`` (default zeros) are read
    for task id 0 only."""
    task_ids = jnp.asarray(task_ids, jnp.int32)
    n = task_ids.shape[0]
    grids = jnp.asarray(grids, jnp.int8)
    if grids.ndim == 2:
        grids = jnp.broadcast_to(grids, (n,) + grids.shape)
    cells = jnp.zeros((n, 4), jnp.int32) if cells is None else jnp.asarray(cells, jnp.int32).reshape(n, 4)
    return EpisodeInputs(keys=jnp.asarray(keys), task_ids=task_ids, grids=grids,
                         kappa=jnp.broadcast_to(jnp.asarray(kappa, jnp.float32), (n,)),
                         use_graph=jnp.broadcast_to(jnp.asarray(use_graph, bool), (n,)),
                         patience=jnp.broadcast_to(jnp.asarray(patience, jnp.float32), (n,)),
                         edges_only=jnp.broadcast_to(jnp.asarray(edges_only, bool), (n,)),
                         cut_slack=jnp.broadcast_to(jnp.asarray(cut_slack, jnp.float32), (n,)), cells=cells)


def freeze(live: jax.Array, old, new):
    """``new`` where ``live [B]``, else ``old`` (leaf by leaf); a frozen agent asks for no replan."""
    new = new.replace(needs_replan=new.needs_replan & live)
    return jax.tree.map(lambda o, n: jnp.where(live.reshape(live.shape + (1,) * (n.ndim - 1)), n, o), old, new)


def make_decide(agent: Agent, cfg: AgentConfig) -> Decide:
    """The PLAN and ACT half of a control step of ``agent`` (see :func:`make_rollout`)."""
    slots = cfg.slots
    if agent.rule is not None:  # a method's own rule (GAS's, HILP's planning), resolved in the registry
        return planners.decide(agent)
    if not agent.plans:
        def init_flat(aux, graph, obs, goal, inputs):
            return ()

        def act_flat(aux, graph, agents, obs, goal, done, t, inputs):
            keys_t = jax.vmap(lambda k: jax.random.fold_in(k, t))(inputs.keys[:, 1])
            actions = jax.vmap(lambda o, g, k: agent.controller(aux, o, g, t, k))(obs, goal, keys_t)
            return jnp.clip(actions, -1.0, 1.0), agents

        return Decide(init_flat, act_flat)

    def init(aux, graph, obs, goal, inputs):
        d = lambda x, y: agent.dist(aux, x, y)  # noqa: E731
        enc = jax.vmap(lambda o: agent.encode(aux, o))
        return jax.vmap(lambda s, g, kp, u, p, e: agent_init(d, graph, s, g, kp, u, p, e))(
            enc(obs), enc(goal), inputs.kappa, inputs.use_graph, inputs.patience, inputs.edges_only)

    def act(aux, graph, agents, obs, goal, done, t, inputs):
        d = lambda x, y: agent.dist(aux, x, y)  # noqa: E731
        kappa, patience, edges = inputs.kappa, inputs.patience, inputs.edges_only
        enc = jax.vmap(lambda o: agent.encode(aux, o))
        # FOLLOW, BUDGET, PRUNE per environment (rules.agent_step); an environment whose episode is
        # done (at the goal, or at its limit) keeps its agent as it was, so that nothing is timed, cut
        # or logged after the end
        z = enc(obs)

        # d(s, target) once a step, for both the re-attachment's test and the step itself
        followed = jax.vmap(lambda a, s: follow(d, graph, cfg, a, s))(agents, z)

        def step(attach):
            if cfg.cut_slack:  # EXTENSION: parallel cuts, each row at its own slack
                one = lambda a, s, kp, p, e, c, f: agent_step(d, graph, cfg, a, s, kp, p, e, c, attach, f)  # noqa: E731
                return lambda: jax.vmap(one)(agents, z, kappa, patience, edges, inputs.cut_slack, followed)
            # no row cuts in parallel (every row's slack is 0): the neighbourhoods are not computed
            one = lambda a, s, kp, p, e, f: agent_step(d, graph, cfg, a, s, kp, p, e, 0.0, attach, f)  # noqa: E731
            return lambda: jax.vmap(one)(agents, z, kappa, patience, edges, followed)

        # the K distances of a re-attachment only in a step where some environment overran its start leg
        needs = jax.vmap(lambda a, s, p, f: reenters(d, graph, cfg, a, s, p, f))(agents, z, patience, followed)
        stepped = jax.lax.cond(jnp.any(needs), step(True), step(False))
        # REPLAN where an edge was cut (batched over those environments), then take the next hop
        new = replan(freeze(~done, agents, stepped), slots)
        if cfg.keep_route:  # EXTENSION: a cut that leaves no route to the goal is not made
            new = jax.vmap(keep_last_route)(agents, new)
        agents = jax.vmap(redirect)(new, kappa, patience, edges)
        sub = jnp.where((agents.node >= 0)[:, None], graph.obs[jnp.maximum(agents.node, 0)], goal)
        # ACT
        keys_t = jax.vmap(lambda k: jax.random.fold_in(k, t))(inputs.keys[:, 1])
        actions = jax.vmap(lambda o, g, k: agent.controller(aux, o, g, t, k))(obs, sub, keys_t)
        return jnp.clip(actions, -1.0, 1.0), agents

    return Decide(init, act)


def make_rollout(env, agent: Agent, cfg: AgentConfig, steps: int, record_actions: bool = False,
                 progress: Optional[Callable] = None, every: int = EVERY):
    """Build the jittable episode program of ``agent`` in ``env``: per control step the agent's
    :func:`make_decide` half, then ``env.step``.

    Args:
        env: a :class:`aqm_mjx.envs.MazeEnv`.
        agent: its functions are used; parameters come as ``aux`` at call time.
        cfg: the agent's rules; steps: control steps per episode.
        record_actions: also return the clipped actions ``[T, B, A]`` (benchmarks replay them).
        progress: a host hook called with the steps done every ``every`` control steps and at the
            end (:func:`aqm_mjx.progress.tick`); None: no callback in the program.
    An agent without a quasimetric (``agent.dist`` None: the flat baselines) gets a program that
    aims its controller at the goal and ignores ``graph`` (which may be None).
    Returns:
        ``run(aux, graph, inputs: EpisodeInputs) -> dict`` with ``success [B]`` (at the goal at the
        last step), ``pruned [B]`` (legs overrun), ``removed [B]`` (keypoint edges cut), ``cuts [B,
        MAX_CUTS, 2]``, ``legs [B, MAX_LEGS, LEG_FIELDS]`` (completed legs: d, steps, longest stall,
        kind; -1 padded),
        ``n_legs [B]``, ``xy [T, B, 2]``, ``node [T, B]``
        and ``goal_xy [B, 2]``.
    """
    decide = make_decide(agent, cfg)
    plans = agent.plans

    def run(aux: Any, graph: Graph, inputs: EpisodeInputs):
        states = jax.vmap(env.reset)(inputs.keys[:, 0], inputs.task_ids, inputs.grids, inputs.cells)
        agents = decide.init(aux, graph, states.obs, states.goal, inputs)
        no_node = jnp.full(inputs.task_ids.shape, -1, jnp.int32)

        def body(carry, t):
            states, agents = carry
            actions, agents = decide.act(aux, graph, agents, states.obs, states.goal, states.done, t, inputs)
            states = jax.vmap(env.step)(states, actions)  # STEP
            trace = (states.data.qpos[:, :2], agents.node if plans else no_node) + (
                (actions,) if record_actions else ())
            tick(progress, t, steps, every)
            return (states, agents), trace

        (states, agents), trace = jax.lax.scan(body, (states, agents), jnp.arange(steps))
        out = dict(success=states.success, xy=trace[0], node=trace[1], goal_xy=states.goal_xy,
                   **plan_outputs(agents, inputs.task_ids.shape[0], jnp))
        if record_actions:
            out['actions'] = trace[2]
        return out

    return run


def plan_outputs(agents, b: int, xp=np) -> dict:
    """The agent-state outputs of a rollout: ``pruned [B]``, ``removed [B]``, ``cuts [B, MAX_CUTS, 2]``,
    ``legs [B, MAX_LEGS, LEG_FIELDS]``, ``n_legs [B]`` from ``agents``, or nothing pruned, cut or logged for an agent
    without a quasimetric (``agents == ()``). ``xp``: ``jnp`` inside a program, ``np`` on the host."""
    if not hasattr(agents, 'pruned'):  # no quasimetric (``()``), or a rule that never prunes (GAS's)
        return dict(pruned=xp.zeros((b,), xp.int32), removed=xp.zeros((b,), xp.int32),
                    cuts=xp.full((b, MAX_CUTS, 2), -1, xp.int32), legs=xp.full((b, MAX_LEGS, LEG_FIELDS), -1.0, xp.float32),
                    n_legs=xp.zeros((b,), xp.int32))
    return {k: xp.asarray(getattr(agents, k)) for k in ('pruned', 'removed', 'cuts', 'legs', 'n_legs')}


def make_host_rollout(envs, agent: Agent, cfg: AgentConfig, steps: int, progress: Optional[Callable] = None,
                      every: int = EVERY):
    """:func:`make_rollout`'s program with the physics on the host: ``envs`` (an
    :class:`aqm_mjx.envs.ogbench_env.OGBenchEnvs`, OGBench's own environments) step in lockstep and
    the agent's :func:`make_decide` half runs as one jitted, batched call per control step; the agent
    state stays a batched pytree on the device.

    Episode ``i`` is reset with an integer seed drawn from its reset key (``inputs.keys[i, 0]``),
    so it depends on its key alone; its actions use the same keys as the MJX program's.
    Returns ``run(aux, graph, inputs) -> dict`` with :func:`make_rollout`'s outputs (numpy).
    """
    decide = make_decide(agent, cfg)
    init, act = jax.jit(decide.init), jax.jit(decide.act)
    plans = agent.plans
    seed_of = jax.jit(jax.vmap(lambda k: jax.random.randint(k, (), 0, jnp.iinfo(jnp.int32).max)))

    def run(aux: Any, graph, inputs: EpisodeInputs) -> dict:
        seeds = np.asarray(seed_of(inputs.keys[:, 0]))
        obs, goal, goal_xy = envs.reset(seeds, np.asarray(inputs.task_ids), np.asarray(inputs.grids),
                                        np.asarray(inputs.cells))
        b = len(seeds)
        goal_d = jnp.asarray(goal)
        agents = init(aux, graph, jnp.asarray(obs), goal_d, inputs)
        xy, node = np.zeros((steps, b, 2), np.float32), np.full((steps, b), -1, np.int32)
        done = np.zeros(b, bool)
        for t in range(steps):
            actions, agents = act(aux, graph, agents, jnp.asarray(obs), goal_d, jnp.asarray(done), jnp.int32(t),
                                  inputs)
            obs, xy[t], success, done = envs.step(np.asarray(actions))
            if plans:
                node[t] = np.asarray(agents.node)
            if done.all():  # every episode ended: the rest of the trace stands still, as MJX's would
                xy[t + 1:], node[t + 1:] = xy[t], node[t]
                if progress is not None:
                    progress(steps)
                break
            if progress is not None and ((t + 1) % every == 0 or t + 1 == steps):
                progress(t + 1)
        return dict(success=success.astype(np.float32), xy=xy, node=node, goal_xy=goal_xy, **plan_outputs(agents, b))

    def warm(aux: Any, graph, inputs: EpisodeInputs) -> None:
        """Compile the agent's calls for this batch shape (no physics): benchmarks time it apart."""
        b, o = inputs.task_ids.shape[0], envs.obs_size
        z = jnp.zeros((b, o), jnp.float32)
        agents = init(aux, graph, z, z, inputs)
        jax.block_until_ready(act(aux, graph, agents, z, z, jnp.zeros(b, bool), jnp.int32(0), inputs))
        jax.block_until_ready(seed_of(inputs.keys[:, 0]))

    run.warm = warm
    return run
