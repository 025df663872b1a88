"""Table writers, defined once: tidy CSV and markdown, written atomically.

- `write_csv(frame, path)`: a pandas DataFrame as CSV (floats to 6 significant digits,
  gzipped for a `.gz` path), the benchmark report's tables;
- `write_table(rows, columns, csv_path, md_path, title, header, notes)`: rows (dicts) as
  a CSV whose first lines are `# header` comments, and a markdown file with the title,
  the header and notes as a list, then the table; the crosscheck and stability reports;
- `read_table(csv_path)`: such a CSV's header lines and rows (strings) back.
"""

from __future__ import annotations

import csv
import gzip
import io
import os
from typing import Callable, Sequence

from lgnn.files import atomic_path, write_text_atomic


def write_csv(frame, path: str | os.PathLike) -> None:
    """A DataFrame as CSV (no index, floats `%.6g`), atomically; gzipped if `path` ends
    in `.gz`, with no timestamp in the header, so the same table gives the same bytes."""
    buffer = io.StringIO()
    frame.to_csv(buffer, index=False, float_format="%.6g")
    if str(path).endswith(".gz"):
        with atomic_path(path) as tmp:
            tmp.write_bytes(gzip.compress(buffer.getvalue().encode(), mtime=0))
    else:
        write_text_atomic(path, buffer.getvalue())


def _csv_cell(value):
    return f"{value:.3e}" if isinstance(value, float) else value


def _markdown_cell(value) -> str:
    return f"{value:.3g}" if isinstance(value, float) else str(value)


def escape_markdown_cell(text: str) -> str:
    """A cell's text with `|` escaped, so a note like `max |E-E0|` stays in its column."""
    return text.replace("|", "\\|")


def write_table(rows: Sequence[dict], columns: Sequence[str], csv_path: str | os.PathLike, md_path: str | os.PathLike, title: str,
                header: Sequence[str] = (), notes: Sequence[str] = (), csv_cell: Callable = _csv_cell,
                markdown_cell: Callable[[object], str] = _markdown_cell) -> None:
    """Tidy CSV (`header` lines as `#` comments) and a markdown table of the same rows
    (`# title`, then `header` and `notes` as a list), atomically. Floats are written
    `%.3e` in the CSV and `%.3g` in markdown unless `csv_cell` / `markdown_cell` say otherwise."""
    buffer = io.StringIO()
    for line in header:
        buffer.write(f"# {line}\n")
    writer = csv.DictWriter(buffer, fieldnames=list(columns), lineterminator="\n")
    writer.writeheader()
    for row in rows:
        writer.writerow({k: csv_cell(row[k]) for k in columns})
    md = [f"# {title}", ""] + [f"- {line}" for line in header] + [f"- {n}" for n in notes] + ["",
          "| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    md += ["| " + " | ".join(escape_markdown_cell(markdown_cell(row[k])) for k in columns) + " |" for row in rows]
    write_text_atomic(csv_path, buffer.getvalue())
    write_text_atomic(md_path, "\n".join(md) + "\n")


def read_table(csv_path: str | os.PathLike) -> tuple[list[str], list[dict]]:
    """`(header, rows)` of a CSV `write_table` wrote: its `# ` header lines without the
    mark, and its rows as dicts of strings."""
    with open(csv_path) as handle:
        lines = handle.read().splitlines()
    header = [line[2:] for line in lines if line.startswith("# ")]
    return header, list(csv.DictReader(line for line in lines if not line.startswith("#")))
