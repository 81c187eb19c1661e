"""Every benchmark script imports and answers --help: a renamed helper or a changed signature
in bench/common.py breaks one here, not on the day it is run (bench/distributed.py crashed so)."""

from __future__ import annotations

import contextlib
import importlib
import io
import sys
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parent.parent / "bench"
SCRIPTS = sorted(p.stem for p in BENCH.glob("*.py") if "\ndef main(" in p.read_text(encoding="utf-8"))


def test_the_scripts_are_found():
    assert {"gpu", "collection", "distributed", "minutes", "train", "versus"} <= set(SCRIPTS)


@pytest.mark.parametrize("name", SCRIPTS)
def test_script_answers_help(name, monkeypatch):
    module = importlib.import_module(name)
    monkeypatch.setattr(sys, "argv", [f"bench/{name}.py", "--help"])
    out = io.StringIO()
    with contextlib.redirect_stdout(out), pytest.raises(SystemExit) as stop:
        module.main()
    assert stop.value.code == 0 and "usage:" in out.getvalue(), out.getvalue()[-500:]
