"""Accelerations of a Lagrangian model with and without its declared mass structure
(`lgnn.physics.MassStructure`): milliseconds per batched call, compile apart, and how far
the two paths' accelerations differ. Untrained parameters: the cost and the agreement do
not depend on training.

    python tools/mass_structure_speed.py --model lgn --scene chain100-3d --batch 8 --rounds 5
    python tools/mass_structure_speed.py --model lgn --scene chain100 --batch 300 --paths declared   # an evaluation's batch on a GPU

The model is configured for its grid's training scene of the scene's dimension (chain4 or
chain4-3d); states are the scene's own positions with random velocities on its
constraint manifold. Prints one markdown table row per path and the environment.
"""
import argparse
import time

from lgnn import runtime

parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
parser.add_argument("--model", default="lgn")
parser.add_argument("--scene", default="chain100-3d")
parser.add_argument("--batch", type=int, default=8)
parser.add_argument("--rounds", type=int, default=5, help="timed calls after the compiling one")
parser.add_argument("--paths", nargs="+", choices=("declared", "dense"), default=("declared", "dense"),
                    help="which paths to time (the dense one is the costly one at large batches)")
args = parser.parse_args()
runtime.configure()

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from lgnn import physics, provenance  # noqa: E402
from lgnn.learn import models  # noqa: E402
from lgnn.scene import get_scene  # noqa: E402

scene = get_scene(args.scene)
config = models.ModelConfig.for_scene(args.model, get_scene("chain4-3d" if scene.dim == 3 else "chain4"))
params = models.init(jax.random.PRNGKey(0), config)
q = jnp.asarray(scene.nodes)
project = jax.jit(physics.projection_fn(scene))
qs = jnp.broadcast_to(q, (args.batch, *q.shape))
qds = jax.vmap(lambda key: project(q, jax.random.normal(key, q.shape))[1])(jax.random.split(jax.random.PRNGKey(1), args.batch))
structure = config.spec.mass(config, params, scene) if config.spec.mass else None
free = len(physics.prepare(scene).constraints.free)
paths = {
    "declared": (models.acceleration_fn(config, params, scene),
             structure.products(physics.prepare(scene)) if structure else free),
    "dense": (physics.acceleration_fn(scene, models.lagrangian_fn(config, params, scene)), free),
}
print(f"{args.model} on {args.scene}, batch {args.batch}; {provenance.device()}; {provenance.versions()}; commit {provenance.commit()}")
print("| path (declared structure or dense Hessian) | products per state | compile + first call s | per call ms (min..max) | max difference / max acceleration |")
print("|---|---|---|---|---|")
reference = None
for label in args.paths:
    accel, products = paths[label]
    call = jax.jit(jax.vmap(accel))
    start = time.perf_counter()
    out = np.asarray(call(qs, qds).block_until_ready())
    compile_s = time.perf_counter() - start
    times = []
    for _ in range(args.rounds):
        start = time.perf_counter()
        call(qs, qds).block_until_ready()
        times.append(1e3 * (time.perf_counter() - start))
    reference = out if reference is None else reference
    difference = np.abs(out - reference).max() / np.abs(reference).max()
    print(f"| {label} | {products} | {compile_s:.1f} | {np.median(times):.1f} ({min(times):.1f}..{max(times):.1f}) | {difference:.1e} |", flush=True)
