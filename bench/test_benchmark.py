"""The benchmark as a test session: train every model of the grid, evaluate it on every
scene, measure speed against error and write the report (`lgnn.bench.stages`,
`lgnn.bench.run`, `lgnn.bench.report`).

    pytest bench/test_benchmark.py               # quick profile -> a temporary folder of the run's
    pytest bench/test_benchmark.py --benchmark   # full profile  -> results/
    pytest bench/test_benchmark.py --bench-out lgnn-out/quick   # resume from and check lgnn benchmark's records

Tests run in file order (train, ground truth, evaluation, speed, scaling, mass matrix, report)
and every stage resumes from the records already on disk, so a killed run restarted
loses no finished work. pytest-benchmark times one training epoch per job and, on
chain4, one evaluation rollout chunk per model, with the functions the stages
compiled (compile time is kept apart, in the records).
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from lgnn import metrics
from lgnn.bench import grid, profiles, store
from lgnn.bench.report import readme as report_readme, summary as report_summary
from lgnn.bench.run import run
from lgnn.bench.stages import evaluate, mass, scaling, speed
from lgnn.bench.stages import truth as truth_stage
from lgnn.bench.stages import train as train_stage
from lgnn.learn import data, models, protocol, train
from lgnn.learn.checkpoints import load_model, refuse_without_parameters
from lgnn.engines import rollouts
from lgnn.scene import State, get_scene

QUICK, FULL = profiles.PROFILES["quick"], profiles.PROFILES["full"]
TIMED_SCENES = ("chain4",)
# Lagrangian RK4 (dt 1e-3) against MuJoCo C (RK4 dt 1e-4) over the evaluation: both
# converge to the same solution on regular scenes; T2 and T3 start self-stressed, where
# the inextensible model is singular (lgnn.physics) and only agree to ~1e-2.
TRUTH_AGREEMENT = {"T2": 1e-1, "T3": 1e-1}
TRUTH_AGREEMENT_DEFAULT = 1e-6
# Scenes whose perturbed (chaos floor) run diverges at the profile's step: T2 and T3's
# perturbed self-stressed states need dt <= 2.5e-5 (EvaluateSettings.scene_dts). The record
# must then say when, rather than hold a floor.
FLOOR_DIVERGES = {"T2", "T3"}
# Training learns: the best validation MSE is at most this fraction of the untrained
# model's on the same validation states (the quick profile takes 30 Adam steps).
LEARNS = 0.75
# Models whose quick-profile training does not learn yet. Strict: the test fails once
# one learns, so its entry is removed then. (LGNN learns since the quick profile's 30
# steps peak at protocol.SHORT_BUDGET_RATE: 0.70 of the untrained model's MSE; LGNN with
# the paper's two message-passing layers reaches 0.76 in those 30 steps.)
DOES_NOT_LEARN_YET: set[str] = {"lgnn-mp2"}


@pytest.fixture(scope="session")
def profile(full_profile) -> profiles.Profile:
    return FULL if full_profile else QUICK


def _ids(items):
    return [getattr(i, "name", None) or f"{i.job.name}-on-{i.scene}" + ("" if i.projected else "-unprojected") for i in items]


def pytest_generate_tests(metafunc):
    profile = FULL if metafunc.config.getoption("--benchmark") else QUICK
    if "job" in metafunc.fixturenames:
        jobs = profiles.training_jobs(profile)
        metafunc.parametrize("job", jobs, ids=_ids(jobs))
    if "pair" in metafunc.fixturenames:
        pairs = profiles.evaluation_pairs(profile)
        metafunc.parametrize("pair", pairs, ids=_ids(pairs))
    if "timed_pair" in metafunc.fixturenames:
        pairs = [p for p in profiles.evaluation_pairs(profile) if p.scene in TIMED_SCENES and p.projected]
        metafunc.parametrize("timed_pair", pairs, ids=_ids(pairs))
    if "eval_scene" in metafunc.fixturenames:
        metafunc.parametrize("eval_scene", profiles.evaluation_scenes(profile))
    if "speed_scene" in metafunc.fixturenames:
        metafunc.parametrize("speed_scene", profile.speed.scenes)
    if "mass_scene" in metafunc.fixturenames:
        metafunc.parametrize("mass_scene", profile.mass.scenes)


def _time(benchmark, run, rounds: int) -> None:
    """Time `run` (compiled by a first call, not timed) where pytest-benchmark times.
    Where it does not (under xdist, as in CI, or `--benchmark-disable`) the program is
    not even compiled: the training or evaluation program the stage ran is another
    one, and compiling each only to run it once untimed cost CI minutes of its 2 cores
    (`test_the_timed_programs_run_from_the_stages_records` runs LGNN's once)."""
    if benchmark.disabled:
        return
    run()
    benchmark.pedantic(run, rounds=rounds, iterations=1)


def _timed_epoch_fn(profile, job, out):
    """`(run, steps)`: a no-argument call running one training epoch of the job (the
    compiled function training used, from the checkpoint's parameters: its best ones
    and a fresh optimiser state for a checkpoint kept for inference), and the Adam
    steps it takes; for pytest-benchmark."""
    scene, model, data_config, train_config = train_stage.job_settings(profile, job)
    layout = store.layout(profile, out)
    path = layout.found(layout.checkpoint(job))
    state, meta = train.load_checkpoint(path)
    refuse_without_parameters(path, meta, "timed")
    dataset = data.load_or_generate(data_config, store.Layout(out).datasets)
    arrays = tuple(jnp.asarray(a[dataset.train]) for a in (dataset.q, dataset.qd, dataset.qdd))
    epoch = train.compiled_epoch_fn(model, scene, train_config)
    key = jax.random.PRNGKey(0)
    steps = len(dataset.train) // train_config.batch_size
    params = state.best_params if state.params is None else state.params
    opt_state = train.fresh_optimiser_state(model, train_config, params) if state.opt_state is None else state.opt_state
    return (lambda: jax.block_until_ready(epoch(params, opt_state, *arrays, key))), steps


def test_training(benchmark, record_rate, request, profile, out, job):
    # The job's seeds train together (one compiled program); later seeds reuse the checkpoints.
    group = [j for j in profiles.training_jobs(profile) if (j.model, j.scene) == (job.model, job.scene)]
    path = train_stage.train_jobs(profile, group, out)[group.index(job)]
    state, meta = train.load_checkpoint(path)
    assert np.isfinite(state.best_val) and state.epoch >= 1
    run_epoch, steps = _timed_epoch_fn(profile, job, out)
    assert steps == protocol.adam_steps_per_epoch(profile.training.data, profile.training.train)  # the schedule rule's count
    _time(benchmark, run_epoch, rounds=3)
    record_rate("adam_steps", steps, job=job.name, epochs=state.epoch, best_val=state.best_val)
    # Training learns: far below the untrained model (same initial parameters) on the
    # same validation states. (Below its own first epoch would hold by construction.)
    scene, (model, best) = get_scene(job.scene), load_model(path)
    assert model == train_stage.job_settings(profile, job)[1]
    dataset = data.load_or_generate(profile.training.data_for(job.scene), store.Layout(out).datasets)
    val = tuple(a[dataset.val] for a in (dataset.q, dataset.qd, dataset.qdd))
    untrained = train.initial_state(model, dataclasses.replace(profile.training.train, seed=job.seed)).params
    untrained_val = train.evaluate_fn(model, scene)(untrained, *val)
    # The checkpoint alone predicts as training validated it: its best parameters, with
    # the statistics a model normalises by, give the best validation MSE again.
    assert train.evaluate_fn(model, scene)(best, *val) == pytest.approx(state.best_val, rel=1e-12)
    # A model that normalises by training-set statistics (the strong GNS, the zoo's
    # graph networks) carries those of its job's training split (one scene's; varied
    # draws pool theirs), computed here from the data.
    # The checkpoint may come from another process (a resumed run: `lgnn benchmark`'s),
    # whose program summed the same states in another order: equal to a few ulps, not
    # bitwise (4e-16 apart on a mean of 1.1, seen), so to 1e-12 of the largest.
    if models.STATISTICS in best and not job.varied_draws:
        expected = models.training_statistics(model, scene, *(a[dataset.train] for a in (dataset.q, dataset.qd, dataset.qdd)))
        for name, value in expected.items():
            np.testing.assert_allclose(best[models.STATISTICS][name], value, rtol=1e-12, atol=1e-12 * np.max(np.abs(value)), err_msg=name)
    if job.model in DOES_NOT_LEARN_YET and profile is QUICK:
        request.applymarker(pytest.mark.xfail(reason="learns too slowly for the quick profile's 30 steps", strict=True))
    assert state.best_val < LEARNS * untrained_val, f"best validation MSE {state.best_val:.3g}, untrained {untrained_val:.3g}"


def test_ground_truth(profile, out, eval_scene):
    arrays, meta = store.load(evaluate.evaluate_scene(profile, eval_scene, out))
    floor = metrics.summarise(arrays["chaos_floor/per_ic_log"])[0]
    agreement = metrics.summarise(arrays["truth_vs_mujoco/per_ic_log"])[0]
    # (Records written before divergence was recorded lack the array; their floor is checked below.)
    floor_diverged = np.isfinite(arrays.get("chaos_floor/diverged_at", np.nan)).any()
    if eval_scene in FLOOR_DIVERGES:
        assert floor_diverged or 0 < floor < 1e-2, f"chaos floor {floor:.3g} without a recorded divergence"
    else:
        assert not floor_diverged and 0 < floor < 1e-2, f"chaos floor {floor:.3g}"
    assert agreement < TRUTH_AGREEMENT.get(eval_scene, TRUTH_AGREEMENT_DEFAULT), f"Lagrangian vs MuJoCo {agreement:.3g}"
    count = arrays["chaos_floor/per_ic_log"].shape[0]
    assert arrays["chaos_floor/node_rms_error/per_ic_log"].shape == (count,)
    for metric in (m.name for m in evaluate.recorded_metrics(profile.evaluate.references)):
        assert arrays[f"{evaluate.REST}/{metric}/per_ic_log"].shape == (count,), f"rest baseline's {metric}"
    if profile is QUICK:  # (the full profile's ground truth takes minutes to redo)
        # The rest baseline's errors are the truth's own displacement from its start,
        # computed here independently of lgnn.metrics, from a truth computed again. The
        # record's may come from the dataset cache, made by another program of the same
        # settings (another chunk size): positions equal to round-off, whose 1e-16
        # become 3e-11 of the first frames' displacements of 3e-6.
        q = truth_stage.ground_truth(profile, eval_scene, True).truth.q
        logs = np.log(np.sqrt(np.mean(np.sum((q[:, 1:] - q[:, :1]) ** 2, axis=-1), axis=-1)))  # (C, F - 1)
        np.testing.assert_allclose(arrays[f"{evaluate.REST}/node_rms_error/per_ic_log"], logs.mean(axis=1), rtol=1e-9)
        # Its curves: every CURVE_DT s, the last frame of each (frame k at k * frame_dt).
        frame_dt = profile.evaluate.frame_dt
        np.testing.assert_allclose(np.diff(arrays["t"]), evaluate.CURVE_DT, rtol=1e-9)
        assert arrays["t"][-1] == pytest.approx(profile.evaluate.duration)
        frames = np.rint(arrays["t"] / frame_dt).astype(int)
        np.testing.assert_allclose(arrays[f"{evaluate.REST}/node_rms_error/gmean"], np.exp(logs.mean(axis=0))[frames - 1], rtol=1e-9)


def test_evaluation(profile, out, pair):
    arrays, meta = store.load(evaluate.evaluate_pair(profile, pair, out))
    count = len(truth_stage.evaluation_initial_states(profile, get_scene(pair.scene)).q)
    for metric in (m.name for m in evaluate.recorded_metrics(profile.evaluate.references)):
        assert arrays[f"{metric}/per_ic_log"].shape == (count,), metric
        assert arrays[f"{metric}/gmean"].shape == arrays["t"].shape, metric
    assert arrays["diverged_at"].shape == (count,)
    if pair.scene not in TRUTH_AGREEMENT:
        # Where the two ground truths agree far better than any model, a model's error
        # against each differs by at most about twice their distance (triangle
        # inequality), frame by frame: the MuJoCo frames are aligned in time.
        truth = evaluate.load_truth(profile, pair.scene, out)[0]
        distance = np.fmax(truth["truth_vs_mujoco/high"], truth["truth_vs_mujoco/gmean"])  # (high is NaN for one IC)
        lagrangian, mujoco = arrays["rollout_error/gmean"], arrays["rollout_error_vs_mujoco/gmean"]
        assert np.all(np.abs(mujoco - lagrangian) <= 1e-3 * lagrangian + 10 * distance)


def test_rollout_speed(benchmark, record_rate, profile, out, timed_pair):
    run_chunk, steps = _timed_rollout_fn(profile, timed_pair, out)
    _time(benchmark, run_chunk, rounds=1 if profile is FULL else 3)
    record_rate("rk4_steps", steps, pair=f"{timed_pair.job.label} on {timed_pair.scene}")


def test_the_timed_programs_run_from_the_stages_records(profile, out):
    """What test_training and test_rollout_speed time, run once here where they do not
    time (`_time`): an epoch of LGNN's training from its checkpoint, and its first
    evaluation chunk on chain4."""
    job = profiles.lgnn_job(profile)
    run_epoch, _ = _timed_epoch_fn(profile, job, out)
    params, _, loss = run_epoch()
    assert np.isfinite(loss) and all(np.isfinite(leaf).all() for leaf in jax.tree.leaves(params))
    pair = next(p for p in profiles.evaluation_pairs(profile) if p.job == job and p.scene in TIMED_SCENES and p.projected)
    run_chunk, steps = _timed_rollout_fn(profile, pair, out)
    rollouts = run_chunk()
    assert np.isfinite(rollouts.q).all() and steps > 0


def test_speed_error(profile, out, speed_scene):
    import json

    rows = json.loads(speed.speed_error(profile, speed_scene, out).read_text())["rows"]
    engines = [r for r in rows if r["kind"] == "engine" and np.isfinite(r["rollout_error"])]
    assert engines, "at least one engine ran"
    # Converged ground truths agree with the reference far below any learned error.
    assert min(r["rollout_error"] for r in engines) < 1e-8
    # Each timing is the median of the profile's repeats, with their spread.
    timed = [r for r in rows if r["runs"]]
    assert timed and all(r["runs"] == profile.speed.repeats for r in timed)
    assert all(r["wall_s_min_per_sim_s"] <= r["wall_s_per_sim_s"] <= r["wall_s_max_per_sim_s"] for r in timed)


def test_scaling(profile, out):
    import json

    rows = json.loads(scaling.scaling(profile, out).read_text())["rows"]
    sizes = {(r["solver"], r["n_links"]) for r in rows if r["kind"] == "size"}
    assert {("lagrangian", n) for n in profile.scaling.lengths} <= sizes
    assert {("mujoco", n) for n in profile.scaling.lengths} <= sizes
    spatial = {(r["solver"], r["n_links"]) for r in rows if r["kind"] == "size" and r["dim"] == 3}
    assert {(solver, n) for solver in ("lagrangian", "mujoco") for n in profile.scaling.spatial_lengths} <= spatial
    batched = [r for r in rows if r["kind"] == "batch"]
    assert {r["scene"] for r in batched} == set(profile.scaling.throughput_scenes)
    assert all(np.isfinite(r["s_per_step"]) and r["s_per_step"] > 0 for r in rows)


def _rod_mass_matrix(scene, q: np.ndarray) -> np.ndarray:
    """The closed-form mass matrix (N*D, N*D) of a scene's rods at positions `q`: each
    rod adds `m/4 [[1, 1], [1, 1]] (x) 1 + I/l^2 [[1, -1], [-1, 1]] (x) (1 - e e^T)` on
    its ends, `e` its unit axis: only motion across the rod turns it (in 2D `1 - e e^T`
    is `t t^T`, `t` the unit normal; in 3D a thin rod has no spin about its axis).
    tests/test_physics.py and tests/test_spatial.py check the formula by hand."""
    n, dim = q.shape
    full = np.zeros((n * dim, n * dim))
    for (i, j), m, inertia in zip(np.asarray(scene.edge_index), scene.masses, scene.inertias):
        rod = q[i] - q[j]
        axis = rod / np.linalg.norm(rod)
        block = m / 4 * np.kron(np.ones((2, 2)), np.eye(dim)) + inertia / (rod @ rod) * np.kron([[1, -1], [-1, 1]], np.eye(dim) - np.outer(axis, axis))
        idx = np.concatenate([np.arange(i * dim, (i + 1) * dim), np.arange(j * dim, (j + 1) * dim)])
        full[np.ix_(idx, idx)] += block
    return full


def _free_coordinates(scene) -> tuple[np.ndarray, np.ndarray]:
    """`(free nodes, their coordinates' indices)`: the rows the mass stage keeps."""
    free = np.setdiff1d(np.arange(scene.n_nodes), scene.pinned)
    return free, (free[:, None] * scene.dim + np.arange(scene.dim)).reshape(-1)


def test_mass_matrix(profile, out, mass_scene):
    arrays, meta = store.load(mass.mass_matrices(profile, mass_scene, out))
    scene = get_scene(mass_scene)
    free, coords = _free_coordinates(scene)
    # The true matrix is the rods' closed form at the state the stage analysed.
    q = evaluate.load_truth(profile, mass_scene, out)[0]["mid_state"][0]
    np.testing.assert_allclose(arrays["true"], _rod_mass_matrix(scene, q)[np.ix_(coords, coords)], rtol=1e-12, atol=1e-14)
    # The learned matrix is banded: nodes farther apart in the graph than one link plus
    # two message-passing hops from each end share no energy term (LGNN's default,
    # no message passing: linked pairs only), so their block is zero to round-off.
    model, _ = load_model(store.Layout(out).checkpoint(profiles.lgnn_job(profile, mass_scene)))
    hops = np.full((scene.n_nodes, scene.n_nodes), scene.n_nodes)
    np.fill_diagonal(hops, 0)
    for i, j in np.asarray(scene.edge_index):
        hops[i, j] = hops[j, i] = 1
    for k in range(scene.n_nodes):  # Floyd-Warshall: graph distances
        hops = np.minimum(hops, hops[:, k:k + 1] + hops[k:k + 1, :])
    far = np.kron(hops[np.ix_(free, free)] > 2 * model.message_passing + 1, np.ones((scene.dim, scene.dim), bool))
    learned = arrays["learned"]
    assert far.any() and np.isfinite(learned).all()
    assert np.max(np.abs(learned[far])) <= 1e-12 * np.max(np.abs(learned)), "coupling between unlinked nodes"
    assert np.max(np.abs(learned[~far])) > 0


def test_a_3d_chains_mass_matrix_is_the_3d_lgnns_against_the_rods_in_3d(tmp_path):
    """The mass stage on a 3D chain analyses the LGNN trained on chain4-3d (on a planar
    scene, the one trained on chain4) against the rods' mass matrix in 3D (no spin about
    a rod's axis), at the state the scene's ground-truth record holds. Untrained
    weights and a record holding only that state: no training, no rollout."""
    from lgnn import physics
    from lgnn.learn import models

    profile = dataclasses.replace(QUICK, mass=dataclasses.replace(QUICK.mass, scenes=("chain4-3d",)))
    job = profiles.lgnn_job(profile, "chain4-3d")
    assert job == grid.TrainingJob("lgnn", grid.SPATIAL_TRAINING_SCENE, 0)
    assert profiles.lgnn_job(profile, "chain8") == profiles.lgnn_job(profile) == grid.TrainingJob("lgnn", grid.TRAINING_SCENE, 0)
    layout, scene = store.Layout(tmp_path), get_scene("chain4-3d")
    model, config = models.ModelConfig.for_scene("lgnn", get_scene(job.scene)), profile.training.train
    layout.checkpoint(job).parent.mkdir(parents=True)
    train.save_checkpoint(layout.checkpoint(job), train.initial_state(model, config), model, config)
    q, qd = (np.asarray(a[0]) for a in physics.benchmark_initial_states(scene, 1, profile.evaluate.ic_seed))
    assert np.ptp(q[:, 2]) > 0.1, "a state out of the x-y plane"
    store.save(layout.truth_record("chain4-3d"), truth_stage.truth_key(profile, "chain4-3d"), {"mid_state": np.stack([q, qd])}, {})
    arrays, meta = store.load(mass.mass_matrices(profile, "chain4-3d", tmp_path))
    assert meta["job"] == "lgnn-chain4-3d-s0"
    assert [m["scene"] for _, m in mass.load_mass(profile, tmp_path)] == ["chain4-3d"]
    _, coords = _free_coordinates(scene)
    np.testing.assert_allclose(arrays["true"], _rod_mass_matrix(scene, q)[np.ix_(coords, coords)], rtol=1e-12, atol=1e-14)
    assert arrays["learned"].shape == arrays["true"].shape == (12, 12) and np.isfinite(arrays["learned"]).all()


def test_report(profile, out):
    run(profile, out, stages=("report",))
    text = (out / "README.md").read_text()
    for pair in profiles.evaluation_pairs(profile):
        assert f"| {pair.scene} |" in text
    # A quick report says its ranking and timings are no results; the full one does not.
    assert (report_readme.QUICK_WARNING in text) == (profile.name != "full")
    for name in (report_summary.SUMMARY, report_summary.CURVES, "speed_error.csv", "mass_matrix.csv"):
        assert (out / "benchmark" / name).stat().st_size > 0
    performance = (out / "performance.md").read_text()
    assert "Lagrangian / MuJoCo" in performance and "Cost per step against chain length" in performance
    figures = sorted((out / "figures").glob("*.png"))
    assert figures
    for figure in figures:
        assert figure.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def _timed_rollout_fn(profile: profiles.Profile, pair: grid.Pair, out):
    """`(run, steps)`: a no-argument call running the pair's model alone on the first
    chunk of the evaluation's initial conditions (through the one rollout path, its
    programs compiled by the first call), and the RK4 steps it takes; for
    pytest-benchmark."""
    scene = get_scene(pair.scene)
    states = truth_stage.evaluation_initial_states(profile, scene)
    chunk = min(profile.evaluate.chunk, len(states.q))
    first = State(states.q[:chunk], states.qd[:chunk])
    layout = store.layout(profile, out)
    model, params = load_model(layout.found(layout.checkpoint(pair.job)))
    config = profile.evaluate.simulation(pair.scene)
    steps = chunk * config.n_frames * config.steps_per_frame
    integration = profile.evaluate.integration
    return (lambda: rollouts.batched_rollouts(scene, config, models.AccelerationFactory(model), first, params, integration=integration, chunk=chunk)), steps
