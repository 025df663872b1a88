"""Where one LGN acceleration's time goes on a large scene, what the dense solve's
alternatives would cost, and whether a trained LGN's mass matrix would allow them.

    python tools/lgn_mass_costs.py parts --scene chain100 --batch 300
    python tools/lgn_mass_costs.py solves --batch 300
    python tools/lgn_mass_costs.py definiteness --scene chain100 --every 100
    python tools/lgn_mass_costs.py agreement --scene chain100 --every 100

- `parts`: milliseconds per batched call (compile apart, median of `--rounds`) of each
  piece of `physics.acceleration_fn` with LGN's declared mass structure
  (`physics.euler_lagrange`, the functions the acceleration calls), untrained
  parameters: the Lagrangian, the right-hand side (`dL/dq` and the Coriolis product),
  the pooled Jacobian's forward products, the mass products (the local part's
  Hessian-vector products with the pooled low-rank part, which holds the Jacobian's
  products again), the whole mass matrix, the regularised KKT solve, and the whole
  acceleration; on a long chain, whose acceleration takes the banded elimination with
  the Woodbury correction, also the whole acceleration with the mass matrix assembled
  and the dense KKT solve instead.
- `solves`: the same batch of random systems of the sizes of chain100 (200 free
  coordinates, 100 rods) and chain100-3d (300, 100): the KKT matrix's LU and the
  refined solve as `solvers.solve_kkt` does them, against factorisations that need
  more of `M` (an LU of `M` alone; a Cholesky factorisation, which needs `M` positive
  definite).
- `definiteness`: the committed checkpoints' 3 seeds of LGN (trained on chain4 or
  chain4-3d; run from the repository's root) rolled out from the benchmark's evaluation initial conditions of
  `--scene`; every `--every` frames, how many states are finite, and of those how many
  have a mass matrix over the free coordinates that is not positive definite (its
  Cholesky factorisation fails), and the smallest ratio of its extreme eigenvalues.
- `agreement`: the same rollouts (`--states` of the initial conditions, `--duration`);
  every `--every` frames, the accelerations `models.acceleration_fn` gives (on a long
  chain the banded elimination with the Woodbury correction) against the dense path's
  (`physics.acceleration_fn` of the Lagrangian: forward-differentiated mass matrix,
  dense KKT LU), at the same states: the largest difference over the states, each
  relative to its state's largest acceleration, and at how many finite states the
  mass matrix is not positive definite.

Prints the environment first, then one line per measurement.
"""
import argparse
import time

from lgnn import runtime

parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
parser.add_argument("what", choices=("parts", "solves", "definiteness", "agreement"))
parser.add_argument("--scene", default="chain100")
parser.add_argument("--batch", type=int, default=300)
parser.add_argument("--rounds", type=int, default=7, help="timed calls after the compiling one")
parser.add_argument("--every", type=int, default=100, help="definiteness, agreement: frames between the states checked")
parser.add_argument("--states", type=int, default=None, help="definiteness, agreement: the first this many initial conditions (default all)")
parser.add_argument("--duration", type=float, default=None, help="definiteness, agreement: seconds rolled out (default the profile's)")
args = parser.parse_args()
runtime.configure()

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from lgnn import physics, provenance  # noqa: E402
from lgnn.learn import models  # noqa: E402
from lgnn.physics import solvers  # noqa: E402
from lgnn.scene import get_scene  # noqa: E402

print(f"{args.what}; {provenance.device()}; {provenance.versions()}; commit {provenance.commit()}", flush=True)


def timed(label: str, fn, *inputs) -> None:
    call = jax.jit(fn)
    jax.block_until_ready(call(*inputs))
    times = []
    for _ in range(args.rounds):
        start = time.perf_counter()
        jax.block_until_ready(call(*inputs))
        times.append(1e3 * (time.perf_counter() - start))
    print(f"| {label} | {np.median(times):.2f} ({min(times):.2f}..{max(times):.2f}) |", flush=True)


def training_scene(scene):
    return get_scene("chain4-3d" if scene.dim == 3 else "chain4")


