"""The one rollout path (`lgnn.engines.rollouts`) and the engine contract (`lgnn.engines.base`).

A batch of initial conditions is one compiled, vmapped program whose parameters are an
argument: the Lagrangian engine's batch equals `simulate` of each member with no loop
over members, a second parameter set of one model config compiles nothing (in
`ModelEngine` and in `lgnn evaluate`), a reference stops at the first diverging member,
the exact dynamics' small batches run on the host's CPU of a GPU machine and a learned
model's on the default device, the evaluation's chaos floor runs its ground truth's
program, and `get_engine` refuses what an engine cannot do in one line.
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from lgnn import physics, sharding
from lgnn.engines import ENGINES, EngineEntry, get_engine, lagrangian, register_engine, rollouts
from lgnn.engines.base import Engine, Integration, SimulationConfig, Trajectory
from lgnn.errors import ConfigError, SimulationError
from lgnn.learn import models
from lgnn.physics import solvers
from lgnn.scene import State, get_scene, sample_initial_states

SHORT = SimulationConfig(dt=1e-3, frame_dt=5e-3, duration=0.05)


def _states(scene, count, seed=3):
    states = sample_initial_states(scene, jax.random.PRNGKey(seed), count)
    return State(np.asarray(states.q), np.asarray(states.qd))


def test_the_lagrangian_batch_is_one_program_equal_to_simulate_of_each_member(monkeypatch):
    scene = get_scene("chain4")
    states = _states(scene, 3)
    alone = [lagrangian.simulate(scene, SHORT, State(q, qd)) for q, qd in zip(states.q, states.qd)]

    def no_loop(*args, **kwargs):
        raise AssertionError("the engine rolled out a member alone")

    monkeypatch.setattr(lagrangian, "simulate", no_loop)
    batch = get_engine("lagrangian").rollout(scene, SHORT, states)
    assert batch.q.shape == (3, SHORT.n_frames + 1, scene.n_nodes, scene.dim) and batch.energy.shape == (3, SHORT.n_frames + 1)
    for member, run in enumerate(alone):
        np.testing.assert_allclose(batch.q[member], run.q, rtol=0, atol=1e-12)
        np.testing.assert_allclose(batch.energy[member], run.energy, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(batch.t, alone[0].t)  # both `np.arange(frames) * frame_dt`


def test_frames_in_calls_give_the_same_trajectory_as_one_call():
    scene = get_scene("chain4")
    states = _states(scene, 2)
    factory = rollouts.Unparametrised(physics.true_acceleration_fn)
    whole = rollouts.batched_rollouts(scene, SHORT, factory, states, integration=Integration(), frames_per_call=SHORT.n_frames, with_energy=True)
    # 10 frames in calls of 3: four calls, the last running past the end (its extra frames dropped).
    called = rollouts.batched_rollouts(scene, SHORT, factory, states, integration=Integration(), frames_per_call=3, with_energy=True)
    # Calls of 3 frames and of 10 are two compiled programs: round-off apart at most (a
    # stale or repeated frame would be off by millimetres).
    np.testing.assert_allclose(called.q, whole.q, rtol=0, atol=1e-12)
    np.testing.assert_allclose(called.energy, whole.energy, rtol=1e-12, atol=1e-12)


def test_a_second_parameter_set_of_one_model_compiles_nothing():
    scene = get_scene("chain4")
    config = models.ModelConfig("lgnn", latent=4, hidden=8)
    first, second = (models.init(jax.random.PRNGKey(seed), config) for seed in (0, 1))
    states = _states(scene, 2)
    a = models.ModelEngine(config, first).rollout(scene, SHORT, states)
    compiled = rollouts.compiled_programs.cache_info().misses
    b = models.ModelEngine(config, second).rollout(scene, SHORT, states)
    assert rollouts.compiled_programs.cache_info().misses == compiled, "the second parameter set compiled a program"
    assert np.abs(a.q - b.q).max() > 1e-6, "each parameter set gives its own trajectories"
    alone = models.rollout(config, second, scene, SHORT, State(states.q[1], states.qd[1]))
    np.testing.assert_allclose(b.q[1], alone.q, rtol=0, atol=1e-12)


def test_lgnn_evaluate_of_a_second_checkpoint_of_one_config_compiles_nothing():
    from lgnn.bench import evaluation

    scene = get_scene("chain4")
    config = models.ModelConfig.for_scene("lgnn", scene, latent=4, hidden=8)
    states = _states(scene, 2)
    evaluation.evaluate_model(config, models.init(jax.random.PRNGKey(0), config), scene, SHORT, states)
    compiled = rollouts.compiled_programs.cache_info().misses
    scored, _ = evaluation.evaluate_model(config, models.init(jax.random.PRNGKey(1), config), scene, SHORT, states)
    assert rollouts.compiled_programs.cache_info().misses == compiled
    assert {item.reference for item in scored} == {"lagrangian", "mujoco"}


def _growing_factory(scene):
    # Accelerations that blow up nodes placed beyond x = 5 and leave the others at rest.
    return lambda q, qd: jnp.where(q[:, :1] > 5.0, 1e4 * q, 0.0 * q)


def test_a_reference_stops_at_its_first_diverging_member_with_the_frames_before_it():
    scene = get_scene("chain4")
    config, unprojected = SimulationConfig(dt=1e-3, frame_dt=1e-3, duration=0.3), Integration(project=False)
    resting = np.asarray(scene.nodes, np.float64)
    states = State(np.stack([resting, resting + 10.0]), np.zeros((2, scene.n_nodes, scene.dim)))
    factory = rollouts.Unparametrised(_growing_factory)
    with pytest.raises(SimulationError) as info:
        rollouts.batched_rollouts(scene, config, factory, states, integration=unprojected, stop_at_divergence=True, frames_per_call=100, hint="a hint")
    message = str(info.value)
    assert "\n" not in message and "initial condition 1" in message and message.endswith("a hint")
    partial = info.value.trajectory
    assert 1 <= len(partial.t) < 100, "stopped within the first call of frames"
    np.testing.assert_array_equal(partial.q[0], states.q[1])
    # A model's rollouts (not a reference) run on: the diverged member keeps its frames.
    runs = rollouts.batched_rollouts(scene, config, factory, states, integration=unprojected)
    assert runs.q.shape[1] == config.n_frames + 1 and runs.energy is None, "energies only where asked for"
    np.testing.assert_array_equal(runs.q[0, -1], resting)  # exact: zero accelerations from rest add only zeros


def test_small_ground_truth_batches_run_on_the_host_of_an_accelerator_and_models_where_jax_computes(monkeypatch):
    scene = get_scene("chain4")
    asked = []

    def recording(*args, **kwargs):
        asked.append(kwargs.get("platform"))
        return rollouts.batched_rollouts(*args, **kwargs)

    monkeypatch.setattr(lagrangian, "batched_rollouts", recording)
    monkeypatch.setattr(models.generic, "batched_rollouts", recording)
    model = models.ModelConfig("lgnn", latent=4, hidden=8)
    params = models.init(jax.random.PRNGKey(0), model)
    small, large = _states(scene, 2), _states(scene, rollouts.HOST_BATCH_MAX + 1)
    # On a CPU machine every batch runs where JAX computes (None: no context entered).
    assert rollouts.ground_truth_platform(1) is None

    def as_on_a_gpu_machine(count):  # JAX's default backend an accelerator
        with monkeypatch.context() as patched:
            patched.setattr(rollouts.jax, "default_backend", lambda: "gpu")
            return rollouts.ground_truth_platform(count)

    assert [as_on_a_gpu_machine(n) for n in (1, rollouts.HOST_BATCH_MAX, rollouts.HOST_BATCH_MAX + 1)] == ["cpu", "cpu", None]
    monkeypatch.setattr(lagrangian, "ground_truth_platform", as_on_a_gpu_machine)
    lagrangian.simulate(scene, SHORT)
    get_engine("lagrangian").rollout(scene, SHORT, small)
    get_engine("lagrangian").rollout(scene, SHORT, large)
    lagrangian.simulate(scene, SHORT, accel_factory=models.AccelerationFactory(model), params=params)
    models.ModelEngine(model, params).rollout(scene, SHORT, small)
    assert asked == ["cpu", "cpu", None, None, None]
    # Inside the host's context the sweeps along a chain take their CPU form.
    with sharding.on_platform("cpu"):
        assert sharding.platform() == "cpu" and solvers.sweep_unroll() == 1


def test_a_batch_of_one_keeps_its_branches_on_a_cpu_and_is_vmapped_on_an_accelerator(monkeypatch):
    """On a CPU a batch of one is `fn` itself, where a `lax.cond` stays a branch (the
    guarded solve's saving); on an accelerator it is vmapped like any batch."""

    def branchy(x):
        return jax.lax.cond(x.sum() > 0, lambda y: y, lambda y: -y, x)

    def primitives(platform):
        with monkeypatch.context() as patched:
            patched.setattr(rollouts.sharding, "platform", lambda: platform)
            return {eqn.primitive.name for eqn in jax.make_jaxpr(rollouts._over_batch(branchy, (0,), 1))(jnp.ones((1, 3))).eqns}

    assert "cond" in primitives("cpu")
    assert "cond" not in primitives("gpu") and primitives("gpu") == {e.primitive.name for e in jax.make_jaxpr(jax.vmap(branchy))(jnp.ones((1, 3))).eqns}


def test_a_rollout_says_where_it_ran():
    scene = get_scene("chain4")
    runs = rollouts.batched_rollouts(scene, SHORT, rollouts.Unparametrised(physics.vectorised_true_acceleration_fn), _states(scene, 2),
                                     integration=Integration(), platform="cpu")
    assert runs.platform == "cpu"


def test_get_engine_refuses_what_an_engine_lacks_in_one_line():
    for call, words in [(lambda: get_engine("mujoco", dtype="float32"), ("mujoco", "float64", "float32")),
                        (lambda: get_engine("mjwarp", dtype="float64"), ("mjwarp", "float32")),
                        (lambda: get_engine("lagrangian", form="nested"), ("lagrangian", "form")),
                        (lambda: get_engine("mjx", form="flat"), ("flat", "auto", "nested", "maximal"))]:
        with pytest.raises(ConfigError) as info:
            call()
        assert "\n" not in str(info.value) and all(word in str(info.value) for word in words), str(info.value)
    assert get_engine("mujoco").dtype == "float64" and get_engine("lagrangian", dtype="float32").dtype == "float32"


def test_the_rollout_settings_are_neutral():
    # How an engine integrates is its own (`Integration`), not the settings every engine takes.
    assert [field.name for field in dataclasses.fields(SimulationConfig)] == ["dt", "frame_dt", "duration"]
    with pytest.raises(TypeError):
        SimulationConfig(integrator="verlet")


def test_an_integration_is_the_lagrangian_engines_and_no_mujoco_engines():
    scene = get_scene("chain4")
    states = _states(scene, 2)
    verlet = Integration("verlet", project=False)
    batch = get_engine("lagrangian", integration=verlet).rollout(scene, SHORT, states)
    alone = lagrangian.simulate(scene, SHORT, State(states.q[1], states.qd[1]), integration=verlet)
    np.testing.assert_allclose(batch.q[1], alone.q, rtol=0, atol=1e-12)
    assert batch.metadata["integration"] == {"integrator": "verlet", "project": False}
    # The integration is part of the compiled program: RK4 with projection is another run.
    rk4 = get_engine("lagrangian").rollout(scene, SHORT, states)
    assert np.max(np.abs(rk4.q[1] - batch.q[1])) > 1e-9
    for name, entry in ENGINES.items():
        if not entry.integrates:
            with pytest.raises(ConfigError) as info:
                get_engine(name, integration=verlet)
            assert "\n" not in str(info.value) and name in str(info.value) and "lagrangian" in str(info.value)
    with pytest.raises(ConfigError, match="unknown integrator 'euler'"):
        Integration("euler")


def test_every_engine_answers_the_contract_and_auto_works_for_every_mujoco_engine():
    scene = get_scene("chain4")
    for name, entry in ENGINES.items():
        engine = get_engine(name)
        assert isinstance(engine, Engine) and engine.name == name and engine.dtype == entry.dtypes[0]
        assert engine.accuracy(scene, SHORT) is None or engine.accuracy(scene, SHORT) > 0
        if entry.forms:
            assert get_engine(name, form="auto").form_of(scene) in ("nested", "maximal")
        else:
            assert engine.form_of(scene) == ""


@dataclasses.dataclass(frozen=True)
class _Resting(Engine):
    """An engine whose bodies never move (for the registry test)."""

    name = "resting"
    dtype: str = "float64"

    def rollout(self, scene, config, states):
        q = np.repeat(np.asarray(states.q)[:, None], config.n_frames + 1, axis=1)
        return Trajectory(np.arange(config.n_frames + 1) * config.frame_dt, q, np.zeros_like(q), np.zeros(q.shape[:2]))


def test_a_registered_engine_is_got_like_the_built_ins():
    entry = register_engine(EngineEntry("resting", lambda dtype, progress, form, integration: _Resting(dtype), ("float64",)))
    try:
        engine = get_engine("resting")
        assert isinstance(engine, _Resting) and engine.form_of(get_scene("chain4")) == ""
        with pytest.raises(ConfigError, match="already registered"):
            register_engine(dataclasses.replace(entry, dtypes=("float32",)))
        with pytest.raises(ConfigError, match="float32"):
            get_engine("resting", dtype="float32")
    finally:
        ENGINES.pop("resting", None)


def test_the_chaos_floor_runs_the_ground_truths_compiled_program(monkeypatch):
    # The evaluation's ground truth and its chaos floor roll out one batch each with the
    # same dynamics and settings: the floor compiles nothing (a program of its own took
    # 23-35 s to compile for chain100 on a GPU machine's busy host).
    from lgnn.bench import profiles
    from lgnn.bench.stages import truth as truth_stage

    profile = profiles.load_profile("quick", ["evaluate.duration=0.01", "evaluate.frame_dt=0.005", "evaluate.dt=0.005"])
    compiled = []

    def counting(*args, **kwargs):
        runs = rollouts.batched_rollouts(*args, **kwargs)
        compiled.append(rollouts.compiled_programs.cache_info().misses)
        return runs

    monkeypatch.setattr(truth_stage, "batched_rollouts", counting)
    truth = truth_stage._computed_ground_truth(profile, "chain4", progress=False)
    assert len(compiled) == 2, "the ground truth, then its chaos floor"
    assert compiled[1] == compiled[0], "the chaos floor compiled a program of its own"
    gap = np.abs(truth.floor.q - truth.truth.q).max()
    assert 0 < gap < 1e-2, "the floor starts from perturbed states and stays near the truth this briefly"
