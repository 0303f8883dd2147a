"""Parity with the reference agents: our GCIVL, GCIQL, CRL and HIQL against
``seohongpark/ogbench``'s ``impls/agents``, and our SAW against ``johnlyzhou/saw``'s
(``impls/agents/saw.py``, a fork of OGBench's ``impls``), on the same parameters and the same batch.

    python benchmarks/parity/bench_parity.py --reference /path/to/ogbench    # a checkout, or a bare git copy
    python benchmarks/parity/bench_parity.py --reference OGBENCH --saw-reference /path/to/saw --methods gcivl saw
    python benchmarks/parity/bench_parity.py                                 # no copy given: says so and skips

For each method the reference agent is built with OGBench's ``create`` (its config from
``get_config`` with small widths and the settings ours uses), our parameters are written into its
parameter tree (the networks are built alike, so the trees match leaf for leaf after renaming the
top-level modules; the benchmark checks every shape), and on one batch it prints:
- the total loss and every shared info entry of both, and their largest difference;
- the gradients of the total loss, leaf by leaf (largest difference relative to the largest entry);
- after each of 5 updates on 5 further batches (reference ``agent.update(batch)``, ours
  ``learner.step(state, batch, key)``, both Adam at 3e-4 and Polyak 0.005), the largest difference
  of every parameter and target. (One Adam step alone moves a parameter by about lr * sign(g), so
  the gradients are compared directly, and later steps mix their magnitudes in.)
It exits 1 when a loss or gradient differs by more than ``--loss-tol`` (1e-5, relative) or a
parameter by more than ``--param-tol`` (1e-6 absolute; float32 round-off is about 1e-8).

The reference code is never copied into the project: it is imported from the copy given, with a
small Gaussian stand-in for ``distrax`` (TensorFlow Probability 0.25, which distrax needs, does not
import with JAX 0.10), and needs ``pip install ml-collections``. Its batch keys are OGBench's
(``value_goals``, ``actor_goals``, ``low_actor_goals``, ``high_actor_goals``, ``high_actor_targets``);
ours are :class:`aqm_mjx.data.goals.GCBatch` fields filled from the same arrays.
"""

from __future__ import annotations

import argparse
import atexit
import math
import os
import shutil
import subprocess
import sys
import tempfile
import types

import jax
import jax.numpy as jnp
import numpy as np

METHODS = ('gcivl', 'gciql', 'crl', 'hiql', 'saw')
# the reference's info names -> ours, after the module prefix (value/value_loss -> value/loss)
NAMES = {'value_loss': 'loss', 'actor_loss': 'loss', 'critic_loss': 'loss', 'contrastive_loss': 'loss',
         'bc_log_prob': 'log_prob', 'adv': 'adv_mean', 'awr_loss': 'loss', 'waypoint_loss': 'loss', 'kld': 'kl',
         'wadv': 'adv_mean'}
# SAW's reference modules (and info prefixes) -> ours, where they are named apart (its target sub-policy);
# our module names are unique across methods, so the parameter map applies them to every method
MODULES = {'low_actor': 'sub_actor', 'actor_goal_rep_def': 'actor_goal_rep'}
SAW_ONLY = ('saw',)  # methods whose reference is johnlyzhou/saw's fork, not OGBench


# ------------------------------------------------------------------------ the reference's imports
def _gaussian_standin() -> types.ModuleType:
    """A ``distrax`` module with the one distribution the reference's state-based agents use:
    a diagonal Gaussian (``log_prob``, ``mode``, ``sample``, ``scale_diag``)."""
    mod = types.ModuleType('distrax')

    class MultivariateNormalDiag:
        def __init__(self, loc, scale_diag):
            self.loc, self.scale_diag = loc, scale_diag

        def log_prob(self, x):
            z = (x - self.loc) / self.scale_diag
            return jnp.sum(-0.5 * z * z - jnp.log(self.scale_diag) - 0.5 * math.log(2 * math.pi), axis=-1)

        def mode(self):
            return self.loc

        def sample(self, seed):
            return self.loc + self.scale_diag * jax.random.normal(seed, self.loc.shape)

    class _Unused:
        def __init__(self, *a, **k):
            raise NotImplementedError('the parity benchmark uses the Gaussian actors only')

    mod.MultivariateNormalDiag = MultivariateNormalDiag
    mod.Transformed = mod.Block = mod.Tanh = mod.Categorical = _Unused
    return mod


