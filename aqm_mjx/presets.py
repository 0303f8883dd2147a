"""Every default of a run, in one table: the training loop's size, the map, the agent's rules and
the evaluation protocol, by preset.

    presets.RUN['cpu']['agent']['kappa']   # 1.0: the cpu preset's budget slack
    presets.default('map', 'delta')        # 8.0: what MapConfig() takes, the default preset's value
    presets.loop('ci')                     # steps, batch size, chunking and checkpoints of the ci preset

The fields that every row sets (:data:`SHARED`: the loop, the map's delta, the agent's kappa and
switch radius) take :data:`DEFAULT`'s value here as their dataclass default
(``AgentConfig().kappa == RUN['cpu']['agent']['kappa']``); every other field keeps a neutral default
in its class (no extension of the paper's rule, the paper's protocol: 50 episodes, no calibration),
which a row may change. A method's config adds only its own sizes to :func:`loop` (``learn/aqm.py``,
``learn/baselines/base.py``). This module imports nothing from the package, so every stage reads it.
"""

from __future__ import annotations

DEFAULT = 'cpu-long'  # the preset whose values are the configs' dataclass defaults (and every command's)

# The training loop, once for every method: updates, batch, updates per jitted call, metric lines and
# checkpoints.
LOOP = {
    # the paper's Appendix 10 (and OGBench's): 10^6 updates of batch 1024
    'paper': dict(steps=1_000_000, batch_size=1024, updates_per_call=1000, log_every=5000, checkpoint_every=50_000),
    # a few minutes on a 2-core CPU: 50x fewer updates, a quarter of the batch
    'cpu': dict(steps=20_000, batch_size=256, updates_per_call=500, log_every=500, checkpoint_every=5_000),
    # cpu for 1.25x the updates: antmaze-medium in about 5 min of training on a 2-core CPU
    'cpu-quick': dict(steps=25_000, batch_size=256, updates_per_call=500, log_every=500, checkpoint_every=5_000),
    # cpu for 2.5x the updates (antmaze-medium in about 7 min of training on a 2-core CPU, antmaze-large in
    # 1-1.5 h for 2 seeds); a checkpoint and learning-curve point every 10,000
    'cpu-long': dict(steps=50_000, batch_size=256, updates_per_call=500, log_every=500, checkpoint_every=10_000),
    # cpu for 7.5x the updates: antmaze-giant navigate (RESULTS.md section 2.3)
    'cpu-giant': dict(steps=150_000, batch_size=256, updates_per_call=500, log_every=500, checkpoint_every=5_000),
    # tests and notebooks: seconds on a CPU
    'ci': dict(steps=200, batch_size=64, updates_per_call=50, log_every=50, checkpoint_every=100),
}

# A run's sections beside training. 'collect_episodes' is the data a run collects when no --dataset or
# --collect-episodes is given (100 where a row does not say), 'collect_physics' the physics it collects in
# ('mjx' where a row does not say; 'mujoco': MuJoCo's C library on the host, 6-8x faster on a CPU).
# 'host_evaluation': True where the row's evaluation, on a host without an accelerator, runs in OGBench's
# own environments (backend 'ogbench', 8x faster than MJX on a 2-core CPU, RESULTS 7.4) unless the user
# names a backend or an MJX physics; with an accelerator it stays in MJX.

# The replanning rule of the cpu and cpu-long rows, written once: map and agent values measured at the cpu
# scale (RESULTS.md section 3.4); the AQM row on the stall rule with parallel cuts 0.6 (the paper's single
# cut: cut_slack=0), its patience 6 x the calibration pass's 90th percentile of the longest stall: stable
# across calibration keys where the 0.5% quantile was not, and the larger closure gain on four models'
# development episodes (benchmarks/results/diagnose_closures_dev/NOTES.md); kappas (fixed rule, paper=cal)
# at the protocol's false-alarm rate. Learning curve: 2 development episodes per task at every checkpoint,
# in OGBench's environments (on a 2-core CPU about 8 s a point there, 33 s in MJX)
_CPU_RULE = dict(map=dict(delta=8.0), agent=dict(kappa=1.0, switch_radius=10.0, cut_slack=0.6),
                 protocol=dict(episodes=4, envs=64, calibrate='stall', stall_scale=6.0, curve_episodes=2,
                               curve_backend='ogbench'),
                 host_evaluation=True)

