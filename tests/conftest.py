"""Shared fixtures."""

import os
from pathlib import Path

import pytest

# The project's real test data lives in ../shared/data beside the repository (CI clones it there);
# LFGRAPH_SHARED_DATA points elsewhere.
SHARED_DATA = Path(os.environ.get("LFGRAPH_SHARED_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))


@pytest.fixture(scope="session")
def shared_data() -> Path:
    if not SHARED_DATA.is_dir():
        pytest.fail(f"real test data not found at {SHARED_DATA}; clone beside shared/ or set LFGRAPH_SHARED_DATA")
    return SHARED_DATA
