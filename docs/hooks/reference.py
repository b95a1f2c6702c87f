"""The reference pages, generated from the code every time the site is built.

An MkDocs hook (``hooks:`` in ``mkdocs.yml``): ``on_files`` adds the pages of ``PAGES``
to the site as generated files, so that they never go stale as commands, rig-file keys,
world-file keys, API paths, procedures' parameters and hardware tables change. Each page
comes from the code itself:

- the CLI from the typer app ``rigctl.cli:app`` (``typer.main.get_command``, walked as
  click's command tree);
- the rig file from pydantic's JSON schema of ``rigctl.config.RigConfig``;
- the world file from that of ``rigctl.mocks.world.WorldFile`` (and the prose of
  ``rigctl/mocks/worlds/README.md``);
- the HTTP API from the FastAPI app's OpenAPI (``rigctl.service.create_app``);
- procedures and their parameters from ``rigctl.procedures`` and each one's
  ``params_model``;
- the hardware tables from ``rigctl.hardware.ur_models`` and
  ``rigctl.drivers.dynamixel_models`` with the sources their docstrings cite.

``tests/test_docs_reference.py`` imports ``generate()`` and checks that every command,
key and path is in it, and in the built site.
"""

from __future__ import annotations

import inspect
import json
import re
import sys
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:  # the rigctl of this tree, not of another checkout
    sys.path.insert(0, str(ROOT))

GENERATED_NOTE = ("<!-- generated from the code by docs/hooks/reference.py at build time; "
                  "do not edit -->\n")


def _cell(text: Any) -> str:
    """Text fit for one Markdown table cell."""
    return re.sub(r"\s+", " ", str(text if text is not None else "")).replace("|", "\\|").strip()


def _code(text: Any) -> str:
    return f"`{text}`" if text not in (None, "") else ""


# -- the command line -------------------------------------------------------------------

# commands that hand their arguments to a stand-in's own argparse parser
ARGPARSE_COMMANDS = {("mock", "head"): "rigctl.mocks.dynamixel_bus",
                     ("mock", "arm"): "rigctl.mocks.ur_controller"}


def cli_commands() -> list[tuple[tuple[str, ...], Any]]:
    """Every command of ``rigctl`` (groups left out) as (path, click command), in the
    order the app declares them."""
    import typer

    from rigctl.cli import app

    found: list[tuple[tuple[str, ...], Any]] = []

    def walk(command: Any, path: tuple[str, ...]) -> None:
        subcommands = getattr(command, "commands", None)
        if subcommands is None:
            found.append((path, command))
            return
        for name, sub in subcommands.items():
            walk(sub, (*path, name))

    walk(typer.main.get_command(app), ())
    return found


def cli_groups() -> dict[tuple[str, ...], str]:
    """The help of each command group (``rigctl head``, ``rigctl sim``, ...)."""
    import typer

    from rigctl.cli import app

    groups: dict[tuple[str, ...], str] = {}

    def walk(command: Any, path: tuple[str, ...]) -> None:
        subcommands = getattr(command, "commands", None)
        if subcommands is None:
            return
        groups[path] = inspect.cleandoc(command.help or "")
        for name, sub in subcommands.items():
            walk(sub, (*path, name))

    walk(typer.main.get_command(app), ())
    return groups


def _annotation(param: Any) -> str:
    descriptor = getattr(param, "type_descriptor", None)
    annotation = getattr(descriptor, "annotation", None)
    if annotation is None:
        return ""
    if isinstance(annotation, type):
        return annotation.__name__
    return str(annotation).replace("pathlib.", "").replace("typing.", "")


def _param_row(param: Any) -> str:
    is_option = type(param).__name__.endswith("Option")
    names = ", ".join(_code(o) for o in [*param.opts, *param.secondary_opts]) if is_option \
        else _code(param.name.upper())
    default = param.default
    if param.required:
        shown = "required"
    elif getattr(param, "is_flag", False) and default is False:
        shown = "off"
    elif default in (None, [], ()):
        shown = ""
    else:
        shown = _code(default)
    bounds = [f"{k} {v}" for k, v in (("min", param.min), ("max", param.max)) if v is not None]
    kind = _annotation(param) + (f" ({', '.join(bounds)})" if bounds else "")
    repeat = " Repeatable." if getattr(param, "multiple", False) else ""
    return (f"| {names} | {_cell(kind)} | {_cell(shown)} | "
            f"{_cell((getattr(param, 'help', None) or '') + repeat)} |")