RUN = {
    # the wiring, not the skill: 4 collected episodes, 200 updates, 60-step episodes (compiling dominates)
    'ci': dict(map=dict(delta=0.5, max_keypoints=32, candidates=400),
               agent=dict(kappa=0.0, switch_radius=0.6),
               protocol=dict(episodes=2, horizon=60, envs=64, calibration_episodes=20),
               collect_episodes=4),
    # 100 MJX episodes, 20,000 updates (the models of RESULTS.md section 1), the cpu rule
    'cpu': dict(_CPU_RULE),
    # cpu-long's data and rule at half its updates: `aqm-mjx run --preset cpu-quick` in under 9 min on a 2-core
    # CPU, but replanning does not pay on every model (+2.0 and +21.3 over no pruning on two; RESULTS.md
    # section 3.1), so it is not the default
    'cpu-quick': dict(_CPU_RULE, collect_episodes=400, collect_physics='mujoco'),
    # 4x the data (collected on the host), 2.5x the updates, the same rule. At the cpu scale the controller
    # stalls on detours and replanning pays on two models in four; here on every model trained so far
    # (RESULTS.md section 3.1)
    'cpu-long': dict(_CPU_RULE, collect_episodes=400, collect_physics='mujoco'),
    # antmaze-giant navigate in under 2 h on a 2-core CPU (RESULTS.md section 2.3): 400 collected episodes of
    # 2,001 states, 150,000 updates; a map that fits the giant maze (delta 12, 512 keypoint slots: about 190
    # keypoints, where delta 8 overflows 256); the stall rule at the 0.5% quantile with the paper's single cut
    'cpu-giant': dict(map=dict(delta=12.0, max_keypoints=512), agent=dict(kappa=1.0, switch_radius=10.0),
                      protocol=dict(episodes=10, envs=64, calibrate='stall', curve_episodes=2,
                                    curve_backend='ogbench'),
                      collect_episodes=400, host_evaluation=True),
    # the paper's sizes (Appendix 10): delta 10 (its best in Figure 10, swept 10-25), OGBench's 50 episodes
    'paper': dict(map=dict(delta=10.0), agent=dict(kappa=0.25, switch_radius=5.0),
                  protocol=dict(episodes=50, envs=1024, curve_episodes=10)),
}
# the network sizes each preset trains (the row of a method's SIZES and PRESET_OVERRIDES): cpu-quick, cpu-long
# and cpu-giant train the cpu networks for longer
NETWORKS = {'paper': 'paper', 'cpu': 'cpu', 'cpu-quick': 'cpu', 'cpu-long': 'cpu', 'cpu-giant': 'cpu', 'ci': 'ci'}
SECTIONS = ('map', 'agent', 'protocol')
SHARED = dict(map=('delta',), agent=('kappa', 'switch_radius'))  # set by every row; the classes' defaults


def names() -> list[str]:
    return list(RUN)


def check(name: str) -> str:
    """``name`` if it is a preset, else a ValueError that lists them."""
    if name not in RUN:
        raise ValueError(f'unknown run preset {name!r}; expected one of {", ".join(RUN)}')
    return name


def loop(name: str) -> dict:
    """The loop fields of preset ``name`` (a copy)."""
    if name not in LOOP:
        raise ValueError(f'unknown preset {name!r}; expected one of {", ".join(LOOP)}')
    return dict(LOOP[name])


def networks(name: str) -> str:
    """The network-size row preset ``name`` trains (``'cpu'`` for ``cpu-long`` and ``cpu-giant``)."""
    if name not in NETWORKS:
        raise ValueError(f'unknown preset {name!r}; expected one of {", ".join(NETWORKS)}')
    return NETWORKS[name]


def section(name: str, part: str) -> dict:
    """Fields that preset ``name`` sets in ``part`` (``'map'``, ``'agent'``, ``'protocol'``; a copy)."""
    return dict(RUN[check(name)].get(part, {}))


def default(part: str, field: str):
    """The dataclass default of ``part.field``: :data:`DEFAULT`'s value (``part`` is a run section,
    or ``'loop'``)."""
    if part == 'loop':
        return LOOP[DEFAULT][field]
    if field not in SHARED.get(part, ()):
        raise ValueError(f'{part}.{field} is not set by every preset; its class holds a neutral default')
    return RUN[DEFAULT][part][field]


def collect_episodes(name: str) -> int:
    """Episodes a run of preset ``name`` collects when the user names no number."""
    return RUN[check(name)].get('collect_episodes', 100)


def collect_physics(name: str) -> str:
    """The physics a run of preset ``name`` collects its data in when the user names none: ``'mjx'`` or
    ``'mujoco'`` (the host)."""
    return RUN[check(name)].get('collect_physics', 'mjx')


def host_evaluation(name: str) -> bool:
    """Whether a run of preset ``name`` evaluates in OGBench's environments on a host without an
    accelerator when the user names no backend (the ``cpu`` rows)."""
    return bool(RUN[check(name)].get('host_evaluation', False))