def reference_impls(path: str | None) -> tuple[str | None, str]:
    """``(folder holding impls/, why not)``: a checkout, or a bare git copy extracted to a temp folder."""
    if not path:
        return None, 'no copy of seohongpark/ogbench given (--reference DIR or AQM_OGBENCH_REF)'
    if os.path.isdir(os.path.join(path, 'impls', 'agents')):
        return path, ''
    git_dir = next((p for p in (path, os.path.join(path, 'repo'), os.path.join(path, '.git'))
                    if os.path.isfile(os.path.join(p, 'HEAD'))), None)
    if git_dir is None:
        return None, f'{path} holds neither impls/agents nor a git repository'
    out = tempfile.mkdtemp(prefix='ogbench_ref_')
    atexit.register(shutil.rmtree, out, ignore_errors=True)
    archive = subprocess.run(['git', f'--git-dir={git_dir}', 'archive', 'HEAD', 'impls'], capture_output=True)
    if archive.returncode:
        return None, f'git archive of {git_dir} failed: {archive.stderr.decode()[:200]}'
    subprocess.run(['tar', '-x', '-C', out], input=archive.stdout, check=True)
    return out, ''


def import_reference(root: str):
    """The reference's ``agents`` package (its ``impls/`` on ``sys.path``, ``distrax`` stood in). A
    second reference (SAW's fork) is imported apart: the ``agents`` and ``utils`` packages of one
    are moved out of ``sys.modules`` while the other's load, and put back after."""
    sys.modules.setdefault('distrax', _gaussian_standin())
    held = {k: sys.modules.pop(k) for k in list(sys.modules) if k.split('.')[0] in ('agents', 'utils')}
    sys.path.insert(0, os.path.join(root, 'impls'))
    try:
        import agents  # pylint: disable=import-outside-toplevel,import-error
    finally:
        sys.path.remove(os.path.join(root, 'impls'))
        for k in [k for k in sys.modules if k.split('.')[0] in ('agents', 'utils')]:
            if k in held:
                sys.modules[k] = held.pop(k)
        sys.modules.update(held)
    return agents


# --------------------------------------------------------------------------------- parameter maps
def _flat(tree, prefix=()):
    if isinstance(tree, dict) or hasattr(tree, 'items'):
        out = []
        for k in sorted(tree):
            out += _flat(tree[k], prefix + (k,))
        return out
    return [(prefix, tree)]


def _set(tree, path, value):
    node = tree
    for k in path[:-1]:
        node = node[k]
    node[path[-1]] = value


def _set_checked(tree, path, value):
    """:func:`_set` of a leaf whose shape must equal the reference's leaf at ``path`` (else the
    script stops and names the path)."""
    node = tree
    for k in path[:-1]:
        node = node[k]
    if node[path[-1]].shape != value.shape:
        raise SystemExit(f'shape mismatch at {path}: reference {node[path[-1]].shape}, ours {value.shape}')
    node[path[-1]] = value


def rel(a, b) -> float:
    """Largest absolute difference of ``a`` and ``b`` relative to ``a``'s largest magnitude."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    return float(np.max(np.abs(a - b)) / max(np.max(np.abs(a)), 1e-12))


def worst_gradient(g_ref: dict, g_mine: dict) -> tuple[float, str]:
    """``(largest relative difference, leaf)`` of two gradient trees in the reference's layout (its
    target modules left out)."""
    return max((rel(np.asarray(x), np.asarray(y)), '/'.join(k)) for (k, x), (_, y)
               in zip(_flat({n: v for n, v in g_ref.items() if 'target' not in n}),
                      _flat({n: v for n, v in g_mine.items() if 'target' not in n})))


def max_param_diff(ref: dict, mine: dict) -> float:
    """Largest absolute difference of two parameter trees in the reference's layout."""
    return max(float(np.max(np.abs(np.asarray(x) - np.asarray(y)))) for (_, x), (_, y) in zip(_flat(ref), _flat(mine)))


