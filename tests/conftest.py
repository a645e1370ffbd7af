"""Shared test fixtures: where the shared data lives, and deterministic torch settings."""
import os
from pathlib import Path

import pytest
import torch

from tests.paths import REPO


def shared_dir() -> Path:
    """../shared beside the repository (CI clones main with ../shared beside it);
    ACCEL_BAYES_SHARED overrides."""
    env = os.environ.get("ACCEL_BAYES_SHARED")
    return Path(env) if env else REPO.parent / "shared"


def mimu_data_dir() -> Path:
    return shared_dir() / "data" / "mimu4444-bcd"


@pytest.fixture(scope="session")
def mimu_dir():
    d = mimu_data_dir()
    if not d.is_dir():
        pytest.skip(f"shared MIMU data not found at {d}")
    return d


@pytest.fixture(autouse=True)
def _torch_defaults():
    # Tests are written for float64 and must not depend on the thread count.
    torch.set_num_threads(1)
    yield
