"""The documentation's reference covers the code: every CLI command, rig-file key,
world-file key, procedure parameter and API path, listed here from the code itself (not
from the generator), appears in the generated reference pages and in the site MkDocs
builds from them. A new command, key or path without a line in the reference fails here;
so does a rig-file or world-file key without a description.

The site is built with ``mkdocs build --strict`` (a dev dependency): outside CI the test
of the built site skips when MkDocs is missing; under ``CI=true`` it fails instead.
"""

from __future__ import annotations

import html
import importlib.util
import re
import subprocess
import sys
import types
import typing
from pathlib import Path

import pytest
from pydantic import BaseModel

from tests.needs import dev_dependency, missing

ROOT = Path(__file__).resolve().parents[1]
HOOK = ROOT / "docs" / "hooks" / "reference.py"


def _load_hook() -> types.ModuleType:
    spec = importlib.util.spec_from_file_location("rigctl_docs_reference", HOOK)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


# one worker runs the module, so the site is generated once
pytestmark = pytest.mark.xdist_group("docs-reference")


@pytest.fixture(scope="module")
def pages() -> dict[str, str]:
    """The generated reference pages (the service extra builds the API page)."""
    dev_dependency("fastapi")
    return _load_hook().generate()


# -- what the code has, listed independently of the generator ----------------------------


def cli_command_paths() -> list[str]:
    """Every leaf command of ``rigctl.cli:app``, as typed: ``rigctl sim up``."""
    import typer

    from rigctl.cli import app

    paths: list[str] = []

    def walk(command, path: tuple[str, ...]) -> None:
        if hasattr(command, "commands"):
            for name, sub in command.commands.items():
                walk(sub, (*path, name))
        else:
            paths.append(" ".join(("rigctl", *path)))

    walk(typer.main.get_command(app), ())
    return paths


def cli_options() -> list[tuple[str, str]]:
    """(command, option) for every option of every command."""
    import typer

    from rigctl.cli import app

    found: list[tuple[str, str]] = []

    def walk(command, path: tuple[str, ...]) -> None:
        if hasattr(command, "commands"):
            for name, sub in command.commands.items():
                walk(sub, (*path, name))
            return
        for param in command.params:
            if type(param).__name__.endswith("Option") and not param.hidden:
                found.extend((" ".join(("rigctl", *path)), opt) for opt in param.opts)

    walk(typer.main.get_command(app), ())
    return found


def _models_in(annotation) -> list[tuple[type[BaseModel], bool]]:
    """The pydantic models an annotation holds, each with whether it sits in a list."""
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return [(annotation, False)]
    origin, found = typing.get_origin(annotation), []
    for arg in typing.get_args(annotation):
        if origin is dict:
            continue  # a mapping of free names (procedures.<name>): no fixed keys
        for model, listed in _models_in(arg):
            found.append((model, listed or origin is list))
    return found


def model_keys(model: type[BaseModel], prefix: str = "") -> list[tuple[str, str | None]]:
    """(dotted key, description) of every field of ``model``, nested models included;
    an element of a list is ``key[]``. Fields excluded from dumps are not keys."""
    keys: list[tuple[str, str | None]] = []
    for name, field in model.model_fields.items():
        if field.exclude:
            continue
        key = prefix + name
        keys.append((key, field.description))
        for sub, listed in _models_in(field.annotation):
            keys += model_keys(sub, key + ("[]." if listed else "."))
    return list(dict.fromkeys(keys))


def rig_keys() -> list[tuple[str, str | None]]:
    from rigctl.config import RigConfig

    return model_keys(RigConfig)


def world_keys() -> list[tuple[str, str | None]]:
    from rigctl.mocks.world import WorldFile

    return model_keys(WorldFile)


def procedure_parameters() -> list[tuple[str, str]]:
    from rigctl.procedures import get_procedure, procedure_names

    return [(name, param) for name in procedure_names()
            for param in get_procedure(name).params_model.model_fields]


def api_paths() -> list[str]:
    """Every path of the service's OpenAPI document, from an app on a throwaway rig."""
    dev_dependency("fastapi")
    import tempfile

    from rigctl.config import parse_rig
    from rigctl.service import RigService, create_app

    with tempfile.TemporaryDirectory() as tmp:
        config = parse_rig(f"name: t\nrecords: {{directory: '{tmp}'}}\n")
        return list(create_app(RigService(config)).openapi()["paths"])


# -- the generated Markdown ---------------------------------------------------------------


def test_the_code_has_what_the_reference_must_cover():
    """The listings above find the code's commands, keys and paths (a broken listing
    would make every other test here pass vacuously)."""
    commands = cli_command_paths()
    assert {"rigctl run", "rigctl sim up", "rigctl head scan", "rigctl export"} <= set(commands)
    assert len(commands) >= 25
    keys = dict(rig_keys())
    assert {"devices.head.port", "devices.arm.joint_limits_deg", "service.token",
            "service.schedules[].cron", "service.drift.focal_pct"} <= set(keys)
    assert "source_text" not in keys
    assert "arm.factory_errors.theta_deg" in dict(world_keys())
    assert len(procedure_parameters()) >= 50