def check_losses(pairs, tol: float, rows: list, prefix: str = '') -> bool:
    """``pairs`` of ``(name, reference, ours)`` losses: print and record each (``what``: ``PREFIXloss/NAME``);
    True when every relative difference is within ``tol``."""
    ok = True
    for name, x, y in pairs:
        d = rel(x, y)
        ok &= d <= tol
        rows.append(dict(what=f'{prefix}loss/{name}', reference=float(x), ours=float(y), rel_diff=d))
        print(f'{prefix}{name:14} {float(x):12.6f} {float(y):12.6f} {d:9.1e}')
    return ok


def check_gradients(g_ref: dict, g_mine: dict, tol: float, rows: list, prefix: str = '') -> bool:
    """:func:`worst_gradient`, printed and recorded (``PREFIXgradients``); True when within ``tol``."""
    worst = worst_gradient(g_ref, g_mine)
    rows.append(dict(what=f'{prefix}gradients', rel_diff=worst[0], where=worst[1]))
    print(f'{prefix}gradients: largest relative difference {worst[0]:.1e} ({worst[1]})')
    return worst[0] <= tol


def check_update(i: int, ref: dict, mine: dict, tol: float, rows: list, prefix: str = '') -> bool:
    """:func:`max_param_diff` after update ``i``, printed and recorded (``PREFIXupdate I``); True when within ``tol``."""
    diff = max_param_diff(ref, mine)
    rows.append(dict(what=f'{prefix}update {i}', max_param_diff=diff))
    print(f'{prefix}after update {i}: largest parameter difference {diff:.1e}')
    return diff <= tol


def reference_parser(doc: str, repo: str) -> argparse.ArgumentParser:
    """The options every single-reference parity script takes: ``--reference`` (a checkout of
    ``repo``), the loss and parameter tolerances, and ``--out``."""
    p = argparse.ArgumentParser(description=doc.split('\n')[0])
    p.add_argument('--reference', required=True, help=f'a checkout of github.com/{repo}')
    p.add_argument('--loss-tol', type=float, default=1e-5, help='largest relative difference of a loss')
    p.add_argument('--param-tol', type=float, default=1e-6, help='largest absolute difference of a parameter')
    p.add_argument('--out', default=None, help='write the rows as JSON here')
    return p


def verdict(ok: bool, control_agreed: bool, a, rows: list, updates: str, control: str) -> int:
    """The closing line (``a``: the parsed ``--loss-tol``, ``--param-tol``, ``--out``), the machine
    line and the exit status: 0 when parity holds and the control disagrees."""
    sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # benchmarks/: _report
    from _report import finish  # noqa: PLC0415

    print(f'parity: {"PASS" if ok else "FAIL"} (losses and gradients within {a.loss_tol:g}, parameters within '
          f'{a.param_tol:g} after {updates}); control ({control}): '
          f'{"FAIL (agreed)" if control_agreed else "differs as it must"}')
    finish(rows, a.out)
    return 0 if ok and not control_agreed else 1


def describe(tree) -> list[str]:
    return ['/'.join(map(str, p)) + f' {tuple(np.shape(v))}' for p, v in _flat(tree)]


def reference_path(kind: str, module: str, rest: tuple) -> tuple:
    """Where our leaf ``(params|target)/module/params/...rest`` lives in the reference's tree."""
    theirs = {v: k for k, v in MODULES.items()}.get(module, module)
    top = f'modules_{"target_" if kind == "target" else ""}{theirs}'
    if module in ('goal_rep', 'actor_goal_rep') and rest[:1] == ('MLP_0',):  # nn.Sequential([MLP, LengthNormalize])
        rest = ('layers_0',) + rest[1:]
    return (top,) + rest


