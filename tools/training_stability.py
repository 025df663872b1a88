"""Does a fresh LGNN train stably on chain4, for several seeds? (issue 13, item 1)

For each seed: train LGNN on the paper's chain4 data (100 trajectories, cached in
the user cache, `lgnn.learn.data.default_cache_dir()`, unless `--cache-dir`) for an epoch budget, print the validation loss of the first epochs
and every 25th, the largest validation loss relative to the first epoch's, and the
rollout error of the best parameters over 1 s of chain4 from the scene's own state
(`lgnn.metrics.relative_error` of node positions, averaged over frames, against
`lgnn.engines.lagrangian.simulate`; RK4 with projection at dt 1e-3 for both, as the
benchmark's evaluation).

    PYTHONPATH=. python tools/training_stability.py --seeds 0 1 2 --epochs 200
    PYTHONPATH=. python tools/training_stability.py --seeds 0 --epochs 10 --legacy-optimiser

(`PYTHONPATH=.`: this checkout's lgnn, not an editable install elsewhere.)

`--legacy-optimiser`: the paper's plain Adam (no warm-up, decay or clipping).
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import lgnn


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--epochs", type=int, default=200)
    parser.add_argument("--minutes", type=float, default=None, help="wall-clock cap per seed (the acceptance: a usable model within 5 minutes)")
    parser.add_argument("--legacy-optimiser", action="store_true")
    parser.add_argument("--lr", type=float, default=None)
    # The user cache by default: a tool run from the checkout never writes into results/.
    parser.add_argument("--cache-dir", default="default", help="dataset cache (default: lgnn.learn.data.default_cache_dir())")
    args = parser.parse_args()
    lgnn.configure()

    import numpy as np

    from lgnn import provenance
    from lgnn.engines.base import SimulationConfig
    from lgnn.engines.lagrangian import simulate
    from lgnn.errors import SimulationError
    from lgnn.learn import data, models, protocol, train
    from lgnn.metrics import relative_error
    from lgnn.scene import get_scene

    print(provenance.environment())
    scene = get_scene("chain4")
    dataset = data.load_or_generate(data.DataConfig("chain4"), args.cache_dir)
    model = models.ModelConfig.for_scene("lgnn", scene)
    simulation = SimulationConfig(dt=1e-3, frame_dt=1e-3, duration=1.0)
    truth = simulate(scene, simulation)
    for seed in args.seeds:
        config = protocol.TrainConfig(epochs=args.epochs, seed=seed, patience=args.epochs, minutes=args.minutes)
        if args.legacy_optimiser:
            config = dataclasses.replace(config, **protocol.LEGACY_OPTIMISATION)
        if args.lr:
            config = dataclasses.replace(config, learning_rate=args.lr)
        start = time.monotonic()
        state = train.train(model, config, dataset, scene)
        seconds = time.monotonic() - start
        val = np.array([h[2] for h in state.history])
        shown = [f"{e}:{v:.3g}" for e, v in enumerate(val, 1) if e <= 5 or e % 25 == 0]
        print(f"seed {seed}: {config}")
        print(f"  validation MSE by epoch: {' '.join(shown)}")
        print(f"  max / first epoch's validation MSE: {val.max() / val[0]:.3g}; best {state.best_val:.3g} at epoch {state.best_epoch}; {seconds:.0f} s")
        try:
            predicted = models.rollout(model, state.best_params, scene, simulation)
            error = float(np.mean(relative_error(predicted.q, truth.q, 2)))
            print(f"  1 s chain4 rollout error (mean over frames): {error:.3g}")
        except SimulationError as err:
            print(f"  1 s chain4 rollout diverged: {err}")


if __name__ == "__main__":
    main()
