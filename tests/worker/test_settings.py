"""worker.settings.Settings: the one configuration, from EDGERECON_* variables and REDIS_URL."""

from __future__ import annotations

import pytest
from pydantic import ValidationError

from worker.settings import Settings


@pytest.fixture(autouse=True)
def clean_environment(monkeypatch):
    import os

    for name in list(os.environ):
        if name.startswith("EDGERECON_") or name == "REDIS_URL":
            monkeypatch.delenv(name)


@pytest.mark.parametrize("value, compiled", [("0", False), ("1", True), ("false", False), (None, True), ("", True)])
def test_edgerecon_compile_switches_the_kernels_compilation(monkeypatch, value, compiled):
    if value is not None:
        monkeypatch.setenv("EDGERECON_COMPILE", value)
    assert Settings().compile is compiled


def test_redis_url_is_read_from_the_conventional_variable_or_edgerecons(monkeypatch):
    assert Settings().redis_url is None
    monkeypatch.setenv("EDGERECON_REDIS_URL", "redis://b:6379/0")
    assert Settings().redis_url == "redis://b:6379/0"
    monkeypatch.setenv("REDIS_URL", "redis://a:6379/0")
    assert Settings().redis_url == "redis://a:6379/0"


def test_every_setting_has_its_edgerecon_variable(monkeypatch):
    monkeypatch.setenv("EDGERECON_JOB_TTL", "3600")
    monkeypatch.setenv("EDGERECON_WORKER_THREADS", "2")
    monkeypatch.setenv("EDGERECON_KEY_PREFIX", "other")
    settings = Settings()
    assert (settings.job_ttl, settings.worker_threads, settings.key_prefix) == (3600, 2, "other")


def test_a_bad_value_is_refused(monkeypatch):
    monkeypatch.setenv("EDGERECON_HEARTBEAT_TTL", "1")
    with pytest.raises(ValidationError, match="heartbeat_ttl"):
        Settings()


def test_torch_threads_default_to_the_cores_shared_among_the_workers(monkeypatch):
    monkeypatch.setattr("os.sched_getaffinity", lambda pid: set(range(8)))
    assert Settings().torch_threads() == 8
    assert [Settings().torch_threads(workers) for workers in (2, 3, 8, 16)] == [4, 2, 1, 1]
    monkeypatch.setenv("EDGERECON_WORKER_THREADS", "3")
    assert Settings().torch_threads() == Settings().torch_threads(4) == 3


def test_the_embedded_redis_keeps_its_data_in_the_users_data_folder_never_a_temporary_one(monkeypatch, tmp_path):
    monkeypatch.delenv("XDG_DATA_HOME", raising=False)
    monkeypatch.setenv("HOME", str(tmp_path))
    assert Settings().data_path() == tmp_path / ".local" / "share" / "edgerecon"
    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path / "xdg"))
    assert Settings().data_path() == tmp_path / "xdg" / "edgerecon"
    monkeypatch.setenv("EDGERECON_DATA_DIR", str(tmp_path / "mine"))
    assert Settings().data_path() == tmp_path / "mine"
    assert Settings().redis_maxmemory == 1024**3
