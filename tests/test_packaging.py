"""Installable like a library: the build requirements and extras in pyproject.toml, the
one message naming a missing extra (CLI, runner), and the provenance every run's
versions.json records (exact version, commit, dirty tree). The wheel itself, installed
outside the checkout, is `.ci/wheel-check`'s."""

from __future__ import annotations

import subprocess
import sys
import tomllib

import pytest

from rigctl.config import parse_rig
from rigctl.extras import EXTRAS, MissingExtraError, extra_of, missing_extra, require
from rigctl.records import _built_provenance, software_provenance
from rigctl.runner import Runner
from tests.mockproc import ROOT

PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())


def test_build_requirements_and_extras():
    requires = PYPROJECT["build-system"]["requires"]
    # `license = "MIT"` (an SPDX string) needs setuptools 77 or later
    assert "setuptools>=77" in requires and any(r.startswith("setuptools-scm") for r in requires)
    project = PYPROJECT["project"]
    assert project["license"] == "MIT" and "version" in project["dynamic"]
    assert "version" not in project
    extras = project["optional-dependencies"]
    assert set(extras) == {"service", "arm", "plots", "postgres", "dev"}
    core = " ".join(project["dependencies"]).lower()
    for optional in ("fastapi", "uvicorn", "apscheduler", "jinja2", "ur-rtde", "matplotlib",
                     "psycopg"):
        assert optional not in core, optional
    assert extras["dev"][0] == "rigctl[service,arm,plots,postgres]"
    assert any(r.startswith("build") for r in extras["dev"])
    # each extra's modules (what rigctl.extras checks) are what that extra installs
    installs = {"service": "fastapi", "arm": "ur-rtde", "plots": "matplotlib",
                "postgres": "psycopg"}
    for extra, package in installs.items():
        assert any(r.lower().startswith(package) for r in extras[extra]), extra
        assert EXTRAS[extra]
    assert (ROOT / "LICENSE").read_text().startswith("MIT License")
    assert "## Unreleased" in (ROOT / "CHANGELOG.md").read_text()


def test_missing_extra_names_what_to_install():
    assert extra_of("fastapi.responses") == "service"
    assert extra_of("rtde_control") == "arm" and extra_of("matplotlib.pyplot") == "plots"
    assert extra_of("numpy") is None and missing_extra(ValueError("x")) is None
    exc = missing_extra(ModuleNotFoundError("No module named 'psycopg'", name="psycopg"))
    assert isinstance(exc, MissingExtraError) and "pip install 'rigctl[postgres]'" in str(exc)
    assert missing_extra(ModuleNotFoundError("no", name="numpy")) is None  # a bug stays one
    for extra in EXTRAS:  # the dev extra installs them all
        require(extra)


def _cli_without(module: str, *args: str) -> subprocess.CompletedProcess:
    """`rigctl ARGS` in a Python where ``module`` cannot be imported."""
    code = (f"import sys; sys.modules[{module!r}] = None; from rigctl.cli import app; "
            f"sys.argv = ['rigctl', *{list(args)!r}]; app()")
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          cwd=ROOT, timeout=120)


@pytest.mark.parametrize(("module", "extra", "args"), [
    ("fastapi", "service", ("serve", "--rig", "examples/rig.example.yaml")),
    ("rtde_control", "arm", ("demo", "--quick")),
    ("matplotlib", "plots", ("bench", "active", "--trials", "1", "--plot", "/dev/null")),
])
def test_a_command_without_its_extra_says_which(module, extra, args):
    done = _cli_without(module, *args)
    assert done.returncode == 2, done.stderr[-2000:]
    assert f"pip install 'rigctl[{extra}]'" in done.stderr, done.stderr[-2000:]
    assert "Traceback" not in done.stderr


def test_a_run_without_the_arm_extra_is_recorded_naming_it(tmp_path, monkeypatch):
    """The runner records a run whose arm client is not installed as failed, naming the
    extra, before any device is reached."""
    config = parse_rig("name: no-arm\nrecords: {directory: records}\n"
                       "devices:\n  arm: {host: 127.0.0.1}\n", path=tmp_path / "rig.yaml")
    monkeypatch.setitem(sys.modules, "rtde_control", None)
    monkeypatch.setitem(sys.modules, "rtde_receive", None)
    outcome = Runner(config, show_progress=False).run("arm-sweep", {})
    assert outcome.status == "failed"
    assert "pip install 'rigctl[arm]'" in outcome.reason


def test_provenance_of_this_checkout():
    """From a git checkout: the commit git reports and whether tracked files differ."""
    prov = software_provenance()
    head = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "HEAD"], capture_output=True,
                          text=True, check=True).stdout.strip()
    status = subprocess.run(["git", "-C", str(ROOT), "status", "--porcelain",
                             "--untracked-files=no"], capture_output=True, text=True,
                            check=True).stdout.strip()
    assert prov["from"] == "git checkout"
    assert prov["commit"] == head and prov["dirty"] is bool(status)
    assert prov["version"] and prov["version"] != "0.0.0+unknown"


@pytest.mark.parametrize(("version", "commit_id", "commit", "dirty"), [
    ("0.1.dev263+g7a42ab6.d20260126", None, "7a42ab6", True),  # setuptools-scm, dirty
    ("0.1.dev263+g7a42ab6", None, "7a42ab6", False),
    ("0.2.0", "1b2c3d4", "1b2c3d4", False),  # on a tag: the version file's commit
    ("0.2.1.dev0+d20260126", "1b2c3d4", "1b2c3d4", True),  # on a tag, dirty
    ("0.0.0+unknown", None, None, None),  # built without git metadata
])
def test_provenance_of_a_build(version, commit_id, commit, dirty):
    prov = _built_provenance(version, commit_id)
    assert (prov["version"], prov["commit"], prov["dirty"]) == (version, commit, dirty)
    assert prov["from"] == "build"
