"""The docs a user reads agree with the measurements: every figure README.md and docs/guide.md
quote (a number with a unit: dB, ms, s, min, steps, MB, x, %) is a figure of docs/benchmarks.md, the
same number with the same unit, read whole (25 dB is not 32.25 dB), and docs/benchmarks.md stays a
page of current, stamped tables whose stamps name the CPU and scripts that exist.

Two kinds of figure are not measurements and are not checked: code (inline or fenced: commands,
options, messages and output as the program prints them) and the guide's few settings of the code
named in SETTINGS.

A stamp is a line starting `Stamp:` directly under a table (command, commit, date, CPU), or a
`commit` column of a table whose rows come from several commits: commit hashes appear nowhere else."""

from __future__ import annotations

import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
README = REPO / "README.md"
GUIDE = REPO / "docs" / "guide.md"
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
_CODE = re.compile(r"```.*?```|``.+?``|`[^`]*`")

# Settings of the code, not measurements: each phrase states a value splatcli itself uses (a period,
# a threshold, a default, a cap) and its figure is not checked. Only such values belong here; a
# measured figure goes in docs/benchmarks.md and is quoted from there. Each phrase must be in the
# guide word for word (test_settings_are_in_the_guide), so that none outlives its sentence.
SETTINGS = (
    # progress lines, the live viewer
    "longer than 10 s prints one line every 10 s", "the lines printed every 10 s", "to the CPU at most every 3 s",
    "one asked within 10 s",
    # process: camera grouping, matching, mapping, the pose check
    "agree within 5%", "under 90% of what the shared one does", "so far (at least 60 s)", "at least 2 s of matching",
    "grew by 40% rather than 10%", "at least 30% of the inliers", "has run so far, or 2 minutes",
    # train: the memory estimate, the recipe, the planner, mcmc, options
    "about 3.8 KB per Gaussian", "SH degree +1 every 1000 steps", "again 2 s later", "at most 1,050 s",
    "830 px for 30 min", "the run has 10 minutes or more", "at least every 25 steps",
    "the positions at 0.75× the preset's learning rate, every other parameter at 1.5×",
    "for the first 60% of the run",
    "until 60% of the run", "every 100 steps and at once",
    "at least 5% per refinement", "by 40% of the refinement window", "by 40% of what is left of it", "until 95% of the run",
    "within 0.05 dB of degree 3", "a sphere 5× the cameras' extent", "0.8 × `grow_grad2d`",
    "a `--time-budget` of 1,800 s or more", "900 s once kernels are cached", "10,000 steps or more",
    # eval, and gsplat's kernels
    "F-score at 1% of the", "100/50/25/10 % of the Gaussians", "1.3× the image's extent",
)


def readme_figures(text: str) -> list[str]:
    text = re.sub(r"\s+", " ", text.replace("**", ""))
    found = _COMPOUND.findall(text)
    text = _COMPOUND.sub(" ", text)
    found += [m.group(0).strip() for m in _FIGURE.finditer(text)]
    return found


def checked_figures(text: str, settings: tuple[str, ...] = SETTINGS) -> list[str]:
    """The figures of a page that must be figures of docs/benchmarks.md: all but the settings and code."""
    text = re.sub(r"\s+", " ", text.replace("**", ""))
    for phrase in settings:
        text = text.replace(phrase, " ")
    return readme_figures(_CODE.sub(" ", text))


def test_the_extractor_reads_the_figures_it_should():
    got = readme_figures("took 169 s to **31.50\ndB**, 11 min 7 s, 13.8x smaller, 2,376 steps, 5.8 ms, 54%, "
                         "3.8 min, 33.24-33.35 dB, 1080×1920, exit code 0 success, --time-budget 90")
    assert got == ["11 min 7 s", "169 s", "31.50 dB", "13.8x", "2,376 steps", "5.8 ms", "54%", "3.8 min",
                   "33.24-33.35 dB"]


def test_code_and_settings_are_not_checked_but_a_new_measurement_is():
    text = ("Progress every 10 s; `training needs about 2.6 GB`;\n```sh\nsplatcli view P  # every 3 s\n```\n"
            "the mesh took 42 s, every 10 s again")
    assert checked_figures(text, ("Progress every 10 s",)) == ["42 s", "10 s"]


def test_settings_are_in_the_guide():
    guide = re.sub(r"\s+", " ", GUIDE.read_text(encoding="utf-8").replace("**", ""))
    assert not [p for p in SETTINGS if p not in guide], "SETTINGS names phrases docs/guide.md no longer has"


def test_every_figure_of_the_readme_and_the_guide_is_in_benchmarks():
    held = set(readme_figures(BENCHMARKS.read_text(encoding="utf-8")))
    for doc, at_least in ((README, 25), (GUIDE, 30)):
        figures = checked_figures(doc.read_text(encoding="utf-8"))
        assert len(figures) >= at_least, (doc.name, figures)  # the extractor still finds the page's figures
        missing = sorted({f for f in figures if f not in held})
        assert not missing, f"{doc.name} quotes figures docs/benchmarks.md does not hold: {missing}"


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


_CPU = re.compile(r"\b(?:AMD|EPYC|Ryzen|Intel|Xeon|Apple M\d|Graviton|Neoverse)\b")


def test_stamps_name_the_cpu_and_a_script_that_exists():
    problems = []
    for n, line in enumerate(BENCHMARKS.read_text(encoding="utf-8").splitlines(), 1):
        problems += [f"{n}: {s} is not in the repository" for s in re.findall(r"\bbench/[\w/]+\.py\b", line)
                     if not (REPO / s).is_file()]
        if line.startswith("Stamp:") and not _CPU.search(line):
            problems.append(f"{n}: a stamp without the CPU's model: {line[:80]}")
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
