"""Shared pytest fixtures: paths to the shared real data, a numba cache, free loopback ports."""

from __future__ import annotations

import os
import socket
import tempfile
from pathlib import Path

import pytest

# helper modules shared by several test files: their asserts report values like the tests' own
pytest.register_assert_rewrite("simulate_helpers", "fieldtool_sites")

os.environ.setdefault("NUMBA_CACHE_DIR", os.path.join(tempfile.gettempdir(), "roadwatch-test-numba"))

REPO = Path(__file__).resolve().parent.parent
SHARED_DATA = REPO.parent / "shared" / "data"


@pytest.fixture(scope="session")
def shared_data() -> Path:
    if not SHARED_DATA.is_dir():
        pytest.skip("../shared/data is not beside the repository")
    return SHARED_DATA


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def port() -> int:
    return free_port()
