"""Who may read and change what on the service (in process, no worker: nothing moves),
and the token's redaction from everything a run writes. The real service on the
simulated rig, grepped whole for its token, is tests/test_token_leak.py."""

from __future__ import annotations

import json
import logging
import sys

import pytest
from fastapi.testclient import TestClient

import rigctl.console
from rigctl import service as service_module
from rigctl.config import load_rig, parse_rig
from rigctl.errors import ConfigError
from rigctl.records import RunDirectory
from rigctl.redaction import REDACTED, RedactingFormatter, redact_rig_text
from rigctl.runner import _write_versions
from rigctl.service import Access, RigService, check_bind, create_app

TOKEN = "access-test-token-7f3a"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
# every read: the runs, a capture, the devices' configuration, the console, the events
READS = ("/runs", "/runs/nope", "/runs/nope/captures/0", "/rig", "/procedures",
         "/calibrations/latest", "/calibrations/history", "/console/", "/console/runs",
         "/console/history", "/console/start", "/console/runs/nope", "/events", "/")


def _client(tmp_path, service_yaml: str, host: str | None = None) -> TestClient:
    rig = tmp_path / "rig.yaml"
    rig.write_text("name: access-rig\nrecords: {directory: records}\n"
                   f"devices:\n  head: {{port: /dev/null/not-a-port}}\nservice: {service_yaml}\n")
    return TestClient(create_app(RigService(load_rig(rig)), host=host))


@pytest.mark.parametrize(("service_yaml", "host"), [
    (f"{{token: {TOKEN}, public_read: false}}", None),  # loopback, reads closed
    (f"{{token: {TOKEN}, bind: 0.0.0.0}}", None),  # beyond loopback: closed by default
    (f"{{token: {TOKEN}}}", "192.0.2.10"),  # loopback in the file, served elsewhere
])
def test_reads_need_the_token_when_not_public(tmp_path, service_yaml, host):
    with _client(tmp_path, service_yaml, host) as api:
        for path in READS:
            r = api.get(path, follow_redirects=False)
            assert r.status_code == 401, (path, r.status_code)
            if path.startswith("/console") or path == "/":
                assert "Token needed" in r.text and 'action="/console/login"' in r.text
            else:
                assert r.json()["detail"] == "missing or wrong bearer token"
                assert r.headers["www-authenticate"] == "Bearer"
        for path in ("/runs", "/rig", "/procedures", "/console/", "/console/history"):
            assert api.get(path, headers=AUTH).status_code == 200, path
        assert api.get("/runs", headers={"Authorization": f"Bearer {TOKEN}x"}).status_code \
            == 401
        assert api.get("/health").status_code == 200
        # changes need the token as before
        assert api.post("/runs", json={"procedure": "head-sweep"}).status_code == 401


def test_loopback_reads_are_public_by_default(tmp_path):
    with _client(tmp_path, f"{{token: {TOKEN}}}") as api:
        for path in ("/runs", "/rig", "/procedures", "/calibrations/history", "/console/",
                     "/console/runs", "/console/history", "/console/start"):
            assert api.get(path).status_code == 200, path
        assert api.get("/", follow_redirects=False).status_code == 307
        assert api.post("/runs", json={"procedure": "head-sweep"}).status_code == 401


def test_the_console_signs_in_once(tmp_path):
    with _client(tmp_path, f"{{token: {TOKEN}, public_read: false}}") as api:
        form = api.get("/console/login?next=/console/history")
        assert form.status_code == 200 and 'value="/console/history"' in form.text
        wrong = api.post("/console/login", data={"token": "guess", "next": "/console/"})
        assert wrong.status_code == 401 and "wrong token" in wrong.text
        assert "rigctl_session" not in api.cookies
        # never sent elsewhere after signing in
        off = api.post("/console/login", data={"token": TOKEN, "next": "//evil.example/x"},
                       follow_redirects=False)
        assert off.status_code == 303 and off.headers["location"] == "/console/"
        signed = api.post("/console/login", data={"token": TOKEN, "next": "/console/runs"},
                          follow_redirects=False)
        assert signed.headers["location"] == "/console/runs"
        cookie = signed.headers["set-cookie"].lower()
        assert "httponly" in cookie and "samesite=strict" in cookie and TOKEN not in cookie
        for path in ("/console/", "/console/runs", "/runs", "/rig"):
            assert api.get(path).status_code == 200, path
        # a forged cookie is refused; signing out forgets the session
        api.cookies.clear()
        api.cookies.set("rigctl_session", "0" * 64)
        assert api.get("/runs").status_code == 401
        api.cookies.clear()
        api.post("/console/login", data={"token": TOKEN})
        assert api.get("/runs").status_code == 200
        api.post("/console/logout")
        assert api.get("/runs").status_code == 401


