"""The fixtures every test folder may use; plain helpers are in ``tests/helpers.py``."""

from __future__ import annotations

import os
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.helpers import EXAMPLE_CLOUD, SHARED_DATA
from worker.redis_server import RedisServer


def pytest_configure(config: pytest.Config) -> None:
    """Under ``pytest -n N`` (pytest-xdist), each worker's torch gets its share of the cores.

    Workers each running torch on every core would oversubscribe them, and OpenMP's threads then
    wait on one another (small networks ran 10 to 50 times slower so: tests/core/test_network.py).
    Processes the tests start set their own threads (``tests.helpers.TEST_ENV``).
    """
    workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
    if workers > 1:
        import torch

        torch.set_num_threads(max(1, (os.cpu_count() or 1) // workers))


@pytest.fixture(autouse=True)
def denormals_back() -> Iterator[None]:
    """Denormal floats back on after every test: ``core.runtime.configure``, which some tests run
    in this process as ``edgerecon fit`` does, flushes them in the calling thread, and hypothesis
    (the API fuzz, in the same worker later) refuses to generate floats without them."""
    yield
    torch = sys.modules.get("torch")
    if torch is not None:
        torch.set_flush_denormal(False)


@pytest.fixture
def shared_data() -> Path:
    """../shared/data (the sample shapes); the test is skipped on a fresh clone without it."""
    if not SHARED_DATA.is_dir():
        pytest.skip("../shared/data is absent (a fresh clone has no shared data)")
    return SHARED_DATA


@pytest.fixture(scope="module")
def one_thread() -> Iterator[None]:
    """Torch on one thread for the module: small tensors run faster so on a shared machine."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="session")
def redis_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[RedisServer]:
    """A redis-server of the tests' own on a free port (each test keeps to its own key prefix)."""
    server = RedisServer(tmp_path_factory.mktemp("redis")).start()
    yield server
    server.stop()


@pytest.fixture(scope="session")
def example_cloud() -> bytes:
    """examples/cube.ply, as bytes."""
    if not EXAMPLE_CLOUD.is_file():
        pytest.skip("examples/cube.ply is absent")
    return EXAMPLE_CLOUD.read_bytes()