def _command_section(path: tuple[str, ...], command: Any) -> list[str]:
    full = " ".join(("rigctl", *path))
    params = [p for p in command.params if not getattr(p, "hidden", False)]
    args = " ".join(p.name.upper() if p.required else f"[{p.name.upper()}]"
                    for p in params if not type(p).__name__.endswith("Option"))
    lines = [f"### `{full}`", "", inspect.cleandoc(command.help or ""),
             "", "```", f"{full} [OPTIONS] {args}".rstrip(), "```", ""]
    if params:
        lines += ["| option or argument | type | default | meaning |", "|---|---|---|---|"]
        lines += [_param_row(p) for p in params]
        lines.append("")
    module = ARGPARSE_COMMANDS.get(path)
    if module is not None:
        from importlib import import_module

        parser = import_module(module).build_parser()
        lines += [f"`{full}` passes its arguments to the stand-in (`{module}`):", "",
                  "```", parser.format_help().rstrip(), "```", ""]
    return lines


def cli_page() -> str:
    """The CLI reference: every command with its options, arguments and help."""
    groups = cli_groups()
    lines = [GENERATED_NOTE, "# Command line", "",
             inspect.cleandoc(groups.get((), "")), "",
             "`--json` prints machine-readable output on stdout and nothing else (progress "
             "goes to stderr). Exit codes: 0 success, 1 run failed, 2 refused before "
             "anything moved (bad rig file, bad parameter, soft-limit violation, rig busy, "
             "a missing extra), 3 aborted. `rigctl --version` prints the version.", ""]
    current: tuple[str, ...] | None = None
    for path, command in cli_commands():
        group = path[:-1]
        if group != current:
            current = group
            title = " ".join(("rigctl", *group)) if group else "rigctl"
            lines += [f"## `{title}`", "", groups.get(group, ""), ""]
        lines += _command_section(path, command)
    return "\n".join(lines)


# -- schemas (rig file, world file, procedures' parameters) -----------------------------


def _resolve(node: dict, defs: dict) -> dict:
    ref = node.get("$ref")
    if ref is None and len(node.get("allOf", [])) == 1:
        ref = node["allOf"][0].get("$ref")
    return defs[ref.rsplit("/", 1)[-1]] if ref else node


def _variants(node: dict, defs: dict) -> list[dict]:
    return [_resolve(v, defs) for v in node.get("anyOf", [node])]


def _type_name(node: dict, defs: dict) -> str:
    names = []
    for v in node.get("anyOf", [node]):
        if "$ref" in v or "allOf" in v:
            names.append("mapping")
        elif "enum" in v:
            names.append(" \\| ".join(json.dumps(e) for e in v["enum"]))
        elif "const" in v:
            names.append(json.dumps(v["const"]))
        elif v.get("type") == "array":
            names.append(f"list of {_type_name(v.get('items', {}), defs) or 'values'}")
        elif v.get("type") == "object":
            names.append("mapping")
        elif "type" in v:
            names.append({"number": "number", "integer": "integer", "string": "string",
                          "boolean": "boolean", "null": "null"}.get(v["type"], v["type"]))
    return " or ".join(dict.fromkeys(names))


BOUNDS = (("minimum", ">="), ("exclusiveMinimum", ">"), ("maximum", "<="),
          ("exclusiveMaximum", "<"), ("minLength", "length >="), ("maxLength", "length <="),
          ("pattern", "matches"))


def _constraints(node: dict) -> str:
    found = []
    for v in node.get("anyOf", [node]):
        found += [f"{word} {_code(v[key])}" for key, word in BOUNDS if key in v]
    return ", ".join(found)


def _default(node: dict) -> str:
    if "default" not in node:
        return ""
    value = node["default"]
    if isinstance(value, dict | list) and len(json.dumps(value)) > 60:
        return "see below" if isinstance(value, dict) else _code(json.dumps(value)[:57] + "...")
    return _code(json.dumps(value))


