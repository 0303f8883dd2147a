"""OGBench file I/O (against ogbench.utils.load_dataset) and the goal sampler's statistics."""

import io
import os
import zipfile

import jax
import numpy as np
import pytest
from ogbench.utils import load_dataset

from aqm_mjx.data import dataset as dsm
from aqm_mjx.data import goals


def fake_raw(n_traj=6, length=40, obs=29, act=8, seed=0, with_info=True):
    rng = np.random.default_rng(seed)
    n = n_traj * length
    term = np.zeros(n, bool)
    term[length - 1::length] = True
    d = dict(observations=rng.normal(size=(n, obs)).astype(np.float32),
             actions=rng.uniform(-1, 1, (n, act)).astype(np.float32), terminals=term)
    if with_info:
        d['qpos'] = rng.normal(size=(n, 15)).astype(np.float32)
        d['qvel'] = rng.normal(size=(n, 14)).astype(np.float32)
    return d


def test_round_trip_bit_for_bit_and_ogbench_reads_it(tmp_path):
    raw = fake_raw()
    path = str(tmp_path / 'antmaze-medium-navigate-v0.npz')
    dsm.write_ogbench(path, raw)
    back = dsm.read_ogbench(path, obs_size=29, action_size=8)
    for k in raw:
        assert back[k].dtype == raw[k].dtype and np.array_equal(back[k], raw[k]), k
    path2 = str(tmp_path / 'again.npz')
    dsm.write_ogbench(path2, back)
    f1, f2 = np.load(path), np.load(path2)
    for k in raw:
        assert f1[k].tobytes() == f2[k].tobytes()
    ref = load_dataset(path)  # OGBench's own loader, unchanged
    ours = dsm.transitions(back)
    for k in ('observations', 'actions', 'next_observations', 'terminals'):
        np.testing.assert_array_equal(ref[k], ours[k])
    assert len(ref['observations']) == 6 * 39  # the last state of each trajectory is no source
    assert dsm.val_path(path).endswith('antmaze-medium-navigate-v0-val.npz')


def _bad(tmp_path, name, **arrays):
    p = str(tmp_path / f'{name}.npz')
    np.savez(p, **arrays)
    return p


def test_malformed_files_have_clear_messages(tmp_path):
    raw = fake_raw(with_info=False)
    cases = {
        'missing': (dict(observations=raw['observations'], actions=raw['actions']), "missing key 'terminals'"),
        'lengths': (dict(raw, actions=raw['actions'][:-3]), 'actions has 237 rows but terminals has 240'),
        'nan': (dict(raw, observations=np.where(np.arange(240)[:, None] == 7, np.nan, raw['observations'])),
                'observations contains NaN or inf .* first at row 7'),
        'inf': (dict(raw, actions=np.full_like(raw['actions'], np.inf)), 'actions contains NaN or inf'),
        'empty': (dict(observations=np.zeros((0, 29)), actions=np.zeros((0, 8)), terminals=np.zeros(0, bool)), 'empty'),
        'noend': (dict(raw, terminals=np.zeros(240, bool)), 'no trajectory end is marked'),
        'cut': (dict(raw, terminals=np.r_[raw['terminals'][:-1], False]), 'last state is not marked terminal'),
        'object': (dict(raw, observations=np.array([None] * 240, dtype=object)), 'object array'),
        'scalar': (dict(raw, terminals=np.array(True)), 'terminals is a single value \\(a 0-d array\\)'),
    }
    for name, (arrays, msg) in cases.items():
        with pytest.raises(dsm.DatasetError, match=msg):
            dsm.read_ogbench(_bad(tmp_path, name, **arrays))
    with pytest.raises(dsm.DatasetError, match='observations are 29-d but the environment expects 2'):
        dsm.read_ogbench(_bad(tmp_path, 'width', **raw), obs_size=2)
    with pytest.raises(dsm.DatasetError, match='actions are 8-d but the environment expects 2'):
        dsm.read_ogbench(_bad(tmp_path, 'awidth', **raw), action_size=2)
    with pytest.raises(dsm.DatasetError, match='no such file'):
        dsm.read_ogbench(str(tmp_path / 'nope.npz'))
    junk = tmp_path / 'junk.npz'
    junk.write_bytes(b'not a zip')
    with pytest.raises(dsm.DatasetError, match='not an .npz archive'):
        dsm.read_ogbench(str(junk))
    # a header declaring 2^40 x 29 floats (118,784 GiB): named, not numpy's allocation traceback
    huge = _bad(tmp_path, 'huge', **raw)
    with zipfile.ZipFile(huge) as z:
        members = {n: z.read(n) for n in z.namelist()}
    head = io.BytesIO()
    np.lib.format.write_array_header_1_0(head, {'descr': '<f4', 'fortran_order': False, 'shape': (2 ** 40, 29)})
    members['observations.npy'] = head.getvalue() + b'\0' * 64
    with zipfile.ZipFile(huge, 'w') as z:
        for n, b in members.items():
            z.writestr(n, b)
    with pytest.raises(dsm.DatasetError, match=r'observations declares shape \(1099511627776, 29\) of float32 '
                                               r'\(118,784 GiB\), more than'):
        dsm.read_ogbench(huge)


