"""The bearer token guards every endpoint that changes anything: each one, found from the
app's own routes (not a list kept here), refuses a request without the token or with a
wrong one, before any work; the token can come from RIGCTL_TOKEN."""

from __future__ import annotations

import re

import pytest
from fastapi.testclient import TestClient

from rigctl.config import load_rig
from rigctl.service import RigService, create_app

MUTATING = {"POST", "PUT", "PATCH", "DELETE"}


def _service(tmp_path, token_line: str) -> RigService:
    rig = tmp_path / "auth-rig.yaml"
    rig.write_text("name: auth-rig\nrecords: {directory: records}\n"
                   "devices:\n  head: {port: /dev/null/not-a-port}\n" + token_line)
    return RigService(load_rig(rig))


def _mutating_routes(app) -> list[tuple[str, str]]:
    """(method, path) of every mutating endpoint in the app's OpenAPI schema, path
    parameters filled with a name."""
    found = []
    for path, operations in app.openapi()["paths"].items():
        for method in operations:
            if method.upper() in MUTATING:
                found.append((method.upper(), re.sub(r"\{[^}]+\}", "run-x", path)))
    return found


def _refused_without_token(api, routes, good: str) -> None:
    for method, path in routes:
        for headers in ({}, {"Authorization": "Bearer wrong"},
                        {"Authorization": good}):  # the bare token, no "Bearer "
            answer = api.request(method, path, json={}, headers=headers)
            assert answer.status_code in (401, 403), (method, path, headers,
                                                      answer.status_code, answer.text)


def test_every_mutating_endpoint_refuses_a_request_without_the_token(tmp_path):
    service = _service(tmp_path, "service: {token: units-token}\n")
    app = create_app(service)
    routes = _mutating_routes(app)
    # the app has them: runs, their abort, accept and reject at least
    assert {("POST", "/runs"), ("POST", "/runs/run-x/abort")} <= set(routes), routes
    assert len(routes) >= 4, routes
    with TestClient(app) as api:
        _refused_without_token(api, routes, "units-token")
        assert service.queue == type(service.queue)()  # nothing was queued
        # and the token opens them: a run is queued
        ok = api.post("/runs", json={"procedure": "head-sweep",
                                     "params": {"pan_deg": [0], "tilt_deg": [0]}},
                      headers={"Authorization": "Bearer units-token"})
        assert ok.status_code in (200, 201, 202), ok.text


def test_the_token_can_come_from_rigctl_token(tmp_path, monkeypatch):
    monkeypatch.setenv("RIGCTL_TOKEN", "from-the-env")
    service = _service(tmp_path, "")
    app = create_app(service)
    with TestClient(app) as api:
        _refused_without_token(api, _mutating_routes(app), "from-the-env")
        ok = api.post("/runs", json={"procedure": "head-sweep",
                                     "params": {"pan_deg": [0], "tilt_deg": [0]}},
                      headers={"Authorization": "Bearer from-the-env"})
        assert ok.status_code in (200, 201, 202), ok.text


@pytest.mark.parametrize("token_line", ["service: {token: units-token}\n", ""])
def test_reading_needs_no_token(tmp_path, token_line):
    service = _service(tmp_path, token_line)
    with TestClient(create_app(service)) as api:
        assert api.get("/health").status_code == 200
        assert api.get("/runs").status_code == 200
