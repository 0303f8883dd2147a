"""Training AQM's learned parts (paper Algorithm 1, steps A and B): one jitted update for the IQE
quasimetric (QRL), the Lagrange multiplier, the Q-AWR target policy and the Q-SAW main policy.

    cfg = TrainConfig.preset('cpu', env='antmaze-medium')
    learner = make_learner(cfg, obs_size=29, action_size=8)
    state = learner.init(jax.random.PRNGKey(cfg.seed))
    state, metrics = learner.chunk(state, dataset)      # cfg.updates_per_call updates under lax.scan

:func:`train` is the host loop around it: progress bar, JSON-lines metrics, Orbax checkpoints,
exact resume. :func:`load` rebuilds a trained model from its run folder alone.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import time
from typing import Any, NamedTuple, Optional

import jax
import jax.numpy as jnp
import optax
from flax import struct

from aqm_mjx import checkpoint as ckpt
from aqm_mjx import dataset as ds_io
from aqm_mjx import envs, policy
from aqm_mjx.quasimetric import IQE, qrl_losses

QRL_VARIANTS = ('paper', 'ogbench')
OBJECTIVES = ('saw', 'awr', 'bc')
POLICY_GOALS = ('trajectory', 'random')
PUSH_OFFSETS = {'arena': 50.0, 'medium': 50.0, 'large': 125.0, 'teleport': 125.0, 'giant': 250.0}  # Table 5
OGBENCH_PUSH_OFFSET = 500.0  # OGBench's QRL: 100 * softplus(5 - d / 100)


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """Everything a training run depends on; saved as JSON beside every checkpoint."""

    preset: str = 'cpu'  # the preset these values came from (recorded with every result)
    env: Optional[str] = 'antmaze-medium'  # sets the push offset (Table 5) when push_offset is None
    steps: int = 20_000  # gradient updates in the run
    batch_size: int = 256  # transitions per update (paper: 1024)
    updates_per_call: int = 500  # updates per jitted host call (lax.scan length); steps must be a multiple
    log_every: int = 500  # updates between metric lines (a multiple of updates_per_call)
    checkpoint_every: int = 5_000  # updates between checkpoints (a multiple of updates_per_call)
    keep: int = 3  # checkpoints kept
    seed: int = 0
    # quasimetric (paper section 4.2, Appendix 10.1)
    q_hidden: tuple = (256, 256, 256)  # encoder MLP widths (paper: 3 x 512)
    n_components: int = 256  # IQE components N (paper: 512)
    component_size: int = 1  # IQE component size M (paper: 1; OGBench's QRL: 8)
    lr_quasimetric: float = 1e-4
    qrl: str = 'paper'  # 'paper': lambda >= 0 by projection; 'ogbench': lambda = exp(log_lambda), offset 500
    epsilon: float = math.sqrt(0.05)  # local-constraint slack: mean(relu(d(s,s') - 1)^2) <= epsilon^2 (OGBench 0.05)
    push_offset: Optional[float] = None  # m of omega; None: Table 5 by maze (or 500 for qrl='ogbench')
    push_scale: float = 0.01  # s of omega (Table 5)
    lambda_init: float = 1.0
    lr_lambda: float = 1e-2
    # policies (paper section 4.4, Appendix 10)
    pi_hidden: tuple = (256, 256, 256)  # policy MLP widths (paper: 3 x 512)
    const_std: bool = True  # unit std as in OGBench's actors (KL = squared mean difference / 2)
    lr_policy: float = 3e-4
    objective: str = 'saw'  # 'saw': Q-AWR target + Q-SAW main; 'awr': Q-AWR on the goal; 'bc': cloning
    # 'goal': raw goal obs (the paper); 'direction': unit x-y direction; 'egocentric': goal + that direction in
    # the torso frame (our default: at CPU scale the ant ignores a raw goal; policy.py has the measurement)
    conditioning: str = 'egocentric'
    temperature: float = 3.0  # advantage temperature (beta_T = beta_M)
    weight_clip: float = 100.0  # cap on exp(temperature * advantage) (SAW)
    subgoal_offset: int = 25  # k: subgoal w = s_{min(t + k, end)}
    policy_goals: str = 'trajectory'  # 'trajectory': uniform over the rest of it; 'random': explore datasets

    def __post_init__(self):
        for name in ('steps', 'batch_size', 'updates_per_call', 'log_every', 'checkpoint_every', 'keep',
                     'n_components', 'component_size', 'subgoal_offset'):
            if int(getattr(self, name)) < 1:
                raise ValueError(f'{name} must be >= 1; got {getattr(self, name)}')
        for name in ('steps', 'log_every', 'checkpoint_every'):
            if int(getattr(self, name)) % int(self.updates_per_call):
                raise ValueError(f'{name} ({getattr(self, name)}) must be a multiple of updates_per_call '
                                 f'({self.updates_per_call})')
        for name, value, allowed in (('qrl', self.qrl, QRL_VARIANTS), ('objective', self.objective, OBJECTIVES),
                                     ('conditioning', self.conditioning, policy.CONDITIONING),
                                     ('policy_goals', self.policy_goals, POLICY_GOALS)):
            if value not in allowed:
                raise ValueError(f'unknown {name} {value!r}; expected one of {", ".join(allowed)}')
        for name in ('lr_quasimetric', 'lr_lambda', 'lr_policy', 'temperature', 'weight_clip', 'push_scale'):
            v = float(getattr(self, name))
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f'{name} must be a finite number > 0; got {v}')
        if self.lambda_init < 0 or self.epsilon < 0:
            raise ValueError('lambda_init and epsilon must be >= 0')
        if self.env is not None:
            envs.parse_name(self.env)
        elif self.push_offset is None and self.qrl == 'paper':
            raise ValueError('push_offset must be given when env is None')

    # -------------------------------------------------------------------- presets and JSON
    @classmethod
    def preset(cls, name: str, **overrides) -> 'TrainConfig':
        """``paper``: Appendix 10 sizes; ``cpu``: a few minutes on a 2-core CPU; ``tiny``: tests."""
        if name not in PRESETS:
            raise ValueError(f'unknown preset {name!r}; expected one of {", ".join(PRESETS)}')
        return cls(**{**PRESETS[name], 'preset': name, **overrides})

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> 'TrainConfig':
        fields = {f.name: f for f in dataclasses.fields(cls)}
        unknown = set(d) - set(fields)
        if unknown:
            raise ValueError(f'unknown config field(s) {sorted(unknown)}')
        return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in d.items()})

    def with_overrides(self, pairs) -> 'TrainConfig':
        """``['batch_size=64', 'q_hidden=64,64']`` -> a new config (values parsed by the field's type)."""
        fields = {f.name: f for f in dataclasses.fields(self)}
        changes = {}
        for pair in pairs:
            if '=' not in pair:
                raise ValueError(f'override {pair!r} is not of the form key=value')
            k, v = pair.split('=', 1)
            if k not in fields:
                raise ValueError(f'unknown config field {k!r}; expected one of {", ".join(fields)}')
            cur = getattr(self, k)
            if isinstance(cur, tuple):
                changes[k] = tuple(int(x) for x in v.split(',') if x)
            elif isinstance(cur, bool):
                changes[k] = v.lower() in ('1', 'true', 'yes')
            elif isinstance(cur, int):
                changes[k] = int(v)
            elif isinstance(cur, float) or k == 'push_offset':
                changes[k] = None if v.lower() == 'none' else float(v)
            else:
                changes[k] = None if v.lower() == 'none' else v
        return dataclasses.replace(self, **changes)

    @property
    def offset(self) -> float:
        if self.push_offset is not None:
            return float(self.push_offset)
        if self.qrl == 'ogbench':
            return OGBENCH_PUSH_OFFSET
        return PUSH_OFFSETS[envs.parse_name(self.env)[1]]

    @property
    def goal_sampling(self) -> ds_io.GoalSampling:
        if self.policy_goals == 'random':
            return ds_io.GoalSampling(p_trajectory=0.0, p_random=1.0, subgoal_offset=self.subgoal_offset)
        return ds_io.GoalSampling(p_trajectory=1.0, geometric=False, subgoal_offset=self.subgoal_offset)


PRESETS = {
    'paper': dict(steps=1_000_000, batch_size=1024, updates_per_call=1000, log_every=5000, checkpoint_every=50_000,
                  q_hidden=(512, 512, 512), n_components=512, component_size=1, pi_hidden=(512, 512, 512),
                  conditioning='goal'),
    # cpu: 20x fewer updates than the paper, so the quasimetric learns 3x faster (at 1e-4 its map of
    # antmaze-medium still joined keypoints across walls after 20,000 updates; RESULTS.md)
    'cpu': dict(steps=20_000, batch_size=256, updates_per_call=500, log_every=500, checkpoint_every=5_000,
                q_hidden=(256, 256, 256), n_components=256, component_size=1, pi_hidden=(256, 256, 256),
                lr_quasimetric=3e-4),
    'tiny': dict(steps=200, batch_size=64, updates_per_call=50, log_every=50, checkpoint_every=100,
                 q_hidden=(32, 32), n_components=32, component_size=1, pi_hidden=(32, 32)),
}


# ------------------------------------------------------------------------------------------ state
@struct.dataclass
class TrainState:
    """Every array a run needs to continue exactly."""

    step: jax.Array  # int32 []
    key: jax.Array  # uint32 [2]
    q_params: Any
    q_opt: Any
    lam: jax.Array  # float32 []: lambda ('paper') or log lambda ('ogbench')
    lam_opt: Any
    pi_params: Any  # {'target': ..., 'main': ...}
    pi_opt: Any


class Learner(NamedTuple):
    """Pure functions built from a config (the config itself stays out of every pytree)."""

    config: TrainConfig
    quasimetric: IQE
    policy: policy.GaussianPolicy
    init: Any  # key -> TrainState
    update: Any  # (TrainState, Dataset) -> (TrainState, metrics)
    chunk: Any  # jitted: (TrainState, Dataset) -> (TrainState, mean metrics over updates_per_call)
    distance: Any  # (q_params, x [..., D], y [..., D]) -> [...]
    act: Any  # (pi_params, obs [..., D], goal [..., D]) -> mean action [..., A] (main policy)


def make_learner(cfg: TrainConfig, obs_size: int, action_size: int) -> Learner:
    """Build the modules, optimisers and the jitted update of a run."""
    iqe = IQE(hidden=tuple(cfg.q_hidden), n_components=cfg.n_components, component_size=cfg.component_size)
    pi = policy.GaussianPolicy(action_size=action_size, hidden=tuple(cfg.pi_hidden), const_std=cfg.const_std)
    q_tx = optax.adam(cfg.lr_quasimetric)
    lam_tx = optax.adam(cfg.lr_lambda)
    pi_tx = optax.adam(cfg.lr_policy)
    goal_dim = policy.goal_input_size(obs_size, cfg.conditioning)
    gs = cfg.goal_sampling
    offset, eps, temp, clip = cfg.offset, cfg.epsilon, cfg.temperature, cfg.weight_clip
    b = cfg.batch_size

    def lam_value(raw):
        return jnp.exp(raw) if cfg.qrl == 'ogbench' else raw

    def init(key):
        k_q, k_t, k_m, k_run = jax.random.split(key, 4)
        x = jnp.zeros((1, obs_size))
        q_params = iqe.init(k_q, x, x)
        gi = jnp.zeros((1, goal_dim))
        pi_params = {'target': pi.init(k_t, x, gi), 'main': pi.init(k_m, x, gi)}
        lam = jnp.asarray(math.log(cfg.lambda_init) if cfg.qrl == 'ogbench' else cfg.lambda_init, jnp.float32)
        return TrainState(step=jnp.zeros((), jnp.int32), key=k_run, q_params=q_params, q_opt=q_tx.init(q_params),
                          lam=lam, lam_opt=lam_tx.init(lam), pi_params=pi_params, pi_opt=pi_tx.init(pi_params))

    def distance(q_params, x, y):
        return iqe.apply(q_params, x, y)

    def act(pi_params, obs, goal):
        return pi.apply(pi_params['main'], obs, policy.goal_input(obs, goal, cfg.conditioning))[0]

    def update(state: TrainState, ds: ds_io.Dataset):
        key, k_batch, k_rand = jax.random.split(state.key, 3)
        batch = ds_io.sample(ds, k_batch, b, gs)
        s, a, s1, w, g = batch.observations, batch.actions, batch.next_observations, batch.subgoals, batch.goals
        rand = ds.observations[jax.random.randint(k_rand, (b,), 0, ds.size)]
        lam = lam_value(state.lam)

        def dist_fn(qp):
            return lambda x, y: iqe.apply(qp, x, y, method=IQE.distance)

        # (A) QUASIMETRIC: one encoder pass over s, s' and random goals (the rows with gradients)
        def q_loss(qp):
            zs, zs1, zr = jnp.split(iqe.apply(qp, jnp.concatenate([s, s1, rand]), method=IQE.encode), 3)
            loss, _, info = qrl_losses(dist_fn(qp)(zs, zs1), dist_fn(qp)(zs, zr), lam, eps, offset, cfg.push_scale)
            return loss, (info, jax.lax.stop_gradient(zs), jax.lax.stop_gradient(zs1))

        (q_l, (q_info, zs, zs1)), q_grads = jax.value_and_grad(q_loss, has_aux=True)(state.q_params)
        # Subgoals and goals only feed the policies' advantages: a forward pass, no backward through them
        zw, zg = jnp.split(iqe.apply(state.q_params, jnp.concatenate([w, g]), method=IQE.encode), 2)
        dist = dist_fn(state.q_params)
        d = dict(sw=dist(zs, zw), s1w=dist(zs1, zw), sg=dist(zs, zg), s1g=dist(zs1, zg), wg=dist(zw, zg))
        q_updates, q_opt = q_tx.update(q_grads, state.q_opt, state.q_params)
        q_params = optax.apply_updates(state.q_params, q_updates)

        close = q_info['qrl/close']  # mean(relu(d_pos - 1)^2) - epsilon^2
        lam_grad = jax.grad(lambda raw: -lam_value(raw) * close)(state.lam)  # ascent on lambda * violation
        lam_updates, lam_opt = lam_tx.update(lam_grad, state.lam_opt, state.lam)
        new_lam = optax.apply_updates(state.lam, lam_updates)
        if cfg.qrl == 'paper':
            new_lam = jnp.maximum(new_lam, 0.0)

        # (B) POLICIES: advantages from the quasimetric held fixed
        def pi_loss(pp):
            def run(params, goal):
                return pi.apply(params, s, policy.goal_input(s, goal, cfg.conditioning))

            mu_m, ls_m = run(pp['main'], g)
            info = {}
            if cfg.objective == 'saw':
                mu_t, ls_t = run(pp['target'], w)
                lt, wt = policy.awr_loss(policy.log_prob(mu_t, ls_t, a), d['sw'] - d['s1w'], temp, clip)
                k = policy.kl(mu_m, ls_m, jax.lax.stop_gradient(mu_t), jax.lax.stop_gradient(ls_t))
                lm, wm = policy.saw_loss(k, d['sg'] - d['wg'], temp, clip)
                info.update({'policy/target_loss': lt, 'policy/target_weight': jnp.mean(wt), 'policy/kl': jnp.mean(k),
                             'policy/target_mse': jnp.mean(jnp.square(mu_t - a))})
                loss = lt + lm
            elif cfg.objective == 'awr':
                lm, wm = policy.awr_loss(policy.log_prob(mu_m, ls_m, a), d['sg'] - d['s1g'], temp, clip)
                loss = lm
            else:
                lm = -jnp.mean(policy.log_prob(mu_m, ls_m, a))
                wm = jnp.ones((b,))
                loss = lm
            info.update({'policy/main_loss': lm, 'policy/main_weight': jnp.mean(wm),
                         'policy/main_weight_clipped': jnp.mean(wm >= clip * (1 - 1e-6)),
                         'policy/main_mse': jnp.mean(jnp.square(mu_m - a))})
            return loss, info

        (_, pi_info), pi_grads = jax.value_and_grad(pi_loss, has_aux=True)(state.pi_params)
        pi_updates, pi_opt = pi_tx.update(pi_grads, state.pi_opt, state.pi_params)
        pi_params = optax.apply_updates(state.pi_params, pi_updates)

        metrics = {**q_info, **pi_info, 'qrl/loss': q_l, 'qrl/alpha': jax.nn.sigmoid(q_params['params']['alpha_logit']),
                   'qrl/d_subgoal_mean': jnp.mean(d['sw'])}
        new = TrainState(step=state.step + 1, key=key, q_params=q_params, q_opt=q_opt, lam=new_lam, lam_opt=lam_opt,
                         pi_params=pi_params, pi_opt=pi_opt)
        return new, metrics

    def _chunk(state, ds):
        state, metrics = jax.lax.scan(lambda st, _: update(st, ds), state, None, length=cfg.updates_per_call)
        return state, jax.tree.map(jnp.mean, metrics)

    return Learner(config=cfg, quasimetric=iqe, policy=pi, init=init, update=update,
                   chunk=jax.jit(_chunk, donate_argnums=0), distance=distance, act=act)


# -------------------------------------------------------------------------------------- host loop
def _meta(cfg: TrainConfig, obs_size: int, action_size: int, dataset_path: Optional[str]) -> dict:
    return dict(config=cfg.to_dict(), obs_size=int(obs_size), action_size=int(action_size), dataset=dataset_path,
                format='aqm_mjx.train/1')


def _trim_metrics(path: str, step: int) -> None:
    """Keep the metric lines up to ``step`` (a resumed run re-logs what came after its checkpoint)."""
    if not os.path.exists(path):
        return
    with open(path) as f:
        lines = [ln for ln in f if ln.strip() and json.loads(ln).get('step', 0) <= step]
    tmp = path + '.tmp'
    with open(tmp, 'w') as f:
        f.writelines(lines)
    os.replace(tmp, path)


def train(cfg: Optional[TrainConfig], data: dict, out: str, resume: bool = False, steps: Optional[int] = None,
          dataset_path: Optional[str] = None, progress: bool = True, log=print,
          key: Optional[jax.Array] = None) -> TrainState:
    """Train (or resume) a run in folder ``out``.

    Args:
        cfg: the run's config (ignored on resume: the saved one is used, ``steps`` may extend it).
        data: raw arrays from :func:`aqm_mjx.dataset.read_ogbench` or a collector.
        out: run folder (``config.json``, ``metrics.jsonl``, ``checkpoints/``).
        resume: continue from the newest readable checkpoint in ``out``.
        steps: override the total number of updates.
        key: the initialisation key (default ``PRNGKey(cfg.seed)``; :mod:`aqm_mjx.pipeline` passes
            its train key so that both paths of a run start alike). Ignored on resume.
    Returns:
        The final TrainState.
    """
    ds = ds_io.to_device(data)  # validates, and refuses a dataset without transitions
    obs_size, action_size = ds.observations.shape[1], ds.actions.shape[1]
    cfg_path = os.path.join(out, 'config.json')
    metrics_path = os.path.join(out, 'metrics.jsonl')
    if resume:
        meta = ckpt.read_json(cfg_path)
        cfg = TrainConfig.from_dict(meta['config'])
        if (meta['obs_size'], meta['action_size']) != (obs_size, action_size):
            raise ValueError(f'{out} was trained on {meta["obs_size"]}-d observations and {meta["action_size"]}-d '
                             f'actions; this dataset has {obs_size} and {action_size}')
    elif os.path.exists(os.path.join(out, 'checkpoints')) and os.listdir(os.path.join(out, 'checkpoints')):
        raise FileExistsError(f'{out} already holds checkpoints; pass --resume to continue it or choose a new --out')
    if cfg is None:
        raise ValueError('a config is needed for a new run')
    if steps is not None:
        cfg = dataclasses.replace(cfg, steps=int(steps))
    os.makedirs(out, exist_ok=True)
    learner = make_learner(cfg, obs_size, action_size)
    meta = _meta(cfg, obs_size, action_size, dataset_path)
    saver = ckpt.Checkpointer(out, keep=cfg.keep)
    state = learner.init(jax.random.PRNGKey(cfg.seed) if key is None else key)
    if resume:
        step, state, _ = saver.restore(state, log=log)
        log(f'resumed {out} at step {step}')
        _trim_metrics(metrics_path, step)
    ckpt.write_json(cfg_path, meta)
    start = int(state.step)
    if start % cfg.updates_per_call:
        raise ValueError(f'checkpoint step {start} is not a multiple of updates_per_call {cfg.updates_per_call}')
    bar = None
    if progress:
        from tqdm.auto import tqdm  # pylint: disable=import-outside-toplevel

        bar = tqdm(total=cfg.steps, initial=start, desc=f'train {cfg.preset}', unit='upd', smoothing=0.1)
    t_last, first = time.perf_counter(), True
    with open(metrics_path, 'a') as mf:
        while int(state.step) < cfg.steps:
            state, m = learner.chunk(state, ds)
            m = {k: float(v) for k, v in jax.device_get(m).items()}
            step = int(state.step)
            now = time.perf_counter()
            m['time/updates_per_s'] = cfg.updates_per_call / (now - t_last)
            m['time/includes_compile'] = first
            t_last, first = now, False
            if step % cfg.log_every == 0 or step == cfg.steps:
                mf.write(json.dumps({'step': step, 'preset': cfg.preset, **m}) + '\n')
                mf.flush()
            if bar is not None:
                bar.update(cfg.updates_per_call)
                bar.set_postfix({'d_pos': f'{m["qrl/d_pos_mean"]:.2f}', 'd_goal': f'{m["qrl/d_goal_mean"]:.1f}',
                                 'lam': f'{m["qrl/lambda"]:.3f}', 'pi': f'{m["policy/main_loss"]:.3g}'})
            if step % cfg.checkpoint_every == 0 or step == cfg.steps:
                saver.save(step, state, meta)
    if bar is not None:
        bar.close()
    saver.close()
    return state


class Trained(NamedTuple):
    """A trained model loaded from its run folder."""

    config: TrainConfig
    learner: Learner
    state: TrainState
    step: int
    meta: dict


def load(out: str, step: Optional[int] = None, log=print) -> Trained:
    """Load a run folder for evaluation: the config JSON and the newest readable checkpoint."""
    meta = ckpt.read_json(os.path.join(out, 'config.json'))
    cfg = TrainConfig.from_dict(meta['config'])
    learner = make_learner(cfg, meta['obs_size'], meta['action_size'])
    template = learner.init(jax.random.PRNGKey(cfg.seed))
    saver = ckpt.Checkpointer(out, keep=None, create=False)
    s, state, _ = saver.restore(template, step=step, log=log)
    saver.close()
    return Trained(config=cfg, learner=learner, state=state, step=s, meta=meta)


def infer_env(path: str) -> tuple[str, Optional[str]]:
    """``.../antmaze-large-navigate-v0.npz`` -> ``('antmaze-large', 'navigate')``."""
    base = os.path.basename(path)
    parts = (base[:-4] if base.endswith('.npz') else base).split('-')
    name = '-'.join(parts[:2])
    try:
        envs.parse_name(name)
    except ValueError:
        raise ValueError(f'cannot infer the environment from {path!r}; pass --env (e.g. antmaze-medium)') from None
    style = parts[2] if len(parts) > 2 and parts[2] in ('navigate', 'stitch', 'explore') else None
    return name, style
