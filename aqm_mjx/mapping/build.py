"""The map stage: dataset states -> candidates -> latents -> keypoints -> graph (one pure function).

    graph, kp = build_map(agent, observations, MapConfig(delta=8.0), key)        # jittable
    graph, info = trimmed_map(agent, observations, MapConfig(delta=8.0), key)    # jitted, trimmed (host)
"""

from __future__ import annotations

import dataclasses
import math
import functools
import time
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from aqm_mjx import config as cfg_lib
from aqm_mjx import presets
from aqm_mjx.config import option
from aqm_mjx.data.dataset import trajectory_ends
from aqm_mjx.interface import Agent
from aqm_mjx.mapping import gas_nodes, states, ttgs_nodes
from aqm_mjx.mapping import keypoints as kps
from aqm_mjx.mapping.graph import Graph, build_graph, trim


def _iwe(dist, latents, key, cfg, valid):
    return kps.iwe(dist, latents, key, cfg.delta, cfg.max_keypoints, valid)


def _iwe_batches(dist, latents, key, cfg, valid):
    if valid is not None:
        raise ValueError("selector 'iwe-batches' draws its own candidate batches and takes no validity mask")
    return kps.iwe_best_of_batches(dist, latents, key, cfg.delta, cfg.max_keypoints, cfg.iwe_batches,
                                   cfg.iwe_batch_size)


def _fps(dist, latents, key, cfg, valid):
    return kps.farthest_point(dist, latents, key, cfg.delta, cfg.max_keypoints, valid)


def _random(dist, latents, key, cfg, valid):
    del dist
    return kps.uniform_random(latents, key, cfg.max_keypoints, valid)


# name -> (dist, latents [N, L], key, MapConfig, valid [N] or None) -> Keypoints
SELECTORS = {'iwe': _iwe, 'iwe-batches': _iwe_batches, 'fps': _fps, 'random': _random}


@dataclasses.dataclass(frozen=True)
class MapConfig:
    """How the keypoint graph is built (paper section 4.3, Appendix 11.5-11.7)."""

    delta: float = option(presets.default('map', 'delta'),
                          "IWE repel radius in the quasimetric's units (control steps); paper: 10-25")
    tau: float = option(0.0, 'edge and attachment radius; 0: 2 delta (the paper\'s proxy)')
    max_keypoints: int = option(256, 'static K: keypoint slots (a mask says which are used)')
    candidates: int = option(10_000, 'dataset states drawn uniformly and encoded as candidates')
    selector: str = option('iwe', "'iwe' (Algorithm 2 over every candidate), 'iwe-batches' (the paper's "
                           "App. 11.7: IWE on random batches, the one with most keypoints), 'fps', 'random' "
                           '(max_keypoints uniform picks)', tuple(SELECTORS))
    iwe_batches: int = option(8, 'iwe-batches: number of random candidate batches')
    iwe_batch_size: int = option(1024, "iwe-batches: candidates per batch (the paper's 1024)")

    def __post_init__(self):
        cfg_lib.check_types(self)
        cfg_lib.check_positive_int(self, 'max_keypoints', 'candidates', 'iwe_batches', 'iwe_batch_size')
        if not (math.isfinite(self.delta) and self.delta > 0):
            raise ValueError(f'MapConfig.delta must be a finite number > 0; got {self.delta}')
        if not (math.isfinite(self.tau) and self.tau >= 0):
            raise ValueError(f'MapConfig.tau must be a finite number >= 0 (0: twice delta); got {self.tau}')
        cfg_lib.check_choice('MapConfig', 'selector', self.selector, tuple(SELECTORS))

    @property
    def edge_radius(self) -> float:
        """tau: the edge radius of the graph and the attachment radius of starts and goals."""
        return self.tau if self.tau > 0 else 2.0 * self.delta