def schema_rows(schema: dict, prefix: str = "", skip: tuple[str, ...] = ()
                ) -> Iterator[tuple[str, dict, bool]]:
    """(dotted key, property schema, required) for every key of a JSON schema, depth
    first; a list of mappings is ``key[].child``, a mapping of anything ``key.<name>``."""
    defs = schema.get("$defs", {})

    def walk(node: dict, prefix: str) -> Iterator[tuple[str, dict, bool]]:
        node = _resolve(node, defs)
        required = set(node.get("required", []))
        for name, prop in node.get("properties", {}).items():
            if name in skip and not prefix:
                continue
            key = f"{prefix}{name}"
            yield key, prop, name in required
            for variant in _variants(prop, defs):
                if variant.get("properties"):
                    yield from walk(variant, key + ".")
                elif variant.get("type") == "array":
                    items = _resolve(variant.get("items", {}), defs)
                    if items.get("properties"):
                        yield from walk(items, key + "[].")

    yield from walk(schema, prefix)


def _description(prop: dict, defs: dict) -> str:
    text = prop.get("description")
    if not text:
        text = next((v.get("description") for v in _variants(prop, defs)
                     if v.get("description")), "")
    return text or ""


def schema_table(schema: dict, prefix: str = "", skip: tuple[str, ...] = (),
                 links: dict[str, str] | None = None) -> list[str]:
    """A table of every key of ``schema``: key, type, default, bounds, meaning."""
    defs = schema.get("$defs", {})
    lines = ["| key | type | default | bounds | meaning |", "|---|---|---|---|---|"]
    for key, prop, required in schema_rows(schema, prefix, skip):
        meaning = _description(prop, defs)
        for pattern, link in (links or {}).items():
            if key == pattern:
                meaning += f" {link}"
        default = "required" if required else _default(prop)
        lines.append(f"| `{key}` | {_cell(_type_name(prop, defs))} | {_cell(default)} | "
                     f"{_cell(_constraints(prop))} | {_cell(meaning)} |")
    return lines


def rig_schema() -> dict:
    """The rig file's JSON schema (pydantic), without the fields rigctl fills itself."""
    from rigctl.config import RigConfig

    return RigConfig.model_json_schema()


def rig_internal_fields() -> tuple[str, ...]:
    """Fields of ``RigConfig`` that are not keys of the file (excluded from dumps)."""
    from rigctl.config import RigConfig

    return tuple(n for n, f in RigConfig.model_fields.items() if f.exclude)


def rig_page() -> str:
    """The rig-file reference: every key, with its type, default, bounds and meaning."""
    from rigctl import config

    schema = rig_schema()
    top = schema.get("properties", {})
    lines = [GENERATED_NOTE, "# Rig file", "", inspect.cleandoc(config.__doc__ or ""), "",
             "One YAML file per rig; unknown keys are refused. The annotated example is "
             "`examples/rig.example.yaml` in the source tree. The keys, section by "
             "section (a `[]` stands for each element of a list):", ""]
    links = {"procedures": "Each procedure's keys: [Procedures](procedures.md).",
             "service.schedules[].procedure": "See [Procedures](procedures.md)."}
    for section, prop in top.items():
        if section in rig_internal_fields():
            continue
        sub = {"$defs": schema.get("$defs", {}), "properties": {section: prop},
               "required": [r for r in schema.get("required", []) if r == section]}
        lines += [f"## `{section}`", ""]
        lines += schema_table(sub, links=links)
        lines.append("")
    return "\n".join(lines)


def world_schema() -> dict:
    from rigctl.mocks.world import WorldFile

    return WorldFile.model_json_schema()


def world_page() -> str:
    """The world-file reference: the schema of ``WorldFile`` and the worlds' README."""
    from rigctl.mocks import world

    readme = (Path(world.__file__).parent / "worlds" / "README.md").read_text()
    prose = [line for line in readme.splitlines()[1:] if not line.startswith("|")]
    shipped = sorted(p.stem for p in world.WORLDS.glob("*.yaml"))
    lines = [GENERATED_NOTE, "# World file", "",
             "The simulated rig's ground truth: what `rigctl sim up --world NAME|FILE`, "
             "`rigctl sim truth` and the stand-ins read (`rigctl.mocks.world`). Shipped "
             f"worlds, by name: {', '.join(_code(s) for s in shipped)}.", "",
             "## Keys", ""]
    lines += schema_table(world_schema())
    lines += ["", "## Notes", "", "From `rigctl/mocks/worlds/README.md`:", ""]
    lines += [re.sub(r"^#+ ", "", line) if line.startswith("#") else line for line in prose]
    return "\n".join(lines)


