"""The benchmark's report: every file under `<out>` written from the records the stages
wrote, in one pass (`write`): the summary tables (`lgnn.bench.report.summary`), the figures
(`lgnn.bench.report.figures`), `performance.md` (`lgnn.bench.report.performance`), `README.md`
(`lgnn.bench.report.readme`) and `LEADERBOARD.md` (`lgnn.bench.report.leaderboard`).

pandas and matplotlib are imported by these modules only, on first use (the library's numerics do not
need them).
"""

from __future__ import annotations

from pathlib import Path

from lgnn.bench.report.figures import draw
from lgnn.bench.profiles import Profile
from lgnn.records import settings_key
from lgnn.bench.report.leaderboard import LEADERBOARD, leaderboard_markdown
from lgnn.bench.report.performance import performance_markdown, speed_markdown
from lgnn.bench.report.readme import readme_markdown
from lgnn.bench.stages.evaluate import load_pairs, load_truths
from lgnn.bench.stages.external import load_externals
from lgnn.bench.stages.mass import load_mass
from lgnn.bench.stages.scaling import load_scaling
from lgnn.bench.stages.speed import speed_rows as load_speed_rows
from lgnn.bench.stages.train import load_checkpoints
from lgnn.bench.report.summary import CURVES, MASS_COLUMNS, SUMMARY, provenance_columns, tables
from lgnn.bench.tables import write_csv
from lgnn.files import write_text_atomic


def stage_sections(profile: Profile, out: Path, sections) -> list[str]:
    """README lines of the registered stages' own sections, in registry order: `sections`
    holds `(name, settings, load, section)` of each stage that has one
    (`lgnn.bench.run.Stage`); each gives its `section(profile, out, load(profile, out))`
    lines, then every setting its records are keyed on (`lgnn.records.settings_key`)."""
    lines = []
    for name, settings, load, section in sections:
        lines += section(profile, out, None if load is None else load(profile, out))
        if settings is not None:
            keyed = settings_key(settings(profile))
            lines += ["", f"Settings of the {name} stage: " + "; ".join(f"`{key}` = {value!r}" for key, value in keyed.items()) + "."]
        lines.append("")
    return lines


def write(profile: Profile, out: Path, sections=(), command: str | None = None) -> Path:
    """Write every report file under `out` from the records there (and in the profile's
    `base` folder, read in place), with the registered stages' `sections`
    (`stage_sections`) before the provenance; `command`: what the header says wrote it
    (default: the call, `lgnn.bench.report.readme`). Returns README.md's path."""
    import matplotlib

    matplotlib.use("Agg")
    import pandas as pd

    from lgnn.provenance import environment

    # The commit before this function writes anything: rewriting the committed report
    # files would otherwise mark the report's own header "+dirty".
    env = environment()
    out = Path(out)
    truths, pairs, externals = load_truths(profile, out), load_pairs(profile, out), load_externals(profile, out)
    summary, curves = tables(truths, pairs + externals, profile.evaluate.references)
    bench_dir = out / "benchmark"
    bench_dir.mkdir(parents=True, exist_ok=True)
    write_csv(summary, bench_dir / SUMMARY)
    # A summary written plain by an older lgnn would sit stale beside the new one.
    (bench_dir / "summary.csv").unlink(missing_ok=True)
    write_csv(curves, bench_dir / CURVES)
    speed_rows = load_speed_rows(profile, out)
    # Where each row was read from is the provenance table's, not a column of the table.
    write_csv(pd.DataFrame([{k: v for k, v in r.items() if k != "folder"} for r in speed_rows]), bench_dir / "speed_error.csv")
    write_text_atomic(bench_dir / "speed_error.md", speed_markdown(speed_rows))
    if speed_rows:
        write_text_atomic(out / "performance.md", performance_markdown(profile, speed_rows, load_scaling(profile, out), out))
    mass_records = load_mass(profile, out)
    write_csv(pd.DataFrame([{**{k: m[k] for k in MASS_COLUMNS}, **provenance_columns(m)} for _, m in mass_records]),
               bench_dir / "mass_matrix.csv")
    figures = draw(profile, out / "figures", truths, pairs, externals, curves, speed_rows, mass_records)
    path = out / "README.md"
    # Each checkpoint read once, for the training table, its warnings and the leaderboard.
    checkpoints = load_checkpoints(profile, out)
    write_text_atomic(path, readme_markdown(profile, out, (truths, pairs + externals), checkpoints, summary, speed_rows, mass_records, figures, env,
                                            stage_sections(profile, out, sections), command))
    write_text_atomic(out / LEADERBOARD, leaderboard_markdown(profile, out, summary, checkpoints, env, command))
    return path