def keypoint_graph(dist, latents: jax.Array, observations: jax.Array, key: jax.Array, cfg: MapConfig,
                   valid: jax.Array | None = None) -> tuple[Graph, kps.Keypoints]:
    """Select keypoints among encoded states and join them (pure, jittable).

    Args:
        dist: pairwise latent quasimetric ``d(x [L], y [L]) -> scalar``.
        latents: ``[N, L]`` encoded candidates; observations: ``[N, D]`` the same states.
        valid: optional bool ``[N]`` real candidates (not for ``iwe-batches``).
    Returns:
        (:class:`Graph` with ``[K, ...]`` arrays, invalid slots zero with ``inf`` edges, ``tau`` the
        edge radius; the :class:`~aqm_mjx.mapping.keypoints.Keypoints` selected).
    """
    kp = SELECTORS[cfg.selector](dist, latents, key, cfg, valid)
    return _joined(dist, latents, observations, kp, cfg), kp


def _joined(dist, latents: jax.Array, observations: jax.Array, kp: kps.Keypoints, cfg: MapConfig) -> Graph:
    """The :class:`Graph` of keypoints ``kp`` among the encoded candidates: their states and tau edges."""
    idx = jnp.maximum(kp.index, 0)
    keep = kp.mask[:, None]
    z = jnp.where(keep, latents[idx], 0.0)
    obs = jnp.where(keep, observations[idx], 0.0)
    tau = cfg.edge_radius
    w = build_graph(dist, z, kp.mask, cfg.delta, tau=tau)
    return Graph(z=z, obs=obs, mask=kp.mask, w=w, tau=jnp.float32(tau))


def build_map(agent: Agent, observations: jax.Array, cfg: MapConfig, key: jax.Array,
              aux: Any = None) -> tuple[Graph, kps.Keypoints]:
    """Keypoints and graph from dataset states (pure, jittable; ``aux`` defaults to the agent's).

    Args:
        observations: ``[N, D]`` dataset states; ``min(N, cfg.candidates)`` of them, drawn uniformly
            without replacement, are encoded as candidates.
    Returns:
        (:class:`Graph`, :class:`~aqm_mjx.mapping.keypoints.Keypoints` with indices into the candidates).
    """
    aux = agent.aux if aux is None else aux
    cand, lat, kp = select_keypoints(agent, observations, cfg, key, aux)
    return _joined(lambda x, y: agent.dist(aux, x, y), lat, cand, kp, cfg), kp


def select_keypoints(agent: Agent, observations: jax.Array, cfg: MapConfig, key: jax.Array,
                     aux: Any = None) -> tuple[jax.Array, jax.Array, kps.Keypoints]:
    """The keypoints :func:`build_map` selects under ``key``, without joining them (pure, jittable):
    ``(candidates [M, D], their latents [M, L], Keypoints)``, ``M = n_candidates(N, cfg)``."""
    aux = agent.aux if aux is None else aux
    k_sel = jax.random.split(key)[1]
    cand = observations[candidate_rows(observations.shape[0], cfg, key)]
    lat = jax.vmap(lambda o: agent.encode(aux, o))(cand)
    return cand, lat, SELECTORS[cfg.selector](lambda x, y: agent.dist(aux, x, y), lat, k_sel, cfg, None)


def n_candidates(n: int, cfg: MapConfig) -> int:
    """How many of ``n`` dataset states :func:`build_map` encodes as candidates: ``min(n, cfg.candidates)``."""
    return min(int(n), int(cfg.candidates))


def candidate_rows(n: int, cfg: MapConfig, key: jax.Array) -> jax.Array:
    """Rows of ``n`` dataset states that :func:`build_map` encodes as candidates under ``key``:
    :func:`n_candidates` of them drawn uniformly without replacement (all of them, in order, when
    there are no more). A file of exactly these states, in this order, gives the same map."""
    m = n_candidates(n, cfg)
    return jax.random.permutation(jax.random.split(key)[0], n)[:m] if m < n else jnp.arange(n)


@functools.lru_cache(maxsize=16)
def _jitted_build(agent_fns: tuple, cfg: MapConfig):
    encode, dist = agent_fns
    agent = Agent(encode, dist, None)
    return jax.jit(lambda aux, obs, key: build_map(agent, obs, cfg, key, aux))


