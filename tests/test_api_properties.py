"""Property-based tests of the service API from its own OpenAPI schema (schemathesis, in
process over ASGI): no request, however odd, gets a server error. The service's worker is
not started, so nothing queued ever moves a device; the event stream is left out (it
never ends by design)."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest
import schemathesis
from hypothesis import HealthCheck, given, settings

from rigctl.config import load_rig
from rigctl.service import RigService, create_app
from tests.mockproc import ROOT

# one worker runs the module, so its schema is loaded once
pytestmark = pytest.mark.xdist_group("api-properties")

TOKEN = "fuzz-token"
AUTH = {"Authorization": f"Bearer {TOKEN}"}


@pytest.fixture(scope="module")
def api_schema(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("api")
    rig = tmp / "rig.yaml"
    rig.write_text("name: fuzz-rig\nrecords: {directory: records}\n"
                   "devices:\n  head: {port: /dev/null/not-a-port}\n"
                   f"service: {{token: {TOKEN}}}\n")
    service = RigService(load_rig(rig))
    schema = schemathesis.openapi.from_asgi("/openapi.json", create_app(service))
    return schema.exclude(path="/events")


def _operations(schema):
    for result in schema.get_all_operations():
        yield result.ok()


@pytest.mark.timeout(300)
def test_no_request_gets_a_server_error(api_schema):
    """30 generated requests per operation (paths, queries and bodies from the schema, and
    schemathesis' edge cases); every answer is below 500."""
    seen = []
    for operation in _operations(api_schema):
        @given(case=operation.as_strategy())
        @settings(max_examples=30, deadline=None, database=None,
                  suppress_health_check=list(HealthCheck))
        def no_server_error(case):
            response = case.call(headers=AUTH)
            assert response.status_code < 500, (
                f"{case.method} {case.formatted_path} query={case.query} body={case.body!r}: "
                f"{response.status_code} {response.text[:300]}")

        no_server_error()
        seen.append(operation.label)
    assert len(seen) >= 10, seen  # every endpoint but the event stream was exercised


@pytest.fixture
def api(tmp_path):
    from fastapi.testclient import TestClient

    rig = tmp_path / "rig.yaml"
    rig.write_text("name: api-rig\nrecords: {directory: records}\n"
                   "devices:\n  head: {port: /dev/null/not-a-port}\n"
                   f"service: {{token: {TOKEN}}}\n")
    service = RigService(load_rig(rig))  # worker not started: nothing queued ever runs
    with TestClient(create_app(service)) as client:
        client.headers.update(AUTH)
        yield client, service, rig


def test_bounds_are_422_with_a_message(api):
    client, _, _ = api
    for url in ("/runs?limit=100000000000000000000000", "/runs?limit=0", "/runs?limit=-1",
                "/runs?procedure=DROP%20TABLE", "/calibrations/history?procedure=head-sweep",
                "/runs/x/captures/100000000000000000000"):
        response = client.get(url)
        assert response.status_code == 422, (url, response.status_code, response.text)
        assert response.json()["detail"], url
    assert client.get("/runs?limit=1000").status_code == 200
    # NaN and Infinity are not JSON, but Python's parser takes them: still a 422
    for body in ('{"procedure": NaN}', '{"procedure": "head-sweep", "params": {"pan_deg": '
                 '[Infinity]}}', '{"procedure": "head-sweep", "operator": -Infinity}'):
        response = client.post("/runs", content=body,
                               headers={"Content-Type": "application/json"})
        assert response.status_code == 422, (body, response.status_code, response.text)


def test_a_plan_past_the_soft_limits_is_refused_at_post_with_the_cli_text(api):
    client, service, rig = api
    bad = {"procedure": "head-sweep", "params": {"pan_deg": [500]}}
    response = client.post("/runs", json=bad)
    assert response.status_code == 422
    detail = response.json()["detail"]
    assert detail.startswith("plan refused before any motion:") and "head.pan" in detail
    cli = subprocess.run([sys.executable, "-m", "rigctl.cli", "run", "head-sweep", "--rig",
                          str(rig), "--param", "pan_deg=[500]", "--json"],
                         capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert cli.returncode == 2 and json.loads(cli.stdout)["error"] == detail
    for body, word in (({"procedure": "head-sweep", "params": {"pan_dg": [5]}}, "pan_dg"),
                       ({"procedure": "no-such-thing"}, "unknown procedure"),
                       ({"procedure": "arm-sweep"}, "devices.arm"),
                       ({"procedure": "head-sweep", "params": {"settle_s": "soon"}},
                        "settle_s")):
        response = client.post("/runs", json=body)
        assert response.status_code == 422 and word in json.dumps(response.json()), body
    # nothing was queued or recorded
    assert client.get("/runs").json() == [] and not service.queue
    ok = client.post("/runs", json={"procedure": "head-sweep", "params": {"pan_deg": [5]}})
    assert ok.status_code == 202 and len(service.queue) == 1


def test_parameters_the_planner_cannot_use_are_refused_not_crashed():
    """hand-eye with seed -1 raised a ValueError from numpy inside the planner (a traceback
    from the CLI, a 500 from the API); it is a refusal naming the procedure."""
    from rigctl.config import parse_rig
    from rigctl.errors import ConfigError
    from rigctl.runner import prepare_run

    config = parse_rig("devices:\n  arm: {host: 127.0.0.1}\n"
                       "  camera: {device: http://127.0.0.1:1/stream.mjpg}\n")
    with pytest.raises(ConfigError, match="hand-eye: cannot plan with these parameters"):
        prepare_run(config, "hand-eye", {"seed": -1})