def to_reference(tree, kind: str = 'params') -> dict:
    """``{reference leaf path: value}`` of our ``{module: {'params': ...}}`` tree (``kind`` 'target' for targets)."""
    out = {}
    for path, value in _flat(tree):
        module, inner, rest = path[0], path[1], path[2:]
        assert inner == 'params', path
        out[reference_path(kind, module, rest)] = jnp.asarray(value)
    return out


def ours_into_reference(state, ref_params) -> dict:
    """The reference's parameter tree with our values (every leaf of both is matched, shapes checked)."""
    ref_flat = dict(_flat(ref_params))
    ours = {**to_reference(state.params), **to_reference(state.target, 'target')}
    if set(ours) != set(ref_flat):
        raise KeyError(f'leaves only ours: {sorted(set(ours) - set(ref_flat))}; only the reference\'s: '
                       f'{sorted(set(ref_flat) - set(ours))}')
    out = {k: jax.tree.map(lambda x: x, dict(v)) for k, v in dict(ref_params).items()}
    for where, value in ours.items():
        if value.shape != np.shape(ref_flat[where]):
            raise ValueError(f'{"/".join(where)}: ours {value.shape}, reference {np.shape(ref_flat[where])}')
        _set(out, where, value)
    return out


def largest_diff(ref: dict, ours: dict) -> tuple[float, str]:
    """``(max |ref - ours| over the leaves of ref, the leaf)``."""
    d = {'/'.join(p): float(jnp.max(jnp.abs(jnp.asarray(v) - ours[p]))) for p, v in ref.items()}
    top = max(d, key=d.get)
    return d[top], top


# ------------------------------------------------------------------------------------- settings
def configs(name: str, ref_module, hidden=(32, 32, 32), perturb=()):
    """(reference config dict, our config): OGBench's AntMaze values, small widths, OGBench's goal input."""
    from aqm_mjx.learn import methods  # pylint: disable=import-outside-toplevel

    ref = dict(ref_module.get_config())
    ref.update(actor_hidden_dims=hidden, value_hidden_dims=hidden)
    over = dict(env=None, actor_hidden=hidden, value_hidden=hidden, conditioning='goal', const_std=True)
    if name == 'crl':
        ref.update(latent_dim=16)
        over.update(latent=16)
    if name in ('hiql', 'saw'):
        ref.update(rep_dim=10)
    if name == 'saw':
        ref.update(low_actor_hidden_dims=hidden, share_goal_rep=False)
    ours = methods.get(name).preset('paper', **over)
    if perturb:  # --set: a deliberate difference, to see the check fail
        return ref, ours.with_overrides([x for x in perturb if x.split('=')[0] in ours.to_dict()])
    shared = dict(lr='lr', discount='discount', tau='tau', expectile='expectile', alpha='alpha',
                  high_alpha='high_alpha', low_alpha='low_alpha', rep_dim='rep_dim', layer_norm='layer_norm',
                  awr_alpha='awr_alpha', kl_alpha='kl_alpha', const_std='const_std')
    for ours_f, ref_f in shared.items():
        if hasattr(ours, ours_f) and ref_f in ref:
            assert getattr(ours, ours_f) == ref[ref_f], (name, ours_f, getattr(ours, ours_f), ref[ref_f])
    return ref, ours


def batches(key, b: int, obs: int, act: int):
    """One batch as the reference's dict and as our GCBatch, from the same arrays (a tenth of the
    value goals are the state itself: reward 0, mask 0)."""
    from aqm_mjx.data import goals  # pylint: disable=import-outside-toplevel

    k = jax.random.split(key, 8)
    s, s1, vg, ag, sub, low = (jax.random.normal(k[i], (b, obs)) for i in range(6))
    a = jax.random.uniform(k[6], (b, act), minval=-1, maxval=1)
    at_goal = jax.random.uniform(k[7], (b,)) < 0.1
    vg = jnp.where(at_goal[:, None], s, vg)
    rewards, masks = jnp.where(at_goal, 0.0, -1.0), jnp.where(at_goal, 0.0, 1.0)
    ref = dict(observations=s, next_observations=s1, actions=a, value_goals=vg, actor_goals=ag, rewards=rewards,
               masks=masks, low_actor_goals=low, high_actor_goals=ag, high_actor_targets=sub)
    idx = jnp.zeros((b,), jnp.int32)
    ours = goals.GCBatch(observations=s, actions=a, next_observations=s1, value_goals=vg, rewards=rewards, masks=masks,
                         actor_goals=ag, subgoals=sub, low_goals=low, index=idx, value_goal_index=idx,
                         value_kind=idx, actor_goal_index=idx, actor_kind=idx, subgoal_index=idx)
    return ref, ours


