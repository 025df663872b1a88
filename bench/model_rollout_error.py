"""Rollout error of trained checkpoints against the ground truth (SPEC metric), as a script.

    PYTHONPATH=. python bench/model_rollout_error.py CKPT... [--scene chain4] [--count 100]
        [--dt 1e-3] [--duration 1] [--seed 1]

Initial conditions come from the paper's sampler with `--seed` (1: not the training
seed 0). Model and ground truth use the same integrator (RK4 with projection) at `--dt`,
a frame every 1e-3 s. Per frame `||q_hat - q|| / (||q_hat|| + ||q||)` over all node
coordinates; summary: geometric mean over frames t > 0 and initial conditions, with a
95% interval of that mean over initial conditions (bootstrap). A frame whose predicted
state is non-finite counts as error 1 (the metric's maximum). The chaos floor is the
same metric between the ground truth and the ground truth from initial positions
perturbed by 1e-4 (projected back onto the constraints).
"""

from __future__ import annotations

import argparse
import time

import jax
import numpy as np

from lgnn import models, physics
from lgnn.integrate import rollout
from lgnn.scene import State
from lgnn.scenes import get_scene, sample_initial_states
from lgnn.simulate import SimulationConfig
from lgnn.train import load_model


def _trajectories(scene, accel, config: SimulationConfig, states: State) -> np.ndarray:
    integrator = config.integrator_for(accel, physics.projection_fn(scene))
    run = jax.jit(jax.vmap(lambda q, qd: rollout(integrator, State(q, qd), config.n_frames, config.steps_per_frame).q))
    return np.asarray(run(states.q, states.qd))


def rollout_errors(q_hat: np.ndarray, q: np.ndarray) -> np.ndarray:
    """(C, F) per-frame relative errors of trajectories (C, F, N, D), frames t > 0."""
    q_hat, q = q_hat[:, 1:], q[:, 1:]
    diff = np.linalg.norm((q_hat - q).reshape(*q.shape[:2], -1), axis=-1)
    scale = np.linalg.norm(q_hat.reshape(diff.shape + (-1,)), axis=-1) + np.linalg.norm(q.reshape(diff.shape + (-1,)), axis=-1)
    error = diff / scale
    return np.where(np.isfinite(error), np.clip(error, 1e-300, 1.0), 1.0)


def summary(errors: np.ndarray, seed: int = 0) -> tuple[float, float, float]:
    per_ic = np.mean(np.log(errors), axis=1)
    rng = np.random.default_rng(seed)
    boots = [np.mean(rng.choice(per_ic, len(per_ic))) for _ in range(2000)]
    low, high = np.percentile(boots, [2.5, 97.5])
    return float(np.exp(per_ic.mean())), float(np.exp(low)), float(np.exp(high))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("checkpoints", nargs="+")
    parser.add_argument("--scene", default="chain4")
    parser.add_argument("--count", type=int, default=100)
    parser.add_argument("--dt", type=float, default=1e-3)
    parser.add_argument("--duration", type=float, default=1.0)
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args()
    jax.config.update("jax_enable_x64", True)
    scene = get_scene(args.scene)
    config = SimulationConfig(dt=args.dt, frame_dt=max(args.dt, 1e-3), duration=args.duration)
    states = sample_initial_states(scene, jax.random.PRNGKey(args.seed), args.count)
    truth = _trajectories(scene, physics.true_acceleration_fn(scene), config, states)
    noise = 1e-4 * jax.random.normal(jax.random.PRNGKey(args.seed + 1000), states.q.shape)
    perturbed = State(*jax.vmap(physics.projection_fn(scene))(states.q + noise, states.qd))
    floor = summary(rollout_errors(_trajectories(scene, physics.true_acceleration_fn(scene), config, perturbed), truth))
    print(f"scene {scene.name}, {args.count} initial conditions (seed {args.seed}), {config.integrator} dt {config.dt:g}, {args.duration:g} s")
    print(f"{'chaos floor (1e-4 perturbation)':<44} {floor[0]:.3e}  [{floor[1]:.3e}, {floor[2]:.3e}]")
    for path in args.checkpoints:
        model, params = load_model(path)
        start = time.monotonic()
        predicted = _trajectories(scene, models.acceleration_fn(model, params, scene), config, states)
        gm, low, high = summary(rollout_errors(predicted, truth))
        print(f"{path:<44} {gm:.3e}  [{low:.3e}, {high:.3e}]  ({time.monotonic() - start:.0f} s)")


if __name__ == "__main__":
    main()
