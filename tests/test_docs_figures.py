"""The docs a user reads agree with the measurements: every figure README.md quotes (a number with
a unit: dB, ms, s, min, steps, MB, x, %) appears verbatim in docs/benchmarks.md, and
docs/benchmarks.md stays a page of current, stamped tables.

A stamp is a line starting `Stamp:` directly under a table (command, commit, date, CPU), or a
`commit` column of a table whose rows come from several commits: commit hashes appear nowhere else."""

from __future__ import annotations

import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
README = REPO / "README.md"
BENCHMARKS = REPO / "docs" / "benchmarks.md"

MAX_LINES = 400
_NUM = r"\d[\d,]*(?:\.\d+)?"
# "11 min 7 s" first, so that its parts are not read again as "7 s"
_COMPOUND = re.compile(rf"(?<![\w.,]){_NUM} min {_NUM} s(?!\w)")
_FIGURE = re.compile(
    rf"(?<![\w.,-])({_NUM}(?:[-–]{_NUM})?)\s?"
    r"(dB|ms|s|min|minutes|steps|KB|MB|GB|%|x(?![\w\d])|×(?!\d))(?![\w])"
)
# 7-40 hex digits with at least one letter and one digit (a commit), as a whole word
_HASH = re.compile(r"\b(?=[0-9a-f]*[a-f])(?=[0-9a-f]*\d)[0-9a-f]{7,40}\b")


def readme_figures(text: str) -> list[str]:
    text = re.sub(r"\s+", " ", text.replace("**", ""))
    found = _COMPOUND.findall(text)
    text = _COMPOUND.sub(" ", text)
    found += [m.group(0).strip() for m in _FIGURE.finditer(text)]
    return found


def test_the_extractor_reads_the_figures_it_should():
    got = readme_figures("took 169 s to **31.50\ndB**, 11 min 7 s, 13.8x smaller, 2,376 steps, 5.8 ms, 54%, "
                         "3.8 min, 33.24-33.35 dB, 1080×1920, exit code 0 success, --time-budget 90")
    assert got == ["11 min 7 s", "169 s", "31.50 dB", "13.8x", "2,376 steps", "5.8 ms", "54%", "3.8 min",
                   "33.24-33.35 dB"]


def test_every_readme_figure_is_in_benchmarks():
    figures = readme_figures(README.read_text(encoding="utf-8"))
    assert len(figures) >= 10, figures  # the extractor still finds README's figures
    bench = re.sub(r"\s+", " ", BENCHMARKS.read_text(encoding="utf-8").replace("**", ""))
    missing = sorted({f for f in figures if f not in bench})
    assert not missing, f"README.md quotes figures docs/benchmarks.md does not hold: {missing}"


def _is_stamp(line: str, table_header: str | None) -> bool:
    if line.startswith("Stamp:"):
        return True
    cells = [c.strip().lower() for c in (table_header or "").strip("|").split("|")]
    return line.startswith("|") and "commit" in cells


def test_benchmarks_is_short_current_and_stamped():
    lines = BENCHMARKS.read_text(encoding="utf-8").splitlines()
    assert len(lines) <= MAX_LINES, f"docs/benchmarks.md has {len(lines)} lines (at most {MAX_LINES})"
    header, previous, problems = None, "", []
    for n, line in enumerate(lines, 1):
        if line.startswith("|") and not previous.startswith("|"):
            header = line  # a table starts
        elif not line.startswith("|"):
            header = None
        if re.search(r"\bsessions?\b", line, re.I):
            problems.append(f"{n}: 'session': {line[:80]}")
        if re.search(r"\bissue\s+#?\d+", line, re.I):
            problems.append(f"{n}: an issue number: {line[:80]}")
        if _HASH.search(line) and not _is_stamp(line, header):
            problems.append(f"{n}: a commit outside a stamp: {line[:80]}")
        previous = line
    assert not problems, "\n".join(problems)


def test_every_table_is_stamped():
    lines = BENCHMARKS.read_text(encoding="utf-8").splitlines()
    unstamped = []
    for n, line in enumerate(lines):
        starts = line.startswith("|") and (n == 0 or not lines[n - 1].startswith("|"))
        if not starts:
            continue
        end = n
        while end < len(lines) and lines[end].startswith("|"):
            end += 1
        after = next((x for x in lines[end:] if x.strip()), "")
        if not (after.startswith("Stamp:") or _is_stamp(line, line)):
            unstamped.append(f"{n + 1}: {line[:80]}")
    assert not unstamped, "tables without a Stamp: line under them or a commit column:\n" + "\n".join(unstamped)
