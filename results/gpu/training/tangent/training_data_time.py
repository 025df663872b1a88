"""Time the full profile's training data of the paper track's four training scenes, one after another, into DIR."""
import sys, time
from lgnn import runtime
runtime.configure()
from lgnn.bench.grid import get_profile, training_jobs
from lgnn.bench.stages.train import job_settings
from lgnn.learn import data
profile = get_profile("full")
jobs = [j for j in training_jobs(profile) if j.scene in ("chain4", "chain4-3d", "chain4-varied", "chain4-drag")]
configs = dict.fromkeys(job_settings(profile, job)[2] for job in jobs)
start = time.perf_counter()
for config in configs:
    t = time.perf_counter()
    data.load_or_generate(config, sys.argv[1])
    print("data", config.scene if hasattr(config, "scene") else config, round(time.perf_counter() - t, 1), "s", flush=True)
print("data total", round(time.perf_counter() - start, 1), "s", len(configs), "configs", flush=True)
