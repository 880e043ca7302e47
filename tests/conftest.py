"""Shared fixtures."""

from pathlib import Path

import pytest

# Small real files the tests need live in tests/data (with their licences), so `make test` passes on a plain clone;
# the larger sets stay in ../shared/data for the benchmarks.
TEST_DATA = Path(__file__).resolve().parent / "data"


@pytest.fixture(scope="session")
def test_data() -> Path:
    return TEST_DATA