def compare_method(name: str, ref_agents, b: int = 64, obs: int = 29, act: int = 8, seed: int = 0,
                   updates_n: int = 5, perturb=()) -> dict:
    """Losses and one update of ours and the reference's on one batch and one set of parameters."""
    from aqm_mjx.learn import methods  # pylint: disable=import-outside-toplevel

    cls = ref_agents[name]
    ref_cfg, cfg = configs(name, sys.modules[cls.__module__], perturb=perturb)
    learner = methods.get(name).make(cfg, obs, act)
    state = learner.init(jax.random.PRNGKey(seed))
    # the targets start apart from the parameters, so the Polyak step and the target-read terms show
    state = state.replace(target=jax.tree.map(lambda x: x + 0.05 * jnp.sin(jnp.arange(x.size).reshape(x.shape)),
                                              state.target))
    agent = cls.create(seed, np.zeros((2, obs), np.float32), np.zeros((2, act), np.float32), ref_cfg)
    params = ours_into_reference(state, agent.network.params)
    agent = agent.replace(network=agent.network.replace(params=params, opt_state=agent.network.tx.init(params)))
    ref_batch, batch = batches(jax.random.PRNGKey(seed + 1), b, obs, act)
    key = jax.random.PRNGKey(seed + 2)

    ref_loss, ref_info = agent.total_loss(ref_batch, agent.network.params, rng=key)
    loss, info = jax.jit(learner.loss)(state.params, state.target, batch, key)
    named = {k: NAMES.get(k.split('/', 1)[1], k.split('/', 1)[1]) for k in ref_info}
    prefixes = MODULES if name == 'saw' else {}  # SAW's low_actor is our sub_actor; HIQL's is our low_actor
    named = {k: f'{prefixes.get(k.split("/", 1)[0], k.split("/", 1)[0])}/{v}' for k, v in named.items()}
    shared = sorted(k for k in ref_info if named[k] in info)
    rows = [('loss (total)', float(ref_loss), float(loss))] + [(k, float(ref_info[k]), float(info[named[k]]))
                                                              for k in shared]

    # gradients of the total loss (the reference's targets get none: it reads them outside grad_params)
    ref_g = dict(_flat(jax.grad(lambda p_: agent.total_loss(ref_batch, p_, rng=key)[0])(agent.network.params)))
    ref_g = {p_: v for p_, v in ref_g.items() if not p_[0].startswith('modules_target_')}
    our_g = to_reference(jax.grad(lambda p_: learner.loss(p_, state.target, batch, key)[0])(state.params))
    g_rel = max(float(jnp.max(jnp.abs(v - our_g[p_])) / (jnp.max(jnp.abs(v)) + 1e-12)) for p_, v in ref_g.items())
    # several updates on different batches (one Adam step alone is about lr * sign(gradient))
    step = jax.jit(learner.step)
    updates = []
    for i in range(updates_n):
        rb, ob = batches(jax.random.PRNGKey(seed + 10 + i), b, obs, act)
        agent, _ = agent.update(rb)
        state, _ = step(state, ob, key)
        ours_now = {**to_reference(state.params), **to_reference(state.target, 'target')}
        updates.append(largest_diff(dict(_flat(agent.network.params)), ours_now))
    moved = max(float(jnp.max(jnp.abs(jnp.asarray(v) - dict(_flat(params))[p_]))) for p_, v in
                _flat(agent.network.params))
    return dict(rows=rows, grad_rel=g_rel, updates=updates, moved=moved, arrays=len(_flat(agent.network.params)),
                only_ref=sorted(set(ref_info) - set(shared)), only_ours=sorted(set(info) - {named[k] for k in shared}))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    p.add_argument('--reference', default=os.environ.get('AQM_OGBENCH_REF'),
                   help='a checkout of seohongpark/ogbench, or a bare git copy of it')
    p.add_argument('--saw-reference', default=os.environ.get('AQM_SAW_REF'),
                   help="a checkout of johnlyzhou/saw (OGBench's impls with SAW), or a bare git copy; SAW is "
                        'compared when it is given')
    p.add_argument('--methods', nargs='+', default=list(METHODS), choices=METHODS)
    p.add_argument('--loss-tol', type=float, default=1e-5, help='largest relative difference of a loss')
    p.add_argument('--param-tol', type=float, default=1e-6, help='largest absolute difference of a parameter')
    p.add_argument('--set', action='append', default=[], metavar='FIELD=VALUE',
                   help='change one of our config fields (e.g. expectile=0.8) to see the check report a mismatch')
    a = p.parse_args(argv)
    root, why = reference_impls(a.reference)
    if root is None:
        print(f'bench_parity: skipped: {why}')
        return 0
    try:
        import ml_collections  # noqa: F401  pylint: disable=import-outside-toplevel,unused-import
    except ImportError:
        print('bench_parity: skipped: the reference agents import ml_collections; pip install ml-collections')
        return 0
    refs = {n: None for n in a.methods}
    ogb = import_reference(root)
    for n in a.methods:
        refs[n] = ogb.agents if n not in SAW_ONLY else None
    if any(n in SAW_ONLY for n in a.methods):
        saw_root, saw_why = reference_impls(a.saw_reference) if a.saw_reference else (None, 'no --saw-reference')
        if saw_root is None:
            print(f'bench_parity: SAW skipped: {saw_why} (a copy of johnlyzhou/saw)')
        else:
            saw_agents = import_reference(saw_root).agents
            for n in SAW_ONLY:
                refs[n] = saw_agents
    methods_run = [n for n in a.methods if refs[n] is not None]
    if a.set:
        print(f'our configs changed on purpose: {", ".join(a.set)}')
    print(f'reference: {root}/impls (distrax stood in by a diagonal Gaussian); jax {jax.__version__} on '
          f'{jax.devices()[0].platform}; batch 64, 29-d observations, 8-d actions, widths 3 x 32')
    failed = []
    for name in methods_run:
        r = compare_method(name, refs[name], perturb=a.set)
        print(f'\n== {name} (reference: {sys.modules[refs[name][name].__module__].__file__})')
        print(f'{"quantity (reference name)":<28}{"reference":>16}{"ours":>16}{"rel. diff":>12}')
        worst = 0.0
        for k, x, y in r['rows']:
            rel = abs(x - y) / max(abs(x), 1e-6)
            worst = max(worst, rel)
            print(f'{k:<28}{x:>16.8g}{y:>16.8g}{rel:>12.2e}')
        if r['only_ref'] or r['only_ours']:
            print(f'info only in the reference: {", ".join(r["only_ref"]) or "-"}; only ours: '
                  f'{", ".join(r["only_ours"]) or "-"}')
        pmax = max(d for d, _ in r['updates'])
        print(f'gradient of the total loss: largest |ours - reference| / max |reference| = {r["grad_rel"]:.2e}')
        print(f'{len(r["updates"])} updates ({r["arrays"]} arrays, targets included), largest |ours - reference| '
              'after each: ' + ', '.join(f'{d:.1e}' for d, _ in r['updates'])
              + f' (worst: {max(r["updates"])[1]}); the updates moved parameters by up to {r["moved"]:.2e}')
        ok = worst <= a.loss_tol and r['grad_rel'] <= a.loss_tol and pmax <= a.param_tol
        print(f'{name}: {"PARITY" if ok else "MISMATCH"} (losses within {worst:.1e} relative, gradients within '
              f'{r["grad_rel"]:.1e}, parameters within {pmax:.1e})')
        if not ok:
            failed.append(name)
    print('\nall methods at parity' if not failed else f'\nmismatch: {", ".join(failed)}')
    return 1 if failed else 0


if __name__ == '__main__':
    raise SystemExit(main())
