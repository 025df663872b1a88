"""The evaluation's ground truth of a scene, computed once and shared: what the truth and
evaluate stages score against.

`ground_truth(profile, scene_name, out=...)` is a `GroundTruth`: the evaluation's
initial states (`evaluation_initial_states`: the scene's own state, or the profile's
`initial_conditions` samples), the Lagrangian ground truth from them (RK4 with
projection at the scene's step, `batched_rollouts` of `TRUE_DYNAMICS`, stopped at a
divergence: a reference that diverged would make every error 1), the chaos floor's
states (initial positions perturbed by `floor_perturbation` and projected back) and
each reference engine's trajectories (`EvaluateSettings.references`, MuJoCo C by
default, through `get_engine(name).rollout` at `mujoco_dt`, in a thread beside the JAX
rollouts), with what each cost. It is kept in the dataset cache (`truth_file`, keyed
on `truth_key`: the scene's content and the evaluation settings as it uses them) and
read back by every later process. `truth_trajectories` names the arrays kept;
`REFERENCE_VERSION` the references' version in every record's meta.
"""

from __future__ import annotations

import dataclasses
import functools
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from lgnn import physics, records
from lgnn.bench import claims, store
from lgnn.bench.profiles import Profile
from lgnn.bench.store import log
from lgnn.engines import get_engine
from lgnn.engines.base import SimulationConfig, Trajectory
from lgnn.engines.rollouts import Unparametrised, batched_rollouts, ground_truth_platform
from lgnn.records import settings_key
from lgnn.runtime import in_background
from lgnn.scene import OWN_STATE, Scene, State, get_scene, initial_state_policy, scene_to_dict

# Version of the reference trajectories, in every record's meta: 2 since MuJoCo C's
# stale last frames were fixed (c0eb960; `tools/upgrade_records.py` reads it).
REFERENCE_VERSION = 2


# The exact dynamics as the one rollout path takes an acceleration (no parameters).
TRUE_DYNAMICS = Unparametrised(physics.vectorised_true_acceleration_fn)


def evaluation_initial_states(profile: Profile, scene: Scene) -> State:
    """The evaluation initial conditions (C, N, D), seed `ic_seed`, by the scene's
    initial-state policy (`lgnn.scene.initial_state_policy`, `physics.benchmark_initial_states`):
    its own state (C = 1: T1-T3), or `initial_conditions` samples of the chain sampler
    or of projected perturbations."""
    return physics.benchmark_initial_states(scene, evaluation_count(profile, scene), profile.evaluate.ic_seed)


def evaluation_count(profile: Profile, scene: Scene) -> int:
    """How many initial conditions a scene is evaluated from: 1 for a scene started from
    its own state (T1-T3), else the profile's `initial_conditions`."""
    return 1 if initial_state_policy(scene) == OWN_STATE else profile.evaluate.initial_conditions


def truth_key(profile: Profile, scene_name: str) -> str:
    """Settings a scene's ground-truth record depends on."""
    return records.digest({"evaluate": settings_key(profile.evaluate.for_scene(scene_name)), "scene": scene_to_dict(get_scene(scene_name))})


def truth_file(profile: Profile, scene_name: str) -> Path:
    """Where `ground_truth` keeps a scene's trajectories: the dataset cache, named by
    the scene and its `truth_key`."""
    return store.truth_trajectories(scene_name, truth_key(profile, scene_name))


# A trajectory's arrays as `ground_truth` keeps them on disk: `q`, `qd`, `energy` of the
# Lagrangian ground truth, `<array>_<engine>` of each reference engine's.
TRAJECTORY_ARRAYS = ("q", "qd", "energy")


def _kept_name(array: str, engine: str | None = None) -> str:
    return array if engine is None else f"{array}_{engine}"


def truth_trajectories(references: tuple[str, ...]) -> tuple[str, ...]:
    """The arrays `ground_truth` keeps on disk (with `states`, its initial conditions):
    the Lagrangian ground truth's positions, velocities and true energies, the chaos
    floor's positions and velocities, and each reference engine's `q_<engine>`,
    `qd_<engine>` and `energy_<engine>` (a file without a reference's velocities, kept
    before metrics could read them, is computed again)."""
    return (*TRAJECTORY_ARRAYS, "q_floor", "qd_floor", *(_kept_name(array, engine) for engine in references for array in TRAJECTORY_ARRAYS))


