"""Speed-against-error stage: wall time per simulated second (single trajectory,
compile apart) against rollout error, for the ground-truth engines at several steps
and for each learned model, against a MuJoCo C reference at a tenth of the smallest step.
The engines are those of the registry the table times (`timed_engines`:
`lgnn.engines.EngineEntry.in_speed_table`: the Lagrangian engine, MuJoCo C, MJX), in
registry order.

A scene's record (JSON) depends on the scene's content, the profile's `SpeedSettings`
and `EvaluateSettings` (its step, frames and initial conditions) and the content of
every checkpoint timed (`speed_key`); which engines are timed is not in the key: a
record lacking a row of a timed engine (made before that engine was registered) is
measured again by `speed_error`. `speed_rows` gives the report the rows of the records
that match, as a tidy table.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from lgnn import metrics, records
from lgnn.bench import store
from lgnn.engines import ENGINES, form_of, get_engine
from lgnn.bench.grid import TRAINING_SCENES, TrainingJob
from lgnn.bench.profiles import Profile, evaluated_jobs
from lgnn.records import settings_key
from lgnn.bench.stages.evaluate import evaluation_initial_states
from lgnn.bench.store import log
from lgnn.engines.base import SimulationConfig
from lgnn.engines.rollouts import timed_rollouts
from lgnn.learn import models
from lgnn.learn.checkpoints import content_digest, load_model
from lgnn.scene import State, get_scene, scene_to_dict


def timed_engines() -> list[str]:
    """The engines the speed table times (`EngineEntry.in_speed_table`), in registry order."""
    return [name for name, entry in ENGINES.items() if entry.in_speed_table]


def timed_jobs(profile: Profile, scene_name: str, jobs: list[TrainingJob] | None = None) -> list[TrainingJob]:
    """The learned models timed on a scene: those the grid evaluates on it
    (`profiles.evaluated_jobs`: CLNN on its own scene only) trained on the main training
    scene of the scene's dimension (`TRAINING_SCENES`: chain4, chain4-3d), restricted
    to `jobs` if given and to `SpeedSettings.models`."""
    trained_on = TRAINING_SCENES[get_scene(scene_name).dim]
    return [j for j in evaluated_jobs(profile, scene_name) if j.scene == trained_on and (jobs is None or j in jobs)
            and (profile.speed.models is None or j.model in profile.speed.models)]


def _checkpoint_digests(profile: Profile, scene_name: str, out: Path, jobs: list[TrainingJob] | None = None) -> dict[str, str]:
    layout = store.layout(profile, out)
    return {j.name: content_digest(layout.found(layout.checkpoint(j))) for j in timed_jobs(profile, scene_name, jobs)
            if layout.found(layout.checkpoint(j)).exists()}


def speed_key(profile: Profile, scene_name: str, out: Path, jobs: list[TrainingJob] | None = None) -> str:
    """Settings a scene's speed record depends on (module docstring)."""
    # Which models are timed enters through the checkpoints named below; the field keeps
    # the None the records made before it could name models hold, so a profile that lists
    # the models its record times finds that record.
    speed = {**settings_key(profile.speed), "models": None}
    if speed["repeats"] == 1:
        del speed["repeats"]  # single-run records made before the field keep their key
    return records.digest({"speed": speed, "evaluate": settings_key(profile.evaluate.for_scene(scene_name)),
                           "scene": scene_to_dict(get_scene(scene_name)), "checkpoints": _checkpoint_digests(profile, scene_name, out, jobs)})


