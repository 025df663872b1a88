"""Time the full profile's training data of the four training scenes of the paper track
(chain4, chain4-3d, chain4-varied, chain4-drag; the transfer track's varied draws of
chain4 come with them), generated one after another into DIR: each dataset's seconds
and the total, JAX's start-up apart.

    PYTHONPATH=. python3 results/gpu/training/tangent/training_data_time.py DIR
"""

import sys
import time

from lgnn import runtime

runtime.configure()

from lgnn.bench.profiles import get_profile, training_jobs  # noqa: E402
from lgnn.bench.stages.train import job_settings  # noqa: E402
from lgnn.learn import data  # noqa: E402

profile = get_profile("full")
jobs = [job for job in training_jobs(profile) if job.scene in ("chain4", "chain4-3d", "chain4-varied", "chain4-drag")]
configs = dict.fromkeys(job_settings(profile, job)[2] for job in jobs)
start = time.perf_counter()
for config in configs:
    began = time.perf_counter()
    data.load_or_generate(config, sys.argv[1])
    print("data", config.scene, round(time.perf_counter() - began, 1), "s", flush=True)
print("data total", round(time.perf_counter() - start, 1), "s", len(configs), "configs", flush=True)