@dataclasses.dataclass(frozen=True)
class GroundTruth:
    """A scene's evaluation ground truth: the initial `states` (C, N, D), the Lagrangian
    ground truth `truth` (a trajectory batch (C, F, N, D)), the chaos floor's states
    `floor` (q, qd (C, F, N, D); scored as a prediction is; None where it was not
    computed: `first_ground_truth`), each reference engine's
    trajectories `references[engine]`, and what they cost: `compile_s`, `run_s` of the
    JAX rollouts, `reference_s[engine]` of each reference, and `platform`, where the
    JAX rollouts ran (None for a file kept before it was recorded)."""

    states: State
    truth: Trajectory
    floor: State | None
    references: dict[str, Trajectory]
    compile_s: float
    run_s: float
    reference_s: dict[str, float]
    platform: str | None

    def arrays(self) -> dict[str, np.ndarray]:
        """The arrays kept on disk (`truth_trajectories`, and `states/q`, `states/qd`)."""
        kept = {_kept_name(array, engine): getattr(trajectory, array)
                for engine, trajectory in [(None, self.truth), *self.references.items()] for array in TRAJECTORY_ARRAYS}
        return {**kept, "q_floor": self.floor.q, "qd_floor": self.floor.qd, "states/q": np.asarray(self.states.q), "states/qd": np.asarray(self.states.qd)}

    def timings(self) -> dict[str, float]:
        """The costs kept with the trajectories and in the record (`truth_timings`)."""
        return {"compile_s": self.compile_s, "run_s": self.run_s, **{f"{engine}_s": s for engine, s in self.reference_s.items()}}

    @classmethod
    def from_arrays(cls, frame_dt: float, arrays: dict, meta: dict, references: tuple[str, ...]) -> GroundTruth:
        """The ground truth of arrays and meta kept on disk (`arrays`, `timings`)."""
        t = np.arange(arrays["q"].shape[1]) * frame_dt

        def trajectory(engine=None):
            return Trajectory(t, *(arrays[_kept_name(array, engine)] for array in TRAJECTORY_ARRAYS))

        return cls(State(arrays["states/q"], arrays["states/qd"]), trajectory(), State(arrays["q_floor"], arrays["qd_floor"]),
                   {engine: trajectory(engine) for engine in references},
                   meta["compile_s"], meta["run_s"], {engine: meta[f"{engine}_s"] for engine in references}, meta.get("platform"))


def truth_timings(references: tuple[str, ...]) -> tuple[str, ...]:
    """The ground truth's costs in seconds (JAX compile, JAX run, each reference
    engine's `<engine>_s`), kept with its trajectories and in its record (beside
    `platform`, where its JAX rollouts ran)."""
    return ("compile_s", "run_s", *(f"{engine}_s" for engine in references))


@functools.lru_cache(maxsize=2)
def ground_truth(profile: Profile, scene_name: str, progress: bool = True, out: Path | None = None) -> GroundTruth:
    """The `GroundTruth` of a scene's evaluation: the Lagrangian ground truth, the chaos
    floor (scored, divergence included, by `evaluate_scene`), each reference engine's
    trajectories, the initial states and timings.

    With `out`, the trajectories are kept in the dataset cache (`truth_file`, named and
    keyed by `truth_key`), and read back by every later process, of any output folder:
    MuJoCo C's reference alone takes 6.6 minutes on 16 cores for chain100-3d, more
    beside other work (a serial chain's joint-space mass matrix is dense: O(nv^3) per
    step), which each process evaluating one of the scene's pairs would otherwise redo.
    Float64 as computed (the reference agrees with MuJoCo to 1e-10 and better); about
    1.2 GB for chain100-3d."""
    if out is None:
        return _computed_ground_truth(profile, scene_name, progress)
    key, path = truth_key(profile, scene_name), truth_file(profile, scene_name)
    trajectories, timings = truth_trajectories(profile.evaluate.references), truth_timings(profile.evaluate.references)
    with claims.once(path):  # processes on one scene: the first computes, the others read
        stored = store.load(path, key)
        # Files written before their reference was fixed, or before references' energies
        # were kept, lack a version or trajectory: computed again.
        if (stored is not None and stored[1].get("mujoco_reference") == REFERENCE_VERSION
                and all(name in stored[0] for name in trajectories) and all(name in stored[1] for name in timings)):
            arrays, meta = stored
            log(f"ground truth {scene_name}: read from {path}")
            return GroundTruth.from_arrays(profile.evaluate.frame_dt, arrays, meta, profile.evaluate.references)
        truth = _computed_ground_truth(profile, scene_name, progress)
        store.save(path, key, truth.arrays(), dict(scene=scene_name, mujoco_reference=REFERENCE_VERSION, platform=truth.platform, **truth.timings()))
        return truth


def _computed_ground_truth(profile: Profile, scene_name: str, progress: bool) -> GroundTruth:
    """`ground_truth`, computed. The reference engines run in a thread beside the
    Lagrangian ground truth and chaos floor (`mujoco.rollout` releases the GIL): on a GPU
    the two overlap, which saves chain100-3d's 6 minutes of JAX rollouts."""
    scene = get_scene(scene_name)
    return _truth_from(profile, scene_name, evaluation_initial_states(profile, scene), progress, with_floor=True)