def procedures() -> list[Any]:
    """Every procedure object, by name."""
    from rigctl.procedures import get_procedure, procedure_names

    return [get_procedure(name) for name in procedure_names()]


def procedures_page() -> str:
    """Each procedure: summary, devices, and its parameters (the rig file's
    ``procedures.<name>`` keys and ``--param key=value``)."""
    lines = [GENERATED_NOTE, "# Procedures", "",
             "A procedure's parameters come from its own defaults (shown here), then the "
             "devices' `settle_s` keys (the longest wait of the devices it moves, for "
             "`settle_s`), the rig file's `procedures.<name>` mapping, then from "
             "`--param key=value` (values read as YAML) on the command line or `params` in "
             "`POST /runs`; unknown parameters are refused. "
             "`rigctl procedures --json` prints the same schemas. What each one records "
             "is in [Result files](results.md).", ""]
    for proc in procedures():
        schema = proc.params_model.model_json_schema()
        optional = ", ".join(proc.optional_devices) or "none"
        lines += [f"## `{proc.name}`", "", proc.summary, "",
                  f"Devices: {', '.join(proc.devices) or 'none'} (optional: {optional}).",
                  "", f"Rig-file keys `procedures.{proc.name}.*`:", ""]
        lines += schema_table(schema) if schema.get("properties") else ["No parameters."]
        lines.append("")
    return "\n".join(lines)


# -- the HTTP API -----------------------------------------------------------------------


def openapi() -> dict:
    """The service's OpenAPI document, from an app on a throwaway rig (nothing runs)."""
    from rigctl.config import parse_rig
    from rigctl.service import RigService, create_app

    with tempfile.TemporaryDirectory(prefix="rigctl-docs-") as tmp:
        config = parse_rig(f"name: docs\nrecords: {{directory: {json.dumps(tmp)}}}\n")
        return create_app(RigService(config)).openapi()


def _operation_params(op: dict) -> str:
    parts = []
    for p in op.get("parameters", []):
        schema = p.get("schema", {})
        bounds = _constraints(schema)
        parts.append(f"`{p['name']}` ({p['in']}{', ' + bounds if bounds else ''})")
    return ", ".join(parts)


def _body(op: dict, spec: dict) -> str:
    content = op.get("requestBody", {}).get("content", {})
    for media in content.values():
        ref = media.get("schema", {}).get("$ref", "")
        name = ref.rsplit("/", 1)[-1]
        schema = spec.get("components", {}).get("schemas", {}).get(name, {})
        keys = ", ".join(_code(k) for k in schema.get("properties", {}))
        return f"body `{name}`: {keys}" if keys else f"body `{name}`"
    return ""


def api_page() -> str:
    """The HTTP API reference from the app's OpenAPI document."""
    spec = openapi()
    lines = [GENERATED_NOTE, "# HTTP API", "",
             "`rigctl serve --rig rig.yaml` serves these on `service.bind:service.port` "
             "(127.0.0.1:8765 by default). The live schema is at `/openapi.json` and the "
             "interactive page at `/docs`. Every query, path and body value is bounded "
             "there, so bad input answers 4xx, never 5xx (`tests/test_api_properties.py` "
             "fuzzes every endpoint with schemathesis). `/` redirects to the operator "
             "console, `/console/`.", "",
             "Authentication: changes (every `POST`) need `Authorization: Bearer <token>` "
             "when a token is set (`service.token` or the environment's `RIGCTL_TOKEN`); "
             "reads need it too when `service.public_read` is false, its default on any "
             "bind but loopback. `/health` is always open. See "
             "[Deploy the service](../how-to/service.md).", "",
             "| method | path | summary | parameters and body | description |",
             "|---|---|---|---|---|"]
    for path, operations in spec.get("paths", {}).items():
        for method, op in operations.items():
            extra = "; ".join(x for x in (_operation_params(op), _body(op, spec)) if x)
            description = (op.get("description") or "").split("\n\n")[0]
            lines.append(f"| {method.upper()} | `{path}` | {_cell(op.get('summary'))} | "
                         f"{_cell(extra)} | {_cell(description)} |")
    schemas = spec.get("components", {}).get("schemas", {})
    bodies = {n: s for n, s in schemas.items()
              if n in ("RunRequest", "AbortRequest", "DecisionRequest")
              or n.endswith("Request")}
    if bodies:
        lines += ["", "## Request bodies", ""]
        for name, schema in bodies.items():
            lines += [f"### `{name}`", ""]
            lines += schema_table({"$defs": schemas, **schema})
            lines.append("")
    return "\n".join(lines)