def test_every_cli_command_and_option_is_in_the_reference(pages):
    cli = pages["reference/cli.md"]
    missing_commands = [c for c in cli_command_paths() if f"### `{c}`" not in cli]
    assert not missing_commands, f"commands without a reference section: {missing_commands}"
    sections = dict(re.findall(r"### `(rigctl[^`]*)`\n(.*?)(?=\n### |\n## |\Z)", cli, re.S))
    missing_options = [(c, o) for c, o in cli_options() if f"`{o}`" not in sections[c]]
    assert not missing_options, f"options missing from their command's section: {missing_options}"


def test_every_rig_file_key_is_in_the_reference_with_its_meaning(pages):
    page = pages["reference/rig-file.md"]
    keys = rig_keys()
    absent = [k for k, _ in keys if f"| `{k}` |" not in page]
    assert not absent, f"rig-file keys missing from the reference: {absent}"
    undescribed = [k for k, d in keys if not d]
    assert not undescribed, ("rig-file keys without Field(description=...) in "
                             f"rigctl/config.py: {undescribed}")


def test_every_world_file_key_is_in_the_reference_with_its_meaning(pages):
    page = pages["reference/world-file.md"]
    keys = world_keys()
    absent = [k for k, _ in keys if f"| `{k}` |" not in page]
    assert not absent, f"world-file keys missing from the reference: {absent}"
    undescribed = [k for k, d in keys if not d]
    assert not undescribed, ("world-file keys without Field(description=...) in "
                             f"rigctl/mocks/world.py: {undescribed}")


def test_every_procedure_and_parameter_is_in_the_reference(pages):
    page = pages["reference/procedures.md"]
    results = (ROOT / "docs" / "reference" / "results.md").read_text()
    sections = dict(re.findall(r"## `([a-z-]+)`\n(.*?)(?=\n## |\Z)", page, re.S))
    absent = [(n, p) for n, p in procedure_parameters() if f"| `{p}` |" not in sections.get(n, "")]
    assert not absent, f"procedure parameters missing from the reference: {absent}"
    no_results = [n for n, _ in procedure_parameters() if f"## `{n}`" not in results]
    assert not no_results, f"procedures without a section in docs/reference/results.md: " \
                           f"{sorted(set(no_results))}"


def test_every_api_path_is_in_the_reference(pages):
    page = pages["reference/http-api.md"]
    paths = api_paths()
    assert {"/runs", "/runs/{run_id}/abort", "/calibrations/{run_id}/accept"} <= set(paths)
    absent = [p for p in paths if f"| `{p}` |" not in page]
    assert not absent, f"API paths missing from the reference: {absent}"


def test_hardware_tables_cover_every_model(pages):
    from rigctl.drivers.dynamixel_models import MODELS as SERVOS
    from rigctl.hardware.ur_models import MODELS as ARMS

    page = pages["reference/hardware.md"]
    absent = [m for m in [*ARMS, *(s.name for s in SERVOS)] if f"| `{m}` |" not in page]
    assert not absent, f"models missing from the hardware reference: {absent}"
    assert all(s.source in page for s in SERVOS)  # each row links its e-Manual page


# -- the built site -----------------------------------------------------------------------


def _text(page: Path) -> str:
    return html.unescape(re.sub(r"<[^>]+>", "", page.read_text()))


@pytest.fixture(scope="module")
def site(tmp_path_factory) -> Path:
    """The site, built with ``mkdocs build --strict`` (broken links fail the build)."""
    if importlib.util.find_spec("mkdocs") is None or \
            importlib.util.find_spec("material") is None:
        missing("MkDocs with the Material theme (mkdocs, mkdocs-material)",
                "pip install -e '.[dev]'")
    out = tmp_path_factory.mktemp("site")
    env = {"PYTHONPATH": str(ROOT), "NO_MKDOCS_2_WARNING": "1", "PATH": "/usr/bin:/bin"}
    done = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--config-file",
                           str(ROOT / "mkdocs.yml"), "--site-dir", str(out)],
                          capture_output=True, text=True, timeout=600, env=env, check=False)
    assert done.returncode == 0, f"mkdocs build --strict failed:\n{done.stderr[-4000:]}"
    return out


def test_the_built_site_holds_every_command_key_and_path(site):
    cli = _text(site / "reference" / "cli" / "index.html")
    rig = _text(site / "reference" / "rig-file" / "index.html")
    world = _text(site / "reference" / "world-file" / "index.html")
    api = _text(site / "reference" / "http-api" / "index.html")
    assert not [c for c in cli_command_paths() if c not in cli]
    assert not [k for k, _ in rig_keys() if k not in rig]
    assert not [k for k, _ in world_keys() if k not in world]
    assert not [p for p in api_paths() if p not in api]
    for page in ("tutorial/simulated-rig", "tutorial/first-real-rig", "how-to/troubleshooting",
                 "explanation/active-camera", "reference/results"):
        assert (site / page / "index.html").stat().st_size > 0
