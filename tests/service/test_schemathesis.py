"""A bounded schemathesis run of the API against its own OpenAPI document, on the server `rafd-serve` runs (the
FakeRunner app behind service/http/server.py): no input may give a 5xx, and every answer must match the schema of its
status (unknown status codes, content types and answer shapes are failures). Issue 34 asked for it after finding 6
(non-ASCII base64 answered 500). Each operation gets `EXAMPLES` generated cases of valid data and as many of
invalid data (schemathesis's positive and negative modes), derandomised so a run repeats.

Driven through hypothesis directly (schemathesis's own pytest plugin does not work with this pytest). A longer run
of the same checks, with its figures, is in docs/performance.md ("Under hostile load").
"""

from __future__ import annotations

import pytest

schemathesis = pytest.importorskip("schemathesis", reason="schemathesis is in the dev extra")
import httpx  # noqa: E402
from hypothesis import HealthCheck, given, settings  # noqa: E402  (hypothesis comes with schemathesis)
from hypothesis.errors import Unsatisfiable  # noqa: E402
from schemathesis.generation.modes import GenerationMode  # noqa: E402
from schemathesis.specs.openapi.checks import (  # noqa: E402
    content_type_conformance,
    response_schema_conformance,
    status_code_conformance,
)

from service.app import create_app  # noqa: E402
from service.settings import Settings  # noqa: E402
from tests.utils.fake_runner import FakeRunner  # noqa: E402
from tests.utils.service_testing import FakeOdometry, serve_in_thread, wait_ready  # noqa: E402

pytestmark = [pytest.mark.network, pytest.mark.slow]

EXAMPLES = 25
CHECKS = [
    schemathesis.checks.not_a_server_error,
    status_code_conformance,
    content_type_conformance,
    response_schema_conformance,
]


def run_operation(operation, mode: GenerationMode, examples: int, calls: list[int]) -> None:
    @given(case=operation.as_strategy(generation_mode=mode))
    @settings(max_examples=examples, deadline=None, suppress_health_check=list(HealthCheck), derandomize=True)
    def check(case) -> None:
        response = case.call_and_validate(checks=CHECKS)
        calls.append(response.status_code)

    try:
        check()
    except Unsatisfiable:  # no invalid input exists for an operation without parameters or body
        assert mode is GenerationMode.NEGATIVE and not operation.body and not operation.path_parameters


def test_no_input_gives_a_5xx_or_an_answer_outside_the_schema():
    # No refusal penalty: the run sends refused requests back to back on purpose.
    app = create_app(Settings(threads=1, refusal_penalty_s=0.0), runner=FakeRunner(), odometry=FakeOdometry())
    calls: list[int] = []
    with serve_in_thread(app) as url:
        with httpx.Client(base_url=url) as http:
            wait_ready(http)
        schema = schemathesis.openapi.from_url(f"{url}/openapi.json")
        operations = [result.ok() for result in schema.get_all_operations()]
        for operation in operations:
            for mode in (GenerationMode.POSITIVE, GenerationMode.NEGATIVE):
                run_operation(operation, mode, EXAMPLES, calls)
    assert len(operations) == 8
    assert len(calls) > 100 and max(calls) < 500