def first_ground_truth(profile: Profile, scene_name: str, count: int, progress: bool = False) -> GroundTruth:
    """The ground truth of a scene's first `count` evaluation initial conditions alone,
    computed (never cached), as `ground_truth` computes it for all of them: the
    Lagrangian ground truth and each reference engine's trajectories from the same
    states, the same settings. No chaos floor (`floor` is None): its perturbations are
    drawn for all the initial conditions at once. What re-deriving a record's first
    initial conditions needs (`lgnn.bench.verify`)."""
    states = evaluation_initial_states(profile, get_scene(scene_name))
    return _truth_from(profile, scene_name, State(np.asarray(states.q)[:count], np.asarray(states.qd)[:count]), progress, with_floor=False)


def _truth_from(profile: Profile, scene_name: str, states: State, progress: bool, with_floor: bool) -> GroundTruth:
    settings = profile.evaluate
    scene = get_scene(scene_name)
    config = settings.simulation(scene_name)
    reference_config = SimulationConfig(settings.mujoco_dt, settings.frame_dt, settings.duration)
    log(f"ground truth {scene_name}: {len(states.q)} initial conditions, RK4 dt {config.dt:g}, {config.duration:g} s; "
        f"{', '.join(settings.references) or 'no reference engine'} at dt {reference_config.dt:g} alongside")
    # A daemon thread: an error or Ctrl-C here does not wait out MuJoCo's minutes.
    references_when_done = in_background(lambda: _reference_rollouts(scene, reference_config, states, settings.references))
    # A reference that diverged would turn every error into 1 for every model: it stops there.
    where = ground_truth_platform(len(states.q))
    truth = batched_rollouts(scene, config, TRUE_DYNAMICS, states, integration=settings.integration, chunk=settings.chunk, stop_at_divergence=True,
                             label=f"truth {scene_name}", progress=progress, hint="give the scene a smaller step (EvaluateSettings.scene_dts)",
                             platform=where)
    floor, floor_s = None, 0.0
    if with_floor:
        noise = settings.floor_perturbation * jax.random.normal(jax.random.PRNGKey(settings.ic_seed + 1000), states.q.shape)
        perturbed = State(*map(np.asarray, jax.vmap(physics.projection_fn(scene))(jnp.asarray(states.q) + noise, jnp.asarray(states.qd))))
        # The perturbed runs are not references: one that diverges (T2/T3's perturbed
        # self-stressed states need dt <= 2.5e-5) is recorded as such, like a model's. With
        # energies, as the ground truth's, so that they run its compiled program (without,
        # another program: chain100's took 23-35 s to compile on an H200's busy host).
        runs = batched_rollouts(scene, config, TRUE_DYNAMICS, perturbed, integration=settings.integration, chunk=settings.chunk,
                                with_energy=True, label=f"floor {scene_name}", progress=progress, platform=where)
        floor, floor_s = State(runs.q, runs.qd), runs.run_s + runs.compile_s
    references = references_when_done()
    # What the scene's ground truth cost, in the part's log: the reference engines
    # (MuJoCo C on chain100-3d) can be most of an evaluate stage.
    log(f"ground truth {scene_name} cost: rollouts {truth.run_s:.1f} s + compile {truth.compile_s:.1f} s on {truth.platform}"
        + (f", chaos floor {floor_s:.1f} s" if with_floor else "")
        + "".join(f"; {engine} {seconds:.1f} s" for engine, (_, seconds) in references.items()))
    t = np.arange(truth.q.shape[1]) * settings.frame_dt
    return GroundTruth(states, Trajectory(t, truth.q, truth.qd, truth.energy), floor,
                       {engine: trajectory for engine, (trajectory, _) in references.items()}, truth.compile_s, truth.run_s,
                       {engine: seconds for engine, (_, seconds) in references.items()}, truth.platform)


def _reference_rollouts(scene: Scene, config: SimulationConfig, states: State, references: tuple[str, ...]) -> dict[str, tuple[Trajectory, float]]:
    """Each reference engine's trajectories from `states` (`Trajectory`: q, qd
    (C, F, N, D), true energies (C, F)) and the seconds they took, by engine, through
    the one engine interface (`get_engine(engine).rollout`; an engine raises
    `SimulationError` at a diverging frame, so no reference that diverged is scored
    against)."""
    found = {}
    for engine in references:
        start = time.perf_counter()
        trajectory = get_engine(engine).rollout(scene, config, State(np.asarray(states.q), np.asarray(states.qd)))
        found[engine] = (trajectory, time.perf_counter() - start)
    return found
