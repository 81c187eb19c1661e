"""Every benchmark script starts and answers --help, run as it is run (`python bench/NAME.py`,
in a child: bench/ is not on the tests' path and no test imports it). A renamed helper or a
changed signature in bench/common.py breaks one here, not on the day it is run
(bench/distributed.py crashed so)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parent.parent / "bench"
SCRIPTS = sorted(p.stem for p in BENCH.glob("*.py") if "\ndef main(" in p.read_text(encoding="utf-8"))


def test_the_scripts_are_found():
    assert set(SCRIPTS) == {"distributed", "formats", "gpu", "peer_train", "peers", "poses", "process", "step", "train"}


@pytest.mark.parametrize("name", SCRIPTS)
def test_script_answers_help(name):
    r = subprocess.run([sys.executable, str(BENCH / f"{name}.py"), "--help"], cwd=BENCH.parent, capture_output=True,
                       text=True, timeout=300)
    assert r.returncode == 0 and "usage:" in r.stdout, (r.stdout[-500:], r.stderr[-2000:])
