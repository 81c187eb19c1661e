"""Shared test fixtures: seeding, paths to optional third-party data."""

from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")  # what the CLI uses (splatcli/cli/main.py); before torch loads

import random
from pathlib import Path

import numpy as np
import pytest
import torch

from support import data_dir  # tests/support (pyproject's pytest pythonpath names tests/)


def pytest_collection_modifyitems(config, items):
    """The tests marked `first` (the longest), then the other slow ones, then the rest (stable: files
    stay in order otherwise). With several test processes (`make test`) each file runs in one of
    them, and a long file started last would leave the others idle at the end."""
    items.sort(key=lambda item: (item.get_closest_marker("first") is None, item.get_closest_marker("slow") is None))


@pytest.fixture(autouse=True)
def _seed_everything():
    random.seed(0)
    np.random.seed(0)
    torch.manual_seed(0)
    yield


@pytest.fixture
def shared_data() -> Path:
    d = data_dir()
    if not d.is_dir():
        pytest.skip("../shared/data is absent")
    return d