def parts() -> None:
    scene = get_scene(args.scene)
    config = models.ModelConfig.for_scene("lgn", training_scene(scene))
    params = models.init(jax.random.PRNGKey(0), config)
    q = jnp.asarray(scene.nodes)
    project = jax.jit(physics.projection_fn(scene))
    qs = jnp.broadcast_to(q, (args.batch, *q.shape))
    qds = jax.vmap(lambda key: project(q, jax.random.normal(key, q.shape))[1])(jax.random.split(jax.random.PRNGKey(1), args.batch))
    constraints = physics.prepare(scene).constraints
    structure = config.spec.mass(config, params, scene)
    lagrangian = models.lagrangian_fn(config, params, scene)
    # The pieces `physics.acceleration_fn` solves, as LGN's acceleration builds them.
    equations = physics.euler_lagrange(scene, lagrangian, structure)
    if equations.pooled_jacobian is None:
        raise SystemExit(f"LGN's mass structure is not used on {args.scene} (the dense path is fewer products): nothing to time by part")

    def restricted(fn):
        return lambda q, qd: fn(constraints.restrict(q), constraints.restrict(qd))

    masses = jax.jit(jax.vmap(restricted(equations.mass_matrix)))(qs, qds)

    def solve(q, qd, m):
        x, v = constraints.restrict(q), constraints.restrict(qd)
        return solvers.solve_kkt(m, constraints.jacobian(x), jnp.ones(m.shape[0]), -constraints.jacobian_dot_v(x, v))

    local, pooled = equations.local, physics.prepare(scene).pooled_jacobian(structure.supports)
    print(f"LGN on {args.scene}, batch {args.batch}: {local.n_colours * scene.dim} local and {pooled.n_colours * scene.dim} "
          f"Jacobian products, {len(constraints.free)} free coordinates")
    print("| part of one acceleration | ms per batched call (min..max) |")
    print("|---|---|")
    timed("the Lagrangian", jax.vmap(lagrangian), qs, qds)
    timed("right-hand side (dL/dq, Coriolis)", jax.vmap(restricted(equations.right_hand_side)), qs, qds)
    timed("pooled Jacobian (forward products)", jax.vmap(restricted(equations.pooled_jacobian)), qs, qds)
    timed("mass products (local Hessian-vector products and the pooled low-rank part)", jax.vmap(restricted(equations.mass_products)), qs, qds)
    timed("mass matrix", jax.vmap(restricted(equations.mass_matrix)), qs, qds)
    timed("regularised KKT solve", jax.vmap(solve), qs, qds, masses)
    timed("whole acceleration", jax.vmap(models.acceleration_fn(config, params, scene)), qs, qds)
    if equations.chain_solve:
        def dense_solve(q, qd):
            x, v = constraints.restrict(q), constraints.restrict(qd)
            m = equations.mass_matrix(x, v)
            return solvers.solve_kkt(m, constraints.jacobian(x), equations.right_hand_side(x, v), -constraints.jacobian_dot_v(x, v))

        timed("whole acceleration, the mass matrix assembled and the dense KKT solve instead", jax.vmap(dense_solve), qs, qds)


def solves() -> None:
    print("| system (batch, free coordinates, rods) | factorisation | ms per batched call (min..max) |")
    print("|---|---|---|")
    for free, rods in ((200, 100), (300, 100)):
        label = f"{args.batch}, {free}, {rods}"
        x = jax.random.normal(jax.random.PRNGKey(0), (args.batch, free, free))
        mass = x @ x.transpose(0, 2, 1) / free + jnp.eye(free)
        rows = jax.random.normal(jax.random.PRNGKey(1), (args.batch, rods, free))
        rhs = jax.random.normal(jax.random.PRNGKey(2), (args.batch, free))
        kkt = jax.vmap(lambda m, a: jnp.block([[m, a.T], [a, -solvers.KKT_REGULARISATION * jnp.eye(rods)]]))(mass, rows)
        timed(f"{label} | LU of the KKT matrix", jax.vmap(jax.scipy.linalg.lu_factor), kkt)
        timed(f"{label} | the refined KKT solve (`solvers.solve_kkt`)",
              jax.vmap(lambda m, a, f: solvers.solve_kkt(m, a, f, jnp.zeros(rods))), mass, rows, rhs)
        timed(f"{label} | LU of M alone", jax.vmap(jax.scipy.linalg.lu_factor), mass)
        timed(f"{label} | Cholesky factorisation of M (M positive definite)", jnp.linalg.cholesky, mass)
        factor = jax.jit(jnp.linalg.cholesky)(mass)
        timed(f"{label} | one solve with M's Cholesky factor", jax.vmap(lambda c, b: jax.scipy.linalg.cho_solve((c, True), b)), factor, rhs)


