"""worker.process: the worker process's own pieces, against a real Redis, and its warm-up."""

from __future__ import annotations

import threading
import time
import uuid

import torch
from rq.serializers import JSONSerializer

from core import network
from tests.helpers import wait_for
from worker.job import JobRunner
from worker.process import FitWorker, warm_kernels
from worker.settings import Settings
from worker.store import JobStore


def test_a_worker_whose_listener_already_read_its_unsubscribe_reply_stops_within_2_s(redis_server):
    # The race seen on busy machines: the listener thread handles the unsubscribe reply before its
    # stop flag is cleared, and waits for a new subscription for its whole poll period, while
    # redis-py 8 joins it with no time limit (rq's own 60 s period: a 60 s exit).
    redis = redis_server.client()
    settings = Settings(key_prefix=f"test-{uuid.uuid4().hex[:12]}", queue=f"q-{uuid.uuid4().hex[:8]}")
    runner = JobRunner(JobStore(redis, settings), settings)
    worker = FitWorker([runner.store.queue], connection=redis, serializer=JSONSerializer, runner=runner)
    worker.subscribe()
    wait_for(lambda: worker.pubsub.subscribed, 5, 0.01, "the subscription")
    worker.pubsub.unsubscribe()
    wait_for(lambda: not worker.pubsub.subscribed, 5, 0.01, "the listener to read the unsubscribe reply")
    time.sleep(0.1)  # the listener is back in its wait for a subscription

    started = time.monotonic()
    stopping = threading.Thread(target=worker.unsubscribe, daemon=True)
    stopping.start()
    stopping.join(timeout=10)
    assert not stopping.is_alive(), "the worker's unsubscribe still waits for its listener after 10 s"
    assert time.monotonic() - started < 2
    redis.close()


def test_the_warm_up_compiles_a_default_jobs_whole_steps_in_each_shape_for_both_networks(monkeypatch):
    steps: set[tuple[int, bool, int]] = set()  # (batch size, with the normal term, Fourier features)

    def compile(function, **options):  # a stand-in for torch.compile: records the whole steps
        def run(*args):
            if function.__name__ == "_step_terms":
                model, batch, normals = args[0], args[1], args[7]
                steps.add((len(batch), normals is not None, model.features))
            return function(*args)

        return run

    monkeypatch.setattr(torch, "compile", compile)
    monkeypatch.setattr(network, "_kernels", network._Kernels())
    warm_kernels()
    shapes = {(512, True), (512, False), (1024, False)}  # the default fit's: half batch, normal term for half
    assert steps == {(*shape, features) for shape in shapes for features in (0, 32)}
