"""Shared test fixtures: seeding, paths to optional third-party data."""

from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")  # what the CLI uses (splatcli/cli/main.py); before torch loads

import random
from pathlib import Path

import numpy as np
import pytest
import torch

from common import data_dir  # bench/common.py (pyproject's pytest pythonpath): the benchmarks' data too


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