def _trim_to_count(graph: Graph, count: int) -> Graph:
    """``graph`` cut to its ``count`` used slots rounded up to 8 (at most its size), host side."""
    return trim(graph, min(graph.mask.shape[0], -(-count // 8) * 8))


def trimmed_map(agent: Agent, observations, cfg: MapConfig, key: jax.Array, static: bool = False) -> tuple[Graph, dict]:
    """:func:`build_map` jitted (one compile per agent functions and config), then trimmed to the
    keypoint count rounded up to 8 (host side): the rollout's cost grows with K, so the padded
    ``cfg.max_keypoints`` slots are cut to the ones used. ``static=True`` keeps every slot (a static
    shape: one compiled evaluation for maps of any count, as a learning curve needs).

    Returns:
        (trimmed graph, ``{'keypoints': count, 'overflow': bool, 'uncovered': int, 'candidates': int,
        'seconds': float}``): ``uncovered`` of the ``candidates`` encoded states were left outside every
        keypoint's delta when the slots ran out (0 without overflow).
    """
    t0 = time.perf_counter()
    build = _jitted_build((agent.encode, agent.dist), cfg)
    graph, kp = build(agent.aux, jnp.asarray(observations), key)
    n_kp = int(kp.count)
    graph = graph if static else _trim_to_count(graph, n_kp)
    return graph, dict(keypoints=n_kp, overflow=bool(kp.overflow), uncovered=int(kp.uncovered),
                       candidates=n_candidates(np.shape(observations)[0], cfg),
                       seconds=time.perf_counter() - t0)


def own_map(agent: Agent, aux, observations: jax.Array, traj_end: jax.Array, max_len: int, key: jax.Array):
    """A method's own map (``agent.mapper``, a :func:`~aqm_mjx.interface.spec`) from a dataset's
    states: ``(map, count, overflow)`` (jittable; ``max_len`` static, the longest trajectory).

    ``('gas', way_steps, te_threshold, max_nodes)``: GAS's graph of every state
    (:func:`aqm_mjx.mapping.gas_nodes.gas_map`); ``('hilp', states)``: HILP's planning states
    (:func:`aqm_mjx.mapping.states.planning_states`); ``('ttgs', nodes, tau)``: TTGS's dense map of
    random states on the agent's distance (:func:`aqm_mjx.mapping.ttgs_nodes.ttgs_map`).
    """
    name, settings = agent.mapper
    kw = dict(settings)
    if name == 'gas':
        return gas_nodes.gas_map(agent.encode, aux, observations, traj_end, max_len, **kw)
    if name == 'hilp':
        return states.planning_states(agent.encode, aux, observations, key, **kw), kw['states'], jnp.bool_(False)
    if name == 'ttgs':
        graph = ttgs_nodes.ttgs_map(agent.encode, agent.dist, aux, observations, key, **kw)
        return graph, graph.mask.shape[0], jnp.bool_(False)
    raise ValueError(f'unknown map {name!r} (known: gas, hilp, ttgs)')


@functools.lru_cache(maxsize=8)
def _jitted_own_map(encode, dist, mapper, max_len: int):
    agent = Agent(encode, dist, None, mapper=mapper)
    return jax.jit(lambda aux, obs, ends, key: own_map(agent, aux, obs, ends, max_len, key))


def method_map(agent: Agent, data: dict, cfg: MapConfig, key: jax.Array, static: bool = False) -> tuple[Graph, dict]:
    """The map an agent plans on, from a dataset's arrays (``observations``, ``terminals``): the
    method's own (``agent.mapper``, GAS's, from every state) or keypoints (:func:`trimmed_map`), trimmed
    to the node count rounded up to 8 (``static=True``: every slot). Returns :func:`trimmed_map`'s
    ``(graph, info)``."""
    if agent.mapper is None:
        return trimmed_map(agent, data['observations'], cfg, key, static)
    t0 = time.perf_counter()
    ends = trajectory_ends(data['terminals'])
    starts = np.concatenate([[0], np.flatnonzero(np.diff(ends)) + 1])
    build = _jitted_own_map(agent.encode, agent.dist, agent.mapper, int(np.max(ends[starts] - starts + 1)))
    graph, count, overflow = build(agent.aux, jnp.asarray(data['observations'], jnp.float32), jnp.asarray(ends), key)
    n = int(count)
    if isinstance(graph, Graph) and not static:
        graph = _trim_to_count(graph, max(n, 1))
    return graph, dict(keypoints=n, overflow=bool(overflow), seconds=time.perf_counter() - t0)


CHECK_OFFSET = 25  # steps of data the distance check compares with one step
CHECK_SCALE = 10.0  # how far from CHECK_OFFSET the median may read before the units are called wrong


def distances_along(agent: Agent, observations, terminals, key: jax.Array, offsets, pairs: int = 256) -> dict | None:
    """A distance along the data's own trajectories: ``{k: d(s_t, s_{t+k}) [P]}`` for each offset ``k``
    (``k = 0``: ``d(s_t, s_t)``), over ``P = min(pairs, ...)`` states ``s_t`` drawn with ``key`` among those
    with ``max(offsets)`` more states in their trajectory; None when the data hold no trajectory that long.
    What :func:`distance_check` tests and ``benchmarks/experiments/distance_profile.py`` prints."""
    obs = np.asarray(observations, np.float32)
    ends = trajectory_ends(np.asarray(terminals))
    ok = np.flatnonzero(ends - np.arange(len(obs)) >= max(offsets))
    if not len(ok):
        return None
    t = np.asarray(jax.random.choice(key, jnp.asarray(ok), (min(pairs, len(ok)),), replace=False))
    enc = jax.jit(jax.vmap(lambda o: agent.encode(agent.aux, o)))
    dist = jax.jit(jax.vmap(lambda x, y: agent.dist(agent.aux, x, y)))
    z0 = enc(obs[t])
    return {k: np.asarray(dist(z0, z0 if k == 0 else enc(obs[t + k]))) for k in offsets}


def distance_check(agent: Agent, observations, terminals, key: jax.Array, name: str = 'the method',
                   pairs: int = 256) -> dict | None:
    """Check a distance before a map is built on it: along the data's own trajectories, ``d`` must
    grow with the steps between two states (``median d(s_t, s_{t+25}) > median d(s_t, s_{t+1})``;
    a value of the wrong sign, one that learned nothing, or one too coarse to resolve 25 steps fails)
    and read 25 steps as steps (the median within a factor 10 of 25; a distance in other units fails).
    ``pairs`` states ``s_t`` with 25 more states in their trajectory are drawn with ``key``
    (:func:`distances_along`).

    Returns ``{'d0', 'd1', 'd25'}`` (the medians of d(s, s), d(s_t, s_{t+1}), d(s_t, s_{t+25})), or
    None when the data hold no trajectory that long (a shipped checkpoint's map states: nothing to
    check on); raises a one-line ValueError naming ``name`` and the numbers when either test fails."""
    d = distances_along(agent, observations, terminals, key, (0, 1, CHECK_OFFSET), pairs)
    if d is None:
        return None
    out = {'d0': float(np.median(d[0])), 'd1': float(np.median(d[1])), 'd25': float(np.median(d[CHECK_OFFSET]))}
    numbers = (f'median d(s, s) {out["d0"]:.3g}, over 1 step {out["d1"]:.3g}, over {CHECK_OFFSET} steps '
               f'{out["d25"]:.3g}, on {len(d[0])} pairs of the data')
    if not np.isfinite(out['d25']) or not out['d25'] > out['d1']:
        raise ValueError(f'the distance of {name} does not grow along the data\'s trajectories ({numbers}): a value of '
                         'the wrong sign, one that learned nothing, or one too coarse to tell 1 step from 25 (a contrastive '
                         'critic at small scale: benchmarks/experiments/distance_profile.py); no map is built on it '
                         '(--set agent.distance_check=false to build one anyway)')
    if not CHECK_OFFSET / CHECK_SCALE <= out['d25'] <= CHECK_OFFSET * CHECK_SCALE:
        raise ValueError(f'the distance of {name} reads {CHECK_OFFSET} steps of data as {out["d25"]:.3g} ({numbers}): '
                         'not control steps (a value in other units?); no map is built on it '
                         '(--set agent.distance_check=false to build one anyway)')
    return out