# -- hardware ---------------------------------------------------------------------------


def _doc_block(module: Any) -> list[str]:
    return ["Sources, as the table's module cites them:", "",
            *[f"> {line}" if line else ">" for line in inspect.cleandoc(module.__doc__ or "")
              .splitlines()], ""]


def hardware_page() -> str:
    """The supported UR arms and Dynamixel servos, from the tables the drivers use."""
    from rigctl.drivers import dynamixel_models as dxl
    from rigctl.hardware import ur_models as ur

    lines = [GENERATED_NOTE, "# Supported hardware", "",
             "Generated from the tables the drivers use. The stand-ins keep their own "
             "transcriptions (`rigctl.mocks.ur_models`, `rigctl.mocks.dxl_models`).", "",
             "## Universal Robots arms", "", "`devices.arm.model` takes these names "
             "(`rigctl.hardware.ur_models`). DH lengths in metres; alpha is "
             f"({', '.join(f'{a:.4g}' for a in ur.UR_ALPHA)}) rad for every model.", "",
             "| model | dashboard says | generation | d1 | a2 | a3 | d4 | d5 | d6 | reach m "
             "| max speed deg/s (joints 1-6) | position limits deg |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for m in ur.MODELS.values():
        limits = "; ".join("free" if lim is None else f"{lim[0]:g}..{lim[1]:g}"
                           for lim in dict.fromkeys(m.position_limits_deg))
        speeds = ", ".join(f"{v:g}" for v in m.max_speed_dps)
        lines.append(f"| `{m.name}` | {m.dashboard} | {m.generation} | {m.d1:g} | {m.a2:g} | "
                     f"{m.a3:g} | {m.d4:g} | {m.d5:g} | {m.d6:g} | {m.reach_m:g} | {speeds} "
                     f"| {limits} |")
    lines += ["", *_doc_block(ur)]
    lines += ["## Dynamixel servos", "",
              "`devices.head.model` takes these names (or leave it out: the driver reads "
              "each servo's model number), `rigctl.drivers.dynamixel_models`.", "",
              "| model | model number | family | pulses per turn | resolution deg | load "
              "item | input V | max C | e-Manual page |",
              "|---|---|---|---|---|---|---|---|---|"]
    for s in dxl.MODELS:
        volts = f"{s.voltage_v[0]:g}" if s.voltage_v[0] == s.voltage_v[1] \
            else f"{s.voltage_v[0]:g}-{s.voltage_v[1]:g}"
        lines.append(f"| `{s.name}` | {s.number} | {s.family} | {s.pulses_per_rev} | "
                     f"{s.resolution_deg:.5g} | {s.load} ({s.load_unit:g} "
                     f"{'mA' if s.load == 'current' else '%'}) | {volts} | "
                     f"{s.max_temperature_c:g} | [{s.name}]({s.source}) |")
    aliases = ", ".join(f"`{a}` = `{b}`" for a, b in dxl.ALIASES.items())
    lines += ["", f"PRO+ names accepted as aliases: {aliases}.", "",
              "Baud rates (`devices.head.baud`, Baud Rate item codes): "
              + ", ".join(f"{code}: {baud}" for code, baud in dxl.BAUD_CODES.items()) + ".",
              "", *_doc_block(dxl)]
    return "\n".join(lines)


PAGES: dict[str, Callable[[], str]] = {
    "reference/cli.md": cli_page,
    "reference/rig-file.md": rig_page,
    "reference/world-file.md": world_page,
    "reference/procedures.md": procedures_page,
    "reference/http-api.md": api_page,
    "reference/hardware.md": hardware_page,
}


def generate() -> dict[str, str]:
    """Every generated page: path under docs/ -> Markdown."""
    return {path: make() for path, make in PAGES.items()}


def on_files(files: Any, config: Any) -> Any:
    """MkDocs hook: add the generated reference pages to the site."""
    from mkdocs.structure.files import File

    for path, text in generate().items():
        files.append(File.generated(config, path, content=text))
    return files
