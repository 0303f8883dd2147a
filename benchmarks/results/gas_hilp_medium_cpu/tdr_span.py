import sys, numpy as np, jax, jax.numpy as jnp
from aqm_mjx.learn import fit
d = np.load('/work/main/runs/antmaze-medium/data/antmaze-medium-navigate.npz')
obs = d['observations'][:1001*20].reshape(20, 1001, -1)
for ck in sys.argv[1:]:
    t = fit.load(ck, log=lambda *_: None)
    ag = t.agent
    f = jax.vmap(jax.vmap(lambda o: ag.encode(ag.aux, o)))(jnp.asarray(obs))
    out = []
    for k in (1, 8, 16, 50, 100, 300):
        dd = jnp.linalg.norm(f[:, k:] - f[:, :-k], axis=-1)
        out.append(f'k={k}: {float(dd.mean()):.2f}')
    print(ck, t.step, '; '.join(out))