def test_tokens_are_compared_in_constant_time(monkeypatch):
    calls = []
    real = service_module.hmac.compare_digest

    def spy(a, b):
        calls.append((a, b))
        return real(a, b)

    monkeypatch.setattr(service_module.hmac, "compare_digest", spy)
    access = Access(TOKEN, public_read=False)
    assert access.token_matches(TOKEN) and not access.token_matches(TOKEN + "x")
    assert not access.token_matches("")
    assert len(calls) == 3 and all(isinstance(a, bytes) for a, _ in calls)
    assert TOKEN not in access.session  # the cookie is a keyed hash, not the token
    assert not Access(None, public_read=False).token_matches("anything")


def test_closed_reads_need_a_token(tmp_path):
    config = parse_rig("service: {public_read: false}\n")
    with pytest.raises(ConfigError, match="public_read: false needs a bearer token"):
        check_bind(config, "127.0.0.1")
    with pytest.raises(ConfigError, match="binding beyond loopback requires"):
        check_bind(parse_rig("service: {bind: 0.0.0.0}\n"), "0.0.0.0")
    check_bind(parse_rig(f"service: {{public_read: true, token: {TOKEN}}}\n"), "0.0.0.0")
    assert parse_rig("service: {bind: 0.0.0.0}\n").service.reads_public() is False
    assert parse_rig("service: {bind: 127.0.0.2}\n").service.reads_public() is True
    assert parse_rig("{}").service.reads_public("::1") is True


RIG = """name: redacted-rig  # {token} in a comment
records: {{directory: records}}
service:
  bind: 127.0.0.1
  token: {value}
  port: 8765
"""


@pytest.mark.parametrize("value", [
    TOKEN, f"'{TOKEN}'", f'"{TOKEN}"', f"|\n    {TOKEN}", f">-\n    {TOKEN}",
])
def test_the_rig_file_copy_has_the_token_redacted(value):
    text = RIG.format(token=TOKEN, value=value)
    assert parse_rig(text).service.token.strip() == TOKEN
    copy = redact_rig_text(text, [TOKEN])
    assert TOKEN not in copy
    config = parse_rig(copy)  # the copy loads, with the same rig
    assert config.service.token == REDACTED and config.service.port == 8765
    assert config.name == "redacted-rig" and copy.startswith("name: redacted-rig  # ")
    assert copy.splitlines()[-1] == "  port: 8765"


def test_a_short_token_is_redacted_where_the_file_holds_it():
    text = "service: {token: ab12, bind: 127.0.0.1}\nname: ab12-rig\n"
    copy = redact_rig_text(text, ["ab12"])
    assert parse_rig(copy).service.token == REDACTED
    assert parse_rig(copy).name == "ab12-rig"  # too short to replace everywhere
    assert redact_rig_text("name: x\n", [TOKEN]) == "name: x\n"


def test_versions_and_log_never_carry_the_token(tmp_path):
    run = RunDirectory.create(tmp_path, "run-1")

    class Device:
        def describe(self):
            return {"model": "stand-in", "url": f"http://user:{TOKEN}@host/", TOKEN: 1}

    _write_versions(run, {"camera": Device()}, [TOKEN])
    text = (run.path / "versions.json").read_text()
    assert TOKEN not in text
    described = json.loads(text)["devices"]["camera"]
    assert described["url"] == f"http://user:{REDACTED}@host/" and described[REDACTED] == 1

    handler = logging.FileHandler(run.path / "run.log")
    handler.setFormatter(RedactingFormatter("%(levelname)s %(message)s", [TOKEN]))
    logger = logging.getLogger("rigctl.test-redaction")
    logger.addHandler(handler)
    try:
        logger.warning("header %s", f"Bearer {TOKEN}")
        try:
            raise ValueError(TOKEN)
        except ValueError:
            logger.exception("failed")
    finally:
        logger.removeHandler(handler)
        handler.close()
    log = (run.path / "run.log").read_text()
    assert TOKEN not in log and f"header Bearer {REDACTED}" in log
    assert f"ValueError: {REDACTED}" in log


def test_figures_without_the_plots_extra_say_which(tmp_path, monkeypatch):
    """The service runs without matplotlib; its figures answer 404 naming the extra."""
    monkeypatch.delitem(sys.modules, "rigctl.console.plots", raising=False)
    monkeypatch.delattr(rigctl.console, "plots", raising=False)
    monkeypatch.setitem(sys.modules, "matplotlib", None)
    # a worker that ran other tests first has matplotlib's submodules loaded, and an
    # import of one of those would not look at the package's entry: hide them too
    for name in [m for m in sys.modules if m.startswith("matplotlib.")]:
        monkeypatch.delitem(sys.modules, name)
    with _client(tmp_path, f"{{token: {TOKEN}}}") as api:
        r = api.get("/console/history/active-camera.png")
        assert r.status_code == 404 and "pip install 'rigctl[plots]'" in r.json()["detail"]
        assert api.get("/console/history").status_code == 200
