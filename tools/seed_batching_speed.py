"""Seconds per training epoch of LGNN on chain4's paper data (750 Adam steps): one seed
alone against 3 seeds in one vmapped program (`lgnn.learn.train.train_seeds`; issue 13,
item 2). Compile runs excluded, best of 3.

    PYTHONPATH=. python tools/seed_batching_speed.py

Measured (2-core AMD EPYC, shared, load ~6): 1 seed 1.53 s, 3 seeds vmapped 2.61 s per
epoch, i.e. 1.76x the throughput of three separate runs.
"""
import time
import jax, jax.numpy as jnp
import lgnn
lgnn.configure()
from lgnn.learn import data, models, protocol, train
from lgnn.scene import get_scene
scene = get_scene("chain4")
ds = data.load_or_generate(data.DataConfig("chain4"), "results/datasets")
arrays = tuple(jnp.asarray(a[ds.train]) for a in (ds.q, ds.qd, ds.qdd))
model = models.ModelConfig.for_scene("lgnn", scene)
config = protocol.scheduled(protocol.TrainConfig(), len(ds.train) // protocol.TrainConfig().batch_size)  # the paper budget: 1e-3, warm-up 1000
states = [train.initial_state(model, protocol.TrainConfig(seed=s)) for s in range(3)]
one = train.compiled_epoch_fn(model, scene, config)
many = train.compiled_epoch_fn(model, scene, config, vmapped=True)
stack = lambda trees: jax.tree.map(lambda *l: jnp.stack(l), *trees)
p3, o3, k3 = stack([s.params for s in states]), stack([s.opt_state for s in states]), jnp.stack([jax.random.PRNGKey(s) for s in range(3)])
for name, run in (("1 seed", lambda: one(states[0].params, states[0].opt_state, *arrays, jax.random.PRNGKey(0))), ("3 seeds vmapped", lambda: many(p3, o3, *arrays, k3))):
    jax.block_until_ready(run())
    times = []
    for _ in range(3):
        t = time.perf_counter(); jax.block_until_ready(run()); times.append(time.perf_counter() - t)
    print(f"{name}: {min(times):.2f} s per epoch (best of 3)", flush=True)