def trained_rollouts():
    """`(scene, loaded, runs)`: the committed checkpoints' 3 seeds of LGN rolled out on
    `--scene` from the evaluation's initial conditions, as the evaluate stage does."""
    import dataclasses

    from lgnn.bench import profiles
    from lgnn.bench.stages.evaluate import evaluation_initial_states
    from lgnn.learn import checkpoints

    profile = profiles.load_profile("full")
    scene = get_scene(args.scene)
    trained_on = training_scene(scene).name
    loaded = [checkpoints.load_model(f"results/benchmark/checkpoints/lgn-{trained_on}-s{seed}.npz") for seed in range(3)]
    model = loaded[0][0]
    states = evaluation_initial_states(profile, scene)
    states = type(states)(*(a[:args.states] for a in states))
    simulation = profile.evaluate.simulation(args.scene)
    if args.duration is not None:
        simulation = dataclasses.replace(simulation, duration=args.duration)
    stacked = jax.tree.map(lambda *leaves: np.stack(leaves), *(params for _, params in loaded))
    engine = models.ModelEngine(model, stacked, integration=profile.evaluate.integration, stop_at_divergence=False, stacked=True)
    runs = engine.rollouts(scene, simulation, states)
    print(f"LGN ({trained_on}) on {args.scene}: {len(states.q)} initial conditions, {runs.q.shape[2]} frames; "
          f"rollouts {runs.run_s:.1f} s + compile {runs.compile_s:.1f} s for 3 seeds", flush=True)
    return scene, loaded, runs


def checked_frames(loaded, runs, check_for):
    """For each seed, every `--every` frames: `(seed, frame, results)`, the results of
    `check_for(model, params)(q, qd)` at each of the rollouts' states (vmapped)."""
    for seed, (model, params) in enumerate(loaded):
        checked = jax.jit(jax.vmap(check_for(model, params)))
        for frame in range(0, runs.q.shape[2], args.every):
            yield seed, frame, [np.asarray(a) for a in checked(jnp.asarray(runs.q[seed, :, frame]), jnp.asarray(runs.qd[seed, :, frame]))]


def free_mass_fn(scene, lagrangian):
    """`(q, qd) -> M` over the free coordinates, and `M -> whether it is positive
    definite` (its Cholesky factorisation finite): what both checks below test."""
    free = np.asarray(physics.prepare(scene).constraints.free)
    mass = physics.mass_matrix_fn(lagrangian)
    return lambda q, qd: mass(q, qd)[np.ix_(free, free)], lambda m: jnp.all(jnp.isfinite(jnp.linalg.cholesky(m)))


def definiteness() -> None:
    scene, loaded, runs = trained_rollouts()
    print("| seed | frame | finite states | of them, M not positive definite | smallest eigenvalue / largest |")
    print("|---|---|---|---|---|")

    def check_for(model, params):
        mass, positive_definite = free_mass_fn(scene, models.lagrangian_fn(model, params, scene))

        def check(q, qd):
            m = mass(q, qd)
            eigenvalues = jnp.linalg.eigvalsh(m)
            return jnp.all(jnp.isfinite(m)), positive_definite(m), eigenvalues[0] / eigenvalues[-1]

        return check

    for seed, frame, (finite, cholesky, ratio) in checked_frames(loaded, runs, check_for):
        smallest = f"{np.min(ratio[finite]):.3g}" if finite.any() else "-"
        print(f"| {seed} | {frame} | {int(finite.sum())} | {int((finite & ~cholesky).sum())} | {smallest} |", flush=True)


def agreement() -> None:
    scene, loaded, runs = trained_rollouts()
    print("| seed | frame | finite states | of them, M not positive definite | largest relative difference | median |")
    print("|---|---|---|---|---|---|")

    def check_for(model, params):
        lagrangian = models.lagrangian_fn(model, params, scene)
        structured, dense = models.acceleration_fn(model, params, scene), physics.acceleration_fn(scene, lagrangian)
        mass, positive_definite = free_mass_fn(scene, lagrangian)

        def compare(q, qd):
            a, b = structured(q, qd), dense(q, qd)
            return jnp.max(jnp.abs(a - b)) / jnp.max(jnp.abs(b)), jnp.all(jnp.isfinite(b)), positive_definite(mass(q, qd))

        return compare

    for seed, frame, (difference, finite, cholesky) in checked_frames(loaded, runs, check_for):
        largest, median = (f"{f(difference[finite]):.2g}" if finite.any() else "-" for f in (np.max, np.median))
        print(f"| {seed} | {frame} | {int(finite.sum())} | {int((finite & ~cholesky).sum())} | {largest} | {median} |", flush=True)


{"parts": parts, "solves": solves, "definiteness": definiteness, "agreement": agreement}[args.what]()