def test_failed_write_keeps_the_old_file(tmp_path):
    path = str(tmp_path / 'd.npz')
    dsm.write_ogbench(path, fake_raw())
    before = open(path, 'rb').read()
    with pytest.raises(dsm.DatasetError):
        dsm.write_ogbench(path, dict(fake_raw(), terminals=np.zeros(240, bool)))
    assert open(path, 'rb').read() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ['d.npz']  # no temporary left behind
    umask = os.umask(0)
    os.umask(umask)
    assert os.stat(path).st_mode & 0o777 == 0o666 & ~umask  # as open() creates files, not mkstemp's 0600


def test_goal_sampler_mixture_offsets_and_boundaries():
    raw = fake_raw(n_traj=50, length=400, with_info=False)
    raw['observations'][:, 0] = np.arange(len(raw['terminals']))  # observation 0 = its own index
    ds = dsm.to_device(raw)
    cfg = goals.GoalSampling(p_current=0.2, p_trajectory=0.5, p_random=0.3, geometric=True, discount=0.9, subgoal_offset=25)
    n = 200_000
    b = jax.jit(lambda k: goals.sample(ds, k, n, cfg))(jax.random.PRNGKey(0))
    idx, goal, sub, kind = (np.asarray(x) for x in (b.index, b.goal_index, b.subgoal_index, b.goal_kind))
    traj = idx // 400
    # Mixture frequencies within 4 standard deviations.
    for k, p in enumerate((0.2, 0.5, 0.3)):
        assert abs((kind == k).mean() - p) < 4 * np.sqrt(p * (1 - p) / n), (k, (kind == k).mean())
    # Sources are never the last state; next observation is t + 1.
    assert np.all(idx % 400 != 399)
    np.testing.assert_array_equal(np.asarray(b.next_observations[:, 0]), idx + 1)
    np.testing.assert_array_equal(np.asarray(b.goals[:, 0]), goal)
    # Current goals are the state; trajectory goals and subgoals stay in the trajectory, after t.
    assert np.all(goal[kind == 0] == idx[kind == 0])
    t = kind == 1
    assert np.all(goal[t] // 400 == traj[t]) and np.all(goal[t] > idx[t])
    assert np.all(sub // 400 == traj) and np.all(sub == np.minimum(idx + 25, traj * 400 + 399))
    # Geometric offsets: P(offset = 1) = 1 - discount and mean 1 / (1 - discount), away from the end.
    far = t & (idx % 400 < 200)
    off = goal[far] - idx[far]
    assert abs((off == 1).mean() - 0.1) < 4 * np.sqrt(0.09 / far.sum())
    assert abs(off.mean() - 10.0) < 4 * np.sqrt(90.0 / far.sum())
    # Random goals cover the whole dataset, across trajectories.
    r = goal[kind == 2]
    assert r.min() < 400 and r.max() > 19_500 and (r // 400 != traj[kind == 2]).mean() > 0.9
    # Uniform trajectory goals: uniform over t + 1 .. end.
    u = goals.sample(ds, jax.random.PRNGKey(1), n, goals.GoalSampling(geometric=False))
    ui, ug = np.asarray(u.index), np.asarray(u.goal_index)
    assert np.all(ug > ui) and np.all(ug // 400 == ui // 400)
    frac = (ug - ui) / (399 - ui % 400)
    assert abs(frac.mean() - 0.5) < 0.01


def test_saws_subgoal_cap_stops_at_the_goal():
    """subgoal_cap='goal': s_{min(t + k, goal index)} for current and trajectory goals, the trajectory's
    end for random goals (SAW's rule, AQM's default); 'end' ignores the goal."""
    raw = fake_raw(n_traj=20, length=100, with_info=False)
    raw['observations'][:, 0] = np.arange(len(raw['terminals']))
    ds = dsm.to_device(raw)
    mix = dict(p_current=0.2, p_trajectory=0.5, p_random=0.3, geometric=True, discount=0.9, subgoal_offset=25)
    for cap in ('goal', 'end'):
        b = goals.sample(ds, jax.random.PRNGKey(2), 20_000, goals.GoalSampling(**mix, subgoal_cap=cap))
        idx, goal, sub, kind = (np.asarray(x) for x in (b.index, b.goal_index, b.subgoal_index, b.goal_kind))
        end = idx // 100 * 100 + 99
        want = np.minimum(idx + 25, np.where((kind == 2) | (cap == 'end'), end, goal))
        np.testing.assert_array_equal(sub, want)
        np.testing.assert_array_equal(np.asarray(b.subgoals[:, 0]), sub)
        if cap == 'goal':  # the rule binds: many trajectory goals lie closer than k
            assert np.mean(sub[kind == 1] < np.minimum(idx + 25, end)[kind == 1]) > 0.5
    with pytest.raises(ValueError, match='subgoal_cap'):
        goals.GoalSampling(subgoal_cap='trajectory')


def test_bad_sampling_config():
    with pytest.raises(ValueError, match='sum to 1'):
        goals.GoalSampling(p_current=0.5, p_trajectory=0.6)
    with pytest.raises(ValueError, match='discount'):
        goals.GoalSampling(discount=1.0)


def test_a_dataset_without_transitions_is_refused():
    raw = fake_raw(n_traj=3, length=1, with_info=False)  # every state ends its trajectory
    with pytest.raises(dsm.DatasetError, match='no transitions'):
        dsm.to_device(raw)


def test_fingerprint_is_the_sha256_of_names_dtypes_shapes_and_bytes():
    import hashlib
    d = dict(terminals=np.array([False, True]), actions=np.arange(4, dtype=np.float32).reshape(2, 2))
    h = hashlib.sha256()
    h.update(b'actions\0<f4\0(2, 2)\0')
    h.update(np.arange(4, dtype=np.float32).tobytes())
    h.update(b'terminals\0|b1\0(2,)\0')
    h.update(b'\x00\x01')
    assert dsm.fingerprint(d) == h.hexdigest()
    raw = fake_raw()
    assert dsm.fingerprint(raw) == dsm.fingerprint(dict(reversed(list(raw.items()))))  # key order does not count
    assert dsm.fingerprint(raw) == dsm.fingerprint({k: np.asfortranarray(v) for k, v in raw.items()})
    for change in (lambda r: r['actions'].__setitem__((3, 2), r['actions'][3, 2] + 1e-6),  # one value
                   lambda r: r.__setitem__('terminals', r['terminals'].astype(np.int8)),  # the dtype
                   lambda r: r.__setitem__('qvel', r['qvel'].reshape(-1, 7, 2))):  # the shape
        other = {k: v.copy() for k, v in raw.items()}
        change(other)
        assert dsm.fingerprint(other) != dsm.fingerprint(raw)
