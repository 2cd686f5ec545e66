"""Property-based fuzzing of the live API from its own OpenAPI schema (schemathesis): whatever a
client sends, valid or not, the API never answers 5xx, and every answer has a documented status
code, content type and shape. Real uvicorn on a redis-server of the module's own; no worker runs.

Half the cases address a real (canceled) job rather than a random id, and half the uploads carry a
valid cloud rather than random bytes, so that the 200s, 202s and 409s are checked too. Bounded in
time: a fixed number of examples per operation and mode (about 30 s in all on two cores).
Schemathesis's own pytest plugin does not run under pytest 9 yet, so its strategies are driven
with hypothesis's ``@given`` here.
"""

from __future__ import annotations

import httpx
import hypothesis
import pytest
import schemathesis
from hypothesis import strategies as st
from schemathesis import GenerationMode
from schemathesis.checks import not_a_server_error
from schemathesis.specs.openapi.checks import (
    content_type_conformance,
    response_schema_conformance,
    status_code_conformance,
)

from tests.helpers import Service, ply_binary, sphere

EXAMPLES = 200  # per operation and mode
CHECKS = [not_a_server_error, status_code_conformance, content_type_conformance, response_schema_conformance]
CLOUD = ply_binary(sphere(300))


@pytest.fixture(scope="module")
def live(redis_server, tmp_path_factory):
    """The API, its schema, and a job that has ended (canceled): its event stream ends at once."""
    service = Service(redis_server.url, tmp_path_factory.mktemp("fuzz"), max_upload_bytes=256 * 1024)
    service.start_api()
    job = service.submit(CLOUD)["id"]
    assert httpx.delete(f"{service.url}/v1/jobs/{job}").status_code == 204
    yield schemathesis.openapi.from_url(service.url + "/openapi.json"), job
    service.stop()


@pytest.mark.parametrize("mode", [GenerationMode.POSITIVE, GenerationMode.NEGATIVE], ids=str)
def test_no_5xx_and_every_answer_as_documented(live, mode):
    schema, job = live
    operations = [result.ok() for result in schema.get_all_operations()]
    assert len(operations) > 10
    for operation in operations:
        if mode == GenerationMode.NEGATIVE and not (operation.path_parameters or operation.query or operation.body):
            continue  # nothing in the request to make invalid (GET /healthz...)
        cases = operation.as_strategy(generation_mode=mode)
        if "job_id" in operation.path:
            cases = st.one_of(cases, operation.as_strategy(generation_mode=mode, path_parameters={"job_id": job}))

        @hypothesis.given(case=cases, valid_cloud=st.booleans())
        @hypothesis.settings(
            max_examples=EXAMPLES,
            deadline=None,
            derandomize=True,
            database=None,
            phases=[hypothesis.Phase.generate],
            suppress_health_check=list(hypothesis.HealthCheck),
        )
        def call(case, valid_cloud):
            if valid_cloud and isinstance(case.body, dict) and "points" in case.body:
                case.body["points"] = CLOUD
            case.call_and_validate(checks=CHECKS, timeout=10)

        call()