def speed_error(profile: Profile, scene_name: str, out: Path, jobs: list[TrainingJob] | None = None) -> Path:
    """Rows `scene, solver, kind, dt, wall_s_per_sim_s, wall_s_min_per_sim_s,
    wall_s_max_per_sim_s, runs, evaluations_per_sim_s, compile_s, rollout_error, note,
    form` (JSON record; `form`: the MJCF form, nested or maximal, a MuJoCo engine ran,
    else ""): every ground-truth engine at each of `SpeedSettings.dts` (MuJoCo C and MJX
    in the form each picks: MJX maximal past depth 8, which compiles in seconds where
    the nested form took minutes, so no scene is skipped) and every
    timed model (`timed_jobs`) at the scene's evaluation dt, single trajectory from the
    scene's first initial condition over `horizon` s, frames every `frame_dt`; wall time:
    the median (and min, max) of `SpeedSettings.repeats` timed runs; compile: the
    first's; error: geometric mean of the rollout error against MuJoCo C at a tenth of
    the smallest step. Engines: `timed_engines()`, each one the profile turns off
    (`SpeedSettings.runs`) a row saying so, and a compiled one's (`EngineEntry.compiled`:
    the JAX engines) runs over `SpeedSettings.max_link_steps` likewise."""
    from lgnn.engines import mujoco as lm

    settings = profile.speed
    scene = get_scene(scene_name)
    layout = store.layout(profile, out)
    checkpoints = _checkpoint_digests(profile, scene_name, out, jobs)
    path, key = layout.speed_record(scene_name), speed_key(profile, scene_name, out, jobs)
    engines = timed_engines()
    stored = layout.load_json(path, key)
    if stored is not None and set(engines) <= {r["solver"] for r in stored["rows"] if r["kind"] == "engine"}:
        return path
    states = evaluation_initial_states(profile, scene)
    single = State(states.q[:1], states.qd[:1])
    horizon, frame_dt = settings.horizon, profile.evaluate.frame_dt
    reference_config = SimulationConfig(min(settings.dts) / 10, frame_dt, horizon)
    log(f"speed/error {scene_name}: MuJoCo C reference at dt {reference_config.dt:g}")
    reference = lm.rollout(scene, reference_config, single).q[0]
    rows = []

    def row(solver, kind, dt, run_s=(), **values):
        wall = [s / horizon for s in run_s] or [float("nan")]
        base = dict(scene=scene_name, solver=solver, kind=kind, dt=dt, wall_s_per_sim_s=float(np.median(wall)),
                    wall_s_min_per_sim_s=min(wall), wall_s_max_per_sim_s=max(wall), runs=len(run_s), evaluations_per_sim_s=4 / dt,
                    compile_s=float("nan"), rollout_error=float("nan"), note="", form="")
        rows.append({**base, **values})

    for engine in engines:
        for dt in settings.dts:
            if not settings.runs(engine):
                row(engine, "engine", dt, note="not run in this profile")
                continue
            if ENGINES[engine].compiled and horizon / dt * scene.n_links > settings.max_link_steps:
                row(engine, "engine", dt, note=f"not run: over {settings.max_link_steps:g} link-steps")
                continue
            config = SimulationConfig(dt, frame_dt, horizon)
            runner = get_engine(engine)  # each engine's own integration: RK4 (with projection for the Lagrangian one)
            timed = [runner.timed_rollout(scene, config, single) for _ in range(settings.repeats)]
            compile_s, _, q = timed[0]
            row(engine, "engine", dt, run_s=[t[1] for t in timed], compile_s=compile_s, rollout_error=metrics.gmean_error(q[0], reference),
                form=form_of(runner, scene))
            log(f"speed/error {scene_name} {engine} dt {dt:g}: {rows[-1]['wall_s_per_sim_s']:.3g} s per simulated s, error {rows[-1]['rollout_error']:.2e}")
    config = SimulationConfig(profile.evaluate.dt_for(scene_name), frame_dt, horizon)
    for job in timed_jobs(profile, scene_name, jobs):
        if job.name not in checkpoints:
            row(job.label, "learned", config.dt, note="no checkpoint")
            continue
        model, params = load_model(layout.found(layout.checkpoint(job)))
        compile_s, run_s, runs = timed_rollouts(scene, config, models.AccelerationFactory(model), single, params,
                                                integration=profile.evaluate.integration, repeats=settings.repeats)
        row(job.label, "learned", config.dt, run_s=run_s, compile_s=compile_s, rollout_error=metrics.gmean_error(runs.q[0], reference))
        log(f"speed/error {scene_name} {job.label}: {rows[-1]['wall_s_per_sim_s']:.3g} s per simulated s, error {rows[-1]['rollout_error']:.2e}")
    store.save_json(path, key, horizon=horizon, rows=rows)
    return path


def load_speed(profile: Profile, scene_name: str, out: Path) -> dict | None:
    """A scene's speed record if it matches the profile and checkpoints, else None."""
    layout = store.layout(profile, out)
    return layout.load_json(layout.speed_record(scene_name), speed_key(profile, scene_name, out))


def speed_rows(profile: Profile, out: Path) -> list[dict]:
    """Tidy rows of every matching speed record (`speed_error`'s columns, `horizon_s`
    and the `commit, versions, device` that made them, `folder` the one it was read
    from: `store.Layout.load_json`); a stale record is not reported."""
    rows = []
    for scene in profile.speed.scenes:
        stored = load_speed(profile, scene, out)
        if stored is not None:
            env = {k: stored.get("environment", {}).get(k, "unknown") for k in ("commit", "versions", "device")}
            rows += [{**r, "horizon_s": stored["horizon"], **env, "folder": stored["folder"]} for r in stored["rows"]]
    return rows
