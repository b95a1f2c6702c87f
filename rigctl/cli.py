"""The ``rigctl`` command line (typer + rich).

``--json`` prints machine-readable output on stdout and nothing else; progress and
messages go to stderr. Exit codes: 0 success, 1 run failed, 2 refused (bad input,
limits, busy), 3 aborted.
"""

from __future__ import annotations

import atexit
import contextlib
import gc
import json
import os
import sys
from pathlib import Path
from typing import Any

import typer
import yaml
from rich.console import Console
from rich.markup import escape
from rich.table import Table

from rigctl import __version__
from rigctl.config import load_rig
from rigctl.errors import ConfigError, RigError


class _Typer(typer.Typer):
    """The command line; an import of a missing extra anywhere in a command ends in one
    message naming the extra to install (``rigctl.extras``), exit 2."""

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        from rigctl.extras import missing_extra

        atexit.unregister(_skip_exit_collections)  # once, however often it is called
        atexit.register(_skip_exit_collections)
        try:
            return super().__call__(*args, **kwargs)
        except (ModuleNotFoundError, ConfigError) as exc:
            missing = missing_extra(exc)
            if missing is None:
                raise
            Console(stderr=True, soft_wrap=True).print(
                f"[red]error:[/red] {escape(str(missing))}", highlight=False)
            sys.exit(EXIT_REFUSED)


def _skip_exit_collections() -> None:
    """At the command's exit: freeze the objects the command made, so that the
    interpreter's teardown does not traverse them again in its last garbage collections
    (0.3 s after an active-camera re-solve). Nothing an ending process needs is left to
    them: the command's files are written and closed, and the exit handlers (logging's,
    temporary directories') do not wait on a collection."""
    gc.freeze()


app = _Typer(add_completion=False, no_args_is_help=True,
             help="rigctl: rig controller for camera and robot calibration.")
runs_app = typer.Typer(no_args_is_help=True, help="Recorded runs.")
mock_app = typer.Typer(no_args_is_help=True, help="Protocol stand-ins for the hardware.")
bench_app = typer.Typer(no_args_is_help=True, help="Benchmarks (JSON and a table).")
head_app = typer.Typer(no_args_is_help=True, help="Dynamixel bus tools: scan, reboot.")
app.add_typer(head_app, name="head")
app.add_typer(runs_app, name="runs")
app.add_typer(mock_app, name="mock")
app.add_typer(bench_app, name="bench")

err = Console(stderr=True, soft_wrap=True)
out = Console()

EXIT_FAILED, EXIT_REFUSED, EXIT_ABORTED = 1, 2, 3


@contextlib.contextmanager
def stdout_to_stderr():
    """Send file descriptor 1 to stderr while device libraries run: ur_rtde prints to
    stdout from C++, and ``--json`` promises JSON on stdout and nothing else. Yields a
    file object on the real stdout."""
    sys.stdout.flush()
    saved = os.dup(1)
    os.dup2(2, 1)
    real = os.fdopen(os.dup(saved), "w")
    try:
        yield real
    finally:
        sys.stdout.flush()
        os.dup2(saved, 1)
        os.close(saved)


def _print_json(data: Any, stream=None) -> None:
    from rigctl.records import to_jsonable

    stream = stream or sys.stdout
    stream.write(json.dumps(to_jsonable(data), indent=2, default=str) + "\n")
    stream.flush()


def _fail(exc: Exception, as_json: bool, code: int = EXIT_REFUSED) -> None:
    if as_json:
        _print_json({"error": str(exc), "type": type(exc).__name__})
    else:
        err.print(f"[red]error:[/red] {escape(str(exc))}", markup=True, highlight=False)
    raise typer.Exit(code)


def parse_params(items: list[str]) -> dict[str, Any]:
    """``key=value`` pairs; values are read as YAML (numbers, lists, booleans)."""
    params: dict[str, Any] = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise ConfigError(f"--param {item!r}: expected key=value")
        try:
            params[key.strip()] = yaml.safe_load(value)
        except yaml.YAMLError:
            raise ConfigError(f"--param {key}: cannot read value {value!r}") from None
    return params


def _version(value: bool) -> None:
    if value:
        typer.echo(f"rigctl {__version__}")
        raise typer.Exit()


@app.callback()
def main(version: bool = typer.Option(False, "--version", callback=_version, is_eager=True,
                                      help="Print the version and exit.")) -> None:
    """rigctl: rig controller for camera and robot calibration."""


@app.command()
def demo(quick: bool = typer.Option(False, "--quick",
                                    help="a short chain: active-camera on fewer rotations, "
                                    "then hand-eye on eight views"),
         records: Path = typer.Option(Path("demo-records"), "--records",
                                      help="where the runs are recorded"),
         world: str = typer.Option("default", "--world",
                                   help="a shipped world's name or a world file")) -> None:
    """The main job on a simulated rig (stand-ins started and stopped here): every
    estimate printed against the world's truth. Needs the arm extra."""
    from rigctl import demo as demo_job

    try:
        with stdout_to_stderr():
            status = demo_job.main(quick=quick, records=records, world=world)
    except RigError as exc:
        _fail(exc, False)
    raise typer.Exit(EXIT_FAILED if status else 0)


@app.command()
def run(procedure: str | None = typer.Argument(None, help="Procedure name (see `rigctl "
                                                         "procedures`); none with --resume."),
        rig: Path = typer.Option(..., "--rig", help="Rig file (YAML)."),
        resume: str | None = typer.Option(None, "--resume", help="Resume this run (id or "
                                          "unique prefix): aborted, interrupted, failed on a "
                                          "device, or tell a paused one to continue."),
        param: list[str] = typer.Option([], "--param", "-p", help="key=value, repeatable."),
        dry_run: bool = typer.Option(False, "--dry-run", help="Print the plan; touch nothing."),
        as_json: bool = typer.Option(False, "--json", help="JSON on stdout, nothing else."),
        operator: str | None = typer.Option(None, "--operator", help="Who runs it.")) -> None:
    """Run a procedure on the rig, recording everything."""
    from rigctl.runner import Runner

    try:
        config = load_rig(rig)
        runner = Runner(config, operator=operator, show_progress=not as_json or sys.stderr.isatty())
        overrides = parse_params(param)
        if resume is not None:
            if procedure is not None or overrides or dry_run:
                raise ConfigError("--resume RUN_ID takes no procedure, --param or --dry-run: "
                                  "the run continues its recorded plan")
            with stdout_to_stderr():
                outcome = runner.resume(resume)
            if outcome is None:
                err.print(f"run {resume} is paused in another process: asked it to continue")
                raise typer.Exit(0)
        elif procedure is None:
            raise ConfigError("give a PROCEDURE to run, or --resume RUN_ID")
        elif dry_run:
            plan = runner.dry_run(procedure, overrides)
            if as_json:
                _print_json(plan.as_dict())
            else:
                _print_plan(plan)
            raise typer.Exit(0 if not plan.violations else EXIT_REFUSED)
        else:
            if overrides.get("teach") is True:  # Enter = capture, `done` = finish (rigctl.teach)
                __import__("rigctl.teach").teach.read_terminal()
            with stdout_to_stderr():
                outcome = runner.run(procedure, overrides)
    except RigError as exc:
        _fail(exc, as_json)
    if as_json:
        _print_json(outcome.result if outcome.status == "succeeded" and outcome.result is not None
                    else outcome.as_dict())
    else:
        colour = {"succeeded": "green", "aborted": "yellow"}.get(outcome.status, "red")
        err.print(f"run {outcome.run_id}: [{colour}]{outcome.status}[/{colour}]"
                  + (f" ({outcome.reason})" if outcome.reason else ""), highlight=False)
        err.print(f"records: {outcome.run_dir}", highlight=False)
        if outcome.result is not None:
            out.print_json(json.dumps(_summary(outcome.result), default=str))
    refused = outcome.status == "failed" and (outcome.reason or "").startswith("ConfigError")
    raise typer.Exit(EXIT_REFUSED if refused else  # the rig file disagrees with a device
                     {"succeeded": 0, "aborted": EXIT_ABORTED}.get(outcome.status, EXIT_FAILED))


def _summary(result: dict[str, Any]) -> dict[str, Any]:
    return result.get("summary", result)


def _print_plan(plan) -> None:
    table = Table(title=f"plan: {plan.procedure} ({len(plan.steps)} steps)")
    table.add_column("#", justify="right")
    table.add_column("device")
    table.add_column("step")
    for row in plan.as_dict()["steps"]:
        table.add_row(str(row["n"]), row["device"] or "-", row["description"])
    out.print(table)
    if plan.violations:
        for violation in plan.violations:
            err.print(f"[red]limit:[/red] {violation}", highlight=False)
    else:
        err.print("[green]all moves within soft limits[/green]; no device was touched")


@app.command("procedures")
def list_procedures(as_json: bool = typer.Option(False, "--json")) -> None:
    """List the procedures with their parameters."""
    from rigctl import procedures

    rows = []
    for name in procedures.procedure_names():
        proc = procedures.get_procedure(name)
        rows.append({"name": name, "summary": proc.summary, "devices": list(proc.devices),
                     "params": proc.params_model.model_json_schema()})
    if as_json:
        _print_json(rows)
        return
    table = Table(title="procedures")
    for col in ("name", "devices", "summary"):
        table.add_column(col)
    for row in rows:
        table.add_row(row["name"], ", ".join(row["devices"]), row["summary"])
    out.print(table)


@runs_app.command("list")
def runs_list(rig: Path = typer.Option(..., "--rig"), limit: int = typer.Option(20, "--limit"),
              procedure: str | None = typer.Option(None, "--procedure"),
              as_json: bool = typer.Option(False, "--json")) -> None:
    """Recent runs from the index."""
    from rigctl.record_index import RecordIndex, replay_pending

    try:
        config = load_rig(rig)
        index = RecordIndex(config.database_url())
        replay_pending(index, config.records_dir())  # writes a run kept while it was away
        rows = index.list(limit, procedure, rig_name=config.name)
    except RigError as exc:
        _fail(exc, as_json)
    if as_json:
        _print_json(rows)
        return
    table = Table(title=f"runs of {config.name}")
    for col in ("run id", "procedure", "status", "started", "operator", "reason"):
        table.add_column(col)
    for r in rows:
        table.add_row(r["run_id"], r["procedure"], r["status"],
                      r["started_at"].strftime("%Y-%m-%d %H:%M:%S"), r["operator"] or "",
                      (r["reason"] or "")[:60])
    out.print(table)


@runs_app.command("show")
def runs_show(run_id: str, rig: Path = typer.Option(..., "--rig"),
              as_json: bool = typer.Option(False, "--json")) -> None:
    """One run of this rig: its index row and its result."""
    from rigctl.record_index import RecordIndex
    from rigctl.records import RunDirectory

    try:
        config = load_rig(rig)
        row = RecordIndex(config.database_url()).get(run_id, rig_name=config.name)
        run_dir = RunDirectory(row["run_dir"])
        row["captures"] = len(run_dir.captures()) if run_dir.path.exists() else 0
        row["segments"] = segments_of(run_dir, row["status"])
        result_path = run_dir.path / "result.json"
        row["result"] = json.loads(result_path.read_text()) if result_path.exists() else None
    except RigError as exc:
        _fail(exc, as_json)
    if as_json:
        _print_json(row)
        return
    for key, value in row.items():
        if key not in ("result", "segments"):
            out.print(f"[bold]{key}[/bold]: {value}", highlight=False)
    for seg in row["segments"]:
        out.print(f"[bold]segment {seg['n']}[/bold]: {seg['started_at']} "
                  f"({seg['start_reason']}) -> {seg['ended_at']} ({seg['end']}"
                  + (f": {seg['end_reason']}" if seg.get("end_reason") else "") + ")",
                  highlight=False)
    if row["result"] is not None:
        out.print_json(json.dumps(_summary(row["result"]), default=str))


def segments_of(run_dir, status: str) -> list[dict[str, Any]]:
    """The run's segments (``segments.json``); of a run no longer running, a segment
    left open is shown as interrupted."""
    from rigctl.resume import close_dangling, read_segments

    if not run_dir.path.exists():
        return []
    segments = read_segments(run_dir)
    return segments if status in ("running", "paused") else close_dangling(segments, run_dir)


def parse_indices(text: str | None) -> list[int]:
    """Capture indices as ``--exclude`` takes them: ``12,17`` (``012`` is 12)."""
    if not text:
        return []
    try:
        indices = [int(part) for part in text.split(",") if part.strip()]
    except ValueError:
        raise ConfigError(f"--exclude {text!r}: expected capture indices as in "
                          "captures/NNN, comma-separated (e.g. 12,17)") from None
    if any(i < 0 for i in indices):
        raise ConfigError(f"--exclude {text!r}: capture indices are 0 or more")
    return indices


@runs_app.command("poses")
def runs_poses(run: str = typer.Argument(..., help="Run directory, or run id with --rig."),
               output: Path = typer.Option(..., "--out", help="The pose file to write."),
               rig: Path | None = typer.Option(None, "--rig"),
               exclude: str | None = typer.Option(None, "--exclude",
                                                  help="Captures to leave out: 12,17.")
               ) -> None:
    """Write the arm poses of a run's captures as a pose file (joint angles in degrees)
    for `--param poses_file=...` of hand-eye and robot-kinematics."""
    from rigctl.procedures.planning import pose_file_text
    from rigctl.record_index import RecordIndex
    from rigctl.records import RunDirectory

    try:
        run_path = Path(run)
        if not run_path.is_dir():
            if rig is None:
                raise ConfigError(f"{run}: not a run directory (give --rig to look up a run id)")
            config = load_rig(rig)
            run_path = Path(RecordIndex(config.database_url()).get(run, rig_name=config.name)
                            ["run_dir"])
        text = pose_file_text(RunDirectory(run_path), set(parse_indices(exclude)))
        output.write_text(text)
    except RigError as exc:
        _fail(exc, False)
    except OSError as exc:
        _fail(ConfigError(f"{output}: cannot write: {exc.strerror}"), False)
    poses = sum(line.startswith("- ") for line in text.splitlines())
    err.print(f"wrote {output} ({poses} poses)", highlight=False)


@app.command()
def solve(run_dir: Path = typer.Argument(..., help="A run directory."),
          exclude: str | None = typer.Option(
              None, "--exclude", help="Capture indices to leave out, as in captures/NNN: 12,17."),
          reason: str = typer.Option("", "--reason", help="Why (kept in the run's decisions)."),
          operator: str | None = typer.Option(None, "--operator",
                                              help="Who excludes (default: the user)."),
          as_json: bool = typer.Option(False, "--json")) -> None:
    """Solve a recorded run again, offline; the old result is kept as result.N.json.
    With --exclude, without those captures; who excluded what, and why, goes into the
    run's decisions, and the result names them (exit 2 for a capture the run lacks)."""
    try:
        excluded = parse_indices(exclude)
    except ConfigError as exc:
        _fail(exc, as_json)
    # the solve's second process first: its interpreter starts, and imports the plots'
    # modules, on the other core while this one imports the solve's
    try:
        helper = _solve_process_for(run_dir)
    except ConfigError as exc:  # RIGCTL_SOLVE_THREADS is not a number of threads
        _fail(exc, as_json, EXIT_FAILED)
    try:
        result = _solve_offline(run_dir, excluded, operator, reason, helper, as_json)
    finally:
        if helper is not None:
            helper.close()
    if as_json:
        _print_json(result)
    else:
        out.print_json(json.dumps(_summary(result), default=str))


def _solve_process_for(run_dir: Path):
    """A second process for the re-solve of ``run_dir`` (``calib.solve_process``, with
    the plots' modules), when its procedure uses one and the solve may use more than
    one thread; else None (also for a run directory without a readable
    ``params.json``: the solve reports that). ``ConfigError`` for a bad
    ``RIGCTL_SOLVE_THREADS``."""
    from rigctl.calib.solve_process import start_if_useful
    from rigctl.procedures import SOLVE_PROCESS_USERS

    try:
        name = json.loads((run_dir / "params.json").read_text()).get("procedure")
    except (OSError, ValueError, AttributeError):
        return None
    return start_if_useful(plots=True) if name in SOLVE_PROCESS_USERS else None


def _open_index(url: str):
    """The record index at ``url`` (``record_index.RecordIndex``, whose SQLAlchemy is
    imported here, only when there is an index to open)."""
    from rigctl.record_index import RecordIndex

    return RecordIndex(url)


def _solve_offline(run_dir: Path, excluded: list[int], operator: str | None, reason: str,
                   helper, as_json: bool) -> dict[str, Any]:
    """``runner.solve_recorded`` on ``run_dir`` with the run's own record index (its
    rig's database, else an ``index.sqlite`` beside it; a run directory copied elsewhere
    has none); a failure ends the command."""
    from rigctl.records import RunDirectory
    from rigctl.runner import recorded_config, solve_recorded

    try:
        index = None
        try:
            config = recorded_config(RunDirectory(run_dir))
            if config.records.database_url:
                index = _open_index(config.database_url())
        except RigError:
            pass
        beside = run_dir.resolve().parent / "index.sqlite"
        if index is None and beside.exists():
            index = _open_index(f"sqlite:///{beside}")
        return solve_recorded(run_dir, index, exclude=excluded, by=operator, reason=reason,
                              solve_process=helper)
    except ConfigError as exc:  # the run directory or an excluded index is wrong
        _fail(exc, as_json, EXIT_REFUSED if excluded else EXIT_FAILED)
    except RigError as exc:
        _fail(exc, as_json, EXIT_FAILED)


@app.command()
def export(run: str = typer.Argument(..., help="Run directory, or run id with --rig."),
           fmt: str = typer.Option("json", "--format",
                                   help="json | opencv | ros | ur | ur-kinematics | urdf | "
                                   "ros-static"),
           output: Path | None = typer.Option(None, "--out", help="Output file."),
           rig: Path | None = typer.Option(None, "--rig")) -> None:
    """Export a run's calibration."""
    from rigctl.exports import SUFFIXES, export_result
    from rigctl.record_index import RecordIndex
    from rigctl.records import RunDirectory

    try:
        run_path = Path(run)
        if not run_path.is_dir():
            if rig is None:
                raise ConfigError(f"{run}: not a run directory (give --rig to look up a run id)")
            config = load_rig(rig)
            row = RecordIndex(config.database_url()).get(run, rig_name=config.name)
            run_path = Path(row["run_dir"])
        run_dir = RunDirectory(run_path)
        target = output or run_dir.path / f"export{SUFFIXES.get(fmt, '.out')}"
        path = export_result(run_dir.result(), fmt, target, run_dir.run_id,
                             run_dir.versions())
    except RigError as exc:
        _fail(exc, False, EXIT_FAILED)
    except (OSError, ValueError, TypeError) as exc:
        _fail(RigError(f"export {run} --format {fmt}: {type(exc).__name__}: {exc}"), False,
              EXIT_FAILED)
    err.print(f"wrote {path}", highlight=False)


@app.command()
def doctor(rig: Path = typer.Option(..., "--rig"),
           as_json: bool = typer.Option(False, "--json")) -> None:
    """Connect each configured device and report what it is and how fast it answers."""
    from rigctl.doctor import check_rig

    try:
        config = load_rig(rig)
    except RigError as exc:
        _fail(exc, as_json)
    with stdout_to_stderr():
        report = check_rig(config)
    if as_json:
        _print_json(report)
    else:
        table = Table(title=f"doctor: {config.name}")
        for col in ("device", "state", "details", "round trip"):
            table.add_column(col)
        for row in report:
            colour = {"ok": "green", "missing": "yellow"}.get(row["state"], "red")
            latency = f"{row['latency_ms']:.2f} ms" if row.get("latency_ms") else "-"
            table.add_row(row["device"], f"[{colour}]{row['state']}[/{colour}]",
                          row["message"], latency)
        out.print(table)
        for row in report:
            if row.get("hint"):
                out.print(f"{row['device']}: {row['hint']}", highlight=False)
    if any(r["state"] == "refused" for r in report):  # e.g. the arm is another model
        raise typer.Exit(EXIT_REFUSED)
    raise typer.Exit(0 if all(r["state"] in ("ok", "missing") for r in report) else EXIT_FAILED)



@mock_app.command("head", context_settings={"allow_extra_args": True,
                                             "ignore_unknown_options": True},
                  add_help_option=False)
def mock_head(ctx: typer.Context) -> None:
    """Dynamixel Protocol 2.0 bus on a pty (see `rigctl mock head --help`)."""
    from rigctl.mocks import dynamixel_bus

    raise typer.Exit(dynamixel_bus.main(ctx.args))



@head_app.command("scan")
def head_scan(port: str = typer.Option(..., "--port", help="serial port of the servo bus"),
              bauds: list[int] = typer.Option(None, "--baud",
                                              help="only these baud rates (default: every "
                                                   "standard rate)"),
              as_json: bool = typer.Option(False, "--json")) -> None:
    """Broadcast ping at every standard baud rate: ID, model, firmware and baud."""
    from rigctl.drivers.dynamixel import scan_bus
    from rigctl.drivers.dynamixel_models import STANDARD_BAUDS

    bad = [b for b in bauds or () if b not in STANDARD_BAUDS]
    if bad:
        _fail(ConfigError(f"--baud {bad[0]}: not a Dynamixel baud rate (one of "
                          f"{', '.join(map(str, STANDARD_BAUDS))})"), as_json)
    try:
        found = scan_bus(port, tuple(bauds) if bauds else STANDARD_BAUDS)
    except RigError as exc:
        _fail(exc, as_json, EXIT_FAILED)
    if as_json:
        _print_json(found)
        return
    table = Table(title=f"head scan: {port}")
    for col in ("id", "model", "model number", "firmware", "baud"):
        table.add_column(col)
    for row in found:
        table.add_row(*(str(row[k]) for k in ("id", "model", "model_number", "firmware",
                                              "baud")))
    out.print(table)
    if not found:
        err.print(f"no servo answered on {port} at any baud rate tried")


@head_app.command("reboot")
def head_reboot(rig: Path = typer.Option(..., "--rig"),
                axis: str | None = typer.Argument(None, help="pan, tilt or roll (default: "
                                                             "every servo in alert)"),
                as_json: bool = typer.Option(False, "--json")) -> None:
    """Reboot a servo in alert (or AXIS), then report its hardware error status."""
    from rigctl.drivers.dynamixel import AXES, DynamixelHead

    try:
        config = load_rig(rig)
        if config.devices.head is None:
            raise ConfigError(f"{rig}: devices.head: not configured")
        if axis is not None and axis not in AXES:
            raise ConfigError(f"AXIS {axis!r}: one of {', '.join(AXES)}")
    except RigError as exc:
        _fail(exc, as_json)
    head = DynamixelHead(config.devices.head)  # connect() writes nothing; no park
    try:
        with stdout_to_stderr():
            head.connect()
            try:
                alerts = {head.axis_of[i] for i in head.hardware_errors()}
                targets = [axis] if axis else sorted(alerts)
                report = [head.reboot(a) for a in targets]
            finally:
                head.disconnect()
    except RigError as exc:
        _fail(exc, as_json, EXIT_FAILED)
    if as_json:
        _print_json(report)
        return
    if not report:
        out.print("no servo in alert; nothing rebooted")
    for row in report:
        out.print(f"{row['axis']} (id {row['id']}, {row['model']}): before {row['before']}, "
                  f"after reboot {row['after']}", highlight=False)
    raise typer.Exit(0 if all(not r["hardware_error_after"] for r in report) else EXIT_FAILED)


@bench_app.command("head")
def bench_head(as_json: bool = typer.Option(False, "--json"),
               samples: int = typer.Option(500, "--samples"),
               transactions: int = typer.Option(10000, "--transactions"),
               mixed: int = typer.Option(2000, "--mixed", help="transactions per mixed bus"),
               mixed_only: bool = typer.Option(False, "--mixed-only",
                                               help="only the mixed buses at 1 Mbaud")) -> None:
    """Dynamixel latency vs wire limit at 57.6k, 1M, 4M baud; failures; settle time;
    mixed buses (XH540 + XM430, PH54 + XM430) at 1 Mbaud."""
    from rigctl.bench import head
    from rigctl.bench.common import print_table

    if mixed_only:
        result = head.run_mixed(mixed)
        if as_json:
            _print_json(result)
        else:
            print_table("bench head, mixed buses (ms)", ["bus", "transaction", "median", "p99",
                                                        "wire limit", "ratio", "failures"],
                        head.rows(result), out)
            out.print(f"targets: {result['targets']}")
        return
    result = head.run(samples, transactions, mixed)
    if as_json:
        _print_json(result)
        return
    print_table("bench head (ms)", ["baud", "transaction", "median", "p99", "wire limit",
                                    "ratio", "failures"], head.rows(result), out)
    lt = result["latency_timer"]
    out.print(f"USB-serial latency timer, median ms at 1 Mbaud: 1 ms {lt['1ms']}, 16 ms "
              f"{lt['16ms']}: +{lt['added_s_per_1000_transactions']:.1f} s per 1000 "
              "fast sync reads")
    out.print(f"failures: {result['failures']}")
    out.print(f"settle: {result['settle']}")
    out.print(f"targets: {result['targets']}")


@mock_app.command("arm", context_settings={"allow_extra_args": True,
                                            "ignore_unknown_options": True},
                  add_help_option=False)
def mock_arm(ctx: typer.Context) -> None:
    """UR controller stand-in: RTDE, dashboard, script port (see `rigctl mock arm --help`)."""
    from rigctl.mocks import ur_controller

    raise typer.Exit(ur_controller.main(ctx.args))


arm_app = typer.Typer(no_args_is_help=True, help="Operator actions on the arm.")
app.add_typer(arm_app, name="arm")


@arm_app.command("unlock")
def arm_unlock(rig: Path = typer.Option(..., "--rig")) -> None:
    """Unlock a protective stop (after inspecting its cause); a paused run then restarts its
    control script and continues."""
    from rigctl.drivers.ur import URArm

    try:
        config = load_rig(rig)
        cfg = config.devices.arm
        if cfg is None:
            raise ConfigError(f"{rig.name}: devices.arm: not configured")
        arm = URArm(cfg)
        import dashboard_client

        dash = dashboard_client.DashboardClient(cfg.host)
        dash.connect()
        answer = dash.safetystatus()
        dash.disconnect()
        err.print(f"arm {cfg.host}: {answer}")
        err.print(arm.unlock_protective_stop())
    except RigError as exc:
        _fail(exc, False, EXIT_FAILED)
    except RuntimeError as exc:
        _fail(RigError(f"arm: {exc}"), False, EXIT_FAILED)


@bench_app.command("arm")
def bench_arm(as_json: bool = typer.Option(False, "--json"),
              seconds: float = typer.Option(5.0, "--seconds")) -> None:
    """ur_rtde against the stand-in: connect, stream rate, moveJ overhead and timing."""
    from rigctl.bench import arm
    from rigctl.bench.common import print_table

    with stdout_to_stderr() as real_stdout:
        result = arm.run(seconds)
    if as_json:
        _print_json(result, real_stdout)
        return
    rows = [[k, v] for k, v in result["stream"].items()]
    rows += [["connect receive s", result["connect_receive_s"]],
             ["connect control s", result["connect_control_s"]],
             ["zero moveJ median ms", result["zero_movej_ms"]["median"]],
             ["zero moveJ p95 ms", result["zero_movej_ms"]["p95"]],
             ["teardown s", result["teardown_s"]]]
    rows += [[f"moveJ {d['distance_rad']} rad v{d['v']} a{d['a']} measured/ideal s",
              f"{d['measured_s']:.4f} / {d['ideal_s']:.4f} ({d['ratio']:.4f})"]
             for d in result["movej"]]
    print_table("bench arm", ["metric", "value"], rows, out)
    out.print(f"targets: {result['targets']}")


sim_app = typer.Typer(no_args_is_help=True, help="The whole rig on stand-ins.")
WORLD_HELP = "a world file's path, or the name of a shipped world (default, ideal, drift, thesis)"
app.add_typer(sim_app, name="sim")


@sim_app.command("up")
def sim_up(world: str = typer.Option("default", "--world", help=WORLD_HELP),
           rig_out: Path = typer.Option(Path("sim-rig.yaml"), "--rig-out"),
           host: str = typer.Option("127.0.0.1", "--host"),
           records: str = typer.Option("records", "--records"),
           port: int = typer.Option(18080, "--camera-port"),
           workdir: Path | None = typer.Option(None, "--workdir",
                                               help="fixed folder for the pty link and "
                                                    "sockets (default: a new temp folder)")
           ) -> None:
    """Start head bus, arm controller and camera on one world; write a rig file; run
    until SIGTERM (or `rigctl sim down`)."""
    from rigctl.mocks import sim

    try:
        raise typer.Exit(sim.up(world, str(rig_out), host, records, port,
                                workdir=str(workdir) if workdir else None))
    except RigError as exc:
        _fail(exc, False)


@sim_app.command("down")
def sim_down(host: str = typer.Option("127.0.0.1", "--host")) -> None:
    """Stop the simulated rig running on HOST."""
    from rigctl.mocks import sim

    try:
        _print_json(sim.down(host))
    except RigError as exc:
        _fail(exc, False, EXIT_FAILED)


@sim_app.command("truth")
def sim_truth(world: str = typer.Option("default", "--world", help=WORLD_HELP),
              as_json: bool = typer.Option(False, "--json")) -> None:
    """The ground truth of a world file."""
    from rigctl.mocks.world import load_world

    try:
        truth = load_world(world).truth()
    except RigError as exc:
        _fail(exc, as_json)
    if as_json:
        _print_json(truth)
    else:
        out.print_json(json.dumps(truth))


@sim_app.command("world")
def sim_world(seed: int = typer.Option(..., "--random", min=0,
                                       help="draw a plausible rig from this seed"),
              out_path: Path | None = typer.Option(None, "--out",
                                                   help="write the world file here"),
              target: str = typer.Option("checkerboard", "--target",
                                         help="checkerboard | charuco | either"),
              mount: str = typer.Option("flange", "--mount",
                                        help="flange (head on the flange, board in the world) "
                                        "| fixed (head beside the arm, board on the flange) "
                                        "| either")) -> None:
    """A random plausible world (camera, head, arm model and errors, hand-eye, target)
    as a world file: for judging solvers on rigs nobody tuned them for."""
    from rigctl.mocks.random_world import random_world

    try:
        spec = random_world(seed, target=target, mount=mount)
    except ValueError as exc:
        _fail(ConfigError(f"sim world: {exc}"), False)
    text = f"# rigctl sim world --random {seed} --target {target} --mount {mount}\n" + \
        yaml.safe_dump(spec, sort_keys=False, default_flow_style=None)
    if out_path is None:
        sys.stdout.write(text)
        return
    try:
        out_path.write_text(text)
    except OSError as exc:
        _fail(ConfigError(f"{out_path}: cannot write the world file: {exc.strerror}"), False)
    err.print(f"world {seed} written to {out_path}")


@bench_app.command("camera")
def bench_camera(as_json: bool = typer.Option(False, "--json"),
                 world: str = typer.Option("default", "--world")) -> None:
    """Simulated camera: render fps, capture latency after settle, survey time."""
    from rigctl.bench import camera

    with stdout_to_stderr() as real_stdout:
        result = camera.run(world)
    if as_json:
        _print_json(result, real_stdout)
        return
    from rigctl.bench.common import print_table

    r, c, s = result["render"], result["capture_after_settle_ms"], result["survey"]
    print_table("bench camera", ["metric", "value"], [
        ["render fps (one core)", r["fps_one_core"]], ["ms per frame", r["ms_per_frame"]],
        ["capture after settle, median ms", c["median"]], ["... max ms", c["max"]],
        ["frame period ms", c["frame_period_ms"]],
        ["capture-survey end to end s", s["seconds"]], ["survey captures", s["captures"]],
    ], out)


def _fmt(value) -> str:
    if value is None:
        return "-"
    if isinstance(value, (list, tuple)):
        return "(" + ", ".join(_fmt(v) for v in value) + ")"
    return f"{value:.1f}" if isinstance(value, float) else str(value)


@bench_app.command("thesis")
def bench_thesis(as_json: bool = typer.Option(False, "--json"),
                 trials: int = typer.Option(25, "--trials")) -> None:
    """Thesis Tables 5.1-5.4 and the noise sweep, ours beside the thesis's."""
    from rigctl.bench import thesis
    from rigctl.bench.common import print_table

    result = thesis.run(trials)
    if as_json:
        _print_json(result)
        return
    print_table("Table 5.1 (no noise, 3 deg)", ["strategy", "points", "true f", "ours",
                                                 "thesis"],
                [[r["strategy"], r["points"], _fmt((r["fx"], r["fy"])),
                  _fmt((r["ours_fx"], r["ours_fy"])), _fmt((r["thesis_fx"], r["thesis_fy"]))]
                 for r in result["table_5_1"]], out)
    print_table("noise sweep, % focal error (fx, fy = 400, 600)",
                ["sigma", "A ours", "A thesis", "B ours", "B thesis"],
                [[r["sigma"], _fmt(r["A_median_err_pct"]), _fmt(r["thesis_A_pct"]),
                  _fmt(r["B_median_err_pct"]), _fmt(r["thesis_B_pct"])]
                 for r in result["noise_sweep"]], out)
    print_table("Table 5.2 Strategy C centre (true 10, 20)",
                ["roll", "s0 ours", "s0 thesis", "s5 ours", "s5 thesis", "s10 ours",
                 "s10 thesis"],
                [[r["roll_deg"]] + [_fmt(r[f"sigma{s}"][k]) for s in (0, 5, 10)
                                    for k in ("ours", "thesis")]
                 for r in result["table_5_2"]], out)
    print_table("Table 5.3 Strategy D centre", ["sigma", "ours", "thesis"],
                [[r["sigma"], _fmt(r["ours"]), _fmt(r["thesis"])]
                 for r in result["table_5_3"]], out)
    print_table("Table 5.4 focal lengths (true 400, 600)",
                ["sigma", "C ours", "C thesis", "D ours", "D thesis"],
                [[r["sigma"], _fmt(r["C_ours"]), _fmt(r["C_thesis"]), _fmt(r["D_ours"]),
                  _fmt(r["D_thesis"])] for r in result["table_5_4"]], out)


@bench_app.command("active")
def bench_active(as_json: bool = typer.Option(False, "--json"),
                 trials: int = typer.Option(200, "--trials"),
                 plot: Path = typer.Option(Path("bench-active.png"), "--plot")) -> None:
    """Monte Carlo of strategies A-D, the refinement and calibrateCamera against truth."""
    from rigctl.bench import active
    from rigctl.bench.common import print_table

    result = active.run(trials, plot=plot)
    if as_json:
        _print_json(result)
        return
    rows = []
    for case in result["cases"]:
        for method in active.METHODS:
            m = case[method]
            rows.append([case["sigma_px"], case["pan_tilt_deg"], case["roll_axis_tilt_deg"],
                         method, m["focal_pct_median"], m["focal_pct_p95"], m["pp_px_median"],
                         m["pp_px_p95"], m["failed"]])
    for case in result["calibrateCamera"]:
        rows.append([case["sigma_px"], "-", "-", f"calibrateCamera {case['views']} views",
                     case["focal_pct_median"], case["focal_pct_p95"], case["pp_px_median"],
                     case["pp_px_p95"], case["failed"]])
    print_table(f"bench active ({result['trials']} trials per row)",
                ["sigma", "pan/tilt", "axis tilt", "method", "f% med", "f% p95", "pp med",
                 "pp p95", "failed"], rows, out)
    out.print(f"targets: {result['targets']}; plot: {result.get('plot')}")


@bench_app.command("active-worlds")
def bench_active_worlds(as_json: bool = typer.Option(False, "--json"),
                        n: int = typer.Option(20, "--n", min=1, max=1000),
                        first_seed: int = typer.Option(0, "--first-seed", min=0),
                        distortion_terms: int = typer.Option(
                            -1, "--distortion-terms",
                            help="0-5; -1: automatic (5 with scene depths, else 2)"),
                        workers: int = typer.Option(1, "--workers", min=1, max=16),
                        shift_mm: float = typer.Option(
                            10.0, "--shift-mm", min=0, max=50,
                            help="the arm's sideways move for scene depths (0: none)"),
                        second_station_mm: float = typer.Option(
                            0.0, "--second-station-mm", min=0, max=500,
                            help="the active-camera procedure's second_station_mm: the "
                            "camera moved this far back, some rotations repeated (0: none)"),
                        ideal_encoders: bool = typer.Option(
                            False, "--ideal-encoders",
                            help="the head's encoders read the commanded angles exactly "
                            "(default: as each world's servos read them, quantized and noisy)"),
                        ) -> None:
    """The active-camera pipeline on N random worlds (rendered directly, no stand-ins):
    focal and centre error against truth, error / sigma of each intrinsic, and the head
    geometry's rotation from home against the world's (largest error in degrees and
    Mahalanobis norm, over a few pans and tilts and over a few rolls)."""
    from rigctl.bench import active_worlds
    from rigctl.bench.common import print_table

    if distortion_terms not in (-1, 0, 1, 2, 3, 4, 5):
        _fail(ConfigError(f"--distortion-terms: -1 (automatic) or 0 to 5, got "
                          f"{distortion_terms}"), as_json)
    result = active_worlds.run(n, first_seed, None if distortion_terms < 0 else distortion_terms,
                               workers, shift_mm / 1000.0, second_station_mm / 1000.0,
                               ideal_encoders)
    if as_json:
        _print_json(result)
        return
    rows = [[r["seed"], r["model"], round(r["fx_true"]), r.get("error", "")[:60]]
            + ([] if "error" in r else [r["focal_pct"], r["centre_px"],
                                        *(r["z"][k] for k in active_worlds.KEYS),
                                        r["head_geometry"]["pan_tilt"]["rotation_error_deg"],
                                        r["head_geometry"]["pan_tilt"]["mahalanobis"],
                                        r["head_geometry"]["roll"]["rotation_error_deg"],
                                        r["head_geometry"]["roll"]["mahalanobis"],
                                        r["solve_s"]])
            for r in result["worlds"]]
    print_table(f"bench active-worlds ({n} worlds)",
                ["seed", "arm", "f", "failure", "f err %", "centre px", "z fx", "z fy",
                 "z cx", "z cy", "pan/tilt deg", "pan/tilt z", "roll deg", "roll z",
                 "solve s"], rows, out)
    out.print_json(json.dumps(result["summary"]))


@bench_app.command("detection")
def bench_detection(as_json: bool = typer.Option(False, "--json"),
                    n: int = typer.Option(16, "--n", min=1, max=1000),
                    first_seed: int = typer.Option(1000, "--first-seed", min=0),
                    views: int = typer.Option(10, "--views", min=1, max=100)) -> None:
    """Checkerboard detection on N random worlds' rendered views: the half-scale first
    search against the whole image's (CPU a view, views found, corner error against
    truth, largest corner difference)."""
    from rigctl.bench import detection
    from rigctl.bench.common import print_table

    result = detection.run(n, first_seed, views)
    if as_json:
        _print_json(result)
        return
    summary = result["summary"]
    print_table(f"bench detection ({summary['views']} views of {n} worlds)",
                ["search", "CPU s a view", "found", "RMS px median", "RMS px p90",
                 "shared px RMS"],
                [[name, *(summary[name][k] for k in (
                    "cpu_s_per_view", "found", "rms_px_median", "rms_px_p90",
                    "shared_px_rms"))] for name in detection.SEARCHES], out)
    largest = summary["largest_change_px"]
    out.print("largest corner difference between the searches: "
              + ("-" if largest is None else f"{largest:.4f} px"))


@bench_app.command("worlds")
def bench_worlds(as_json: bool = typer.Option(False, "--json"),
                 n: int = typer.Option(20, "--n", min=1, max=500),
                 first_seed: int = typer.Option(1000, "--first-seed", min=0),
                 plot: Path = typer.Option(Path("bench-worlds.png"), "--plot"),
                 keep: Path | None = typer.Option(None, "--keep",
                                                  help="keep world files and records here"),
                 from_kept: Path | None = typer.Option(
                     None, "--from-kept", help="report on a --keep folder, run nothing"),
                 combination: str = typer.Option(
                     "each", "--combination",
                     help="each (target x mounting by seed mod 4) or one for every world: "
                     "checkerboard-flange | charuco-flange | checkerboard-fixed | "
                     "charuco-fixed"),
                 until: str | None = typer.Option(
                     None, "--until",
                     help="run the chain up to this procedure only: active-camera | "
                     "hand-eye | robot-kinematics | validate-arm (default: all)")
                 ) -> None:
    """The whole chain (active-camera, hand-eye, robot-kinematics, validate-arm), or its
    first procedures up to --until, through the stand-ins on N random worlds, with
    default parameters, against each world's truth; each combination of target and
    mounting reported apart."""
    from rigctl.bench import worlds
    from rigctl.bench.common import print_table

    try:  # a bad --until or --combination: a clear error before any world runs
        chain = worlds.chain_until(until)
        worlds.combination(first_seed, combination)
    except RigError as exc:
        _fail(exc, as_json)
    with stdout_to_stderr() as real_stdout:
        if from_kept is not None:
            result = worlds.report(worlds.rows_from_kept(from_kept, chain), plot, chain)
            n = len(result["worlds"])
        else:
            result = worlds.run(n, first_seed, plot, keep, console=err, only=combination,
                                chain=chain)
    stopped = typer.Exit(130) if result.get("stopped") else None  # Ctrl-C or SIGTERM
    if as_json:
        _print_json(result, real_stdout)
        if stopped:
            raise stopped
        return
    rows = []
    for r in result["worlds"]:
        p = r["procedures"]
        cam, arm = p.get("active-camera", {}), p.get("robot-kinematics", {})
        failure = next((f"{k}: {v['reason']}" for k, v in p.items()
                        if v["status"] != "succeeded"), "")
        rows.append([r["seed"], r["model"], f"{r.get('target')}-{r.get('mount')}",
                     round(r["fx_true"]),
                     cam.get("focal_pct", "-"), cam.get("centre_px", "-"),
                     arm.get("model_rms_mm", "-"), arm.get("model_max_mm", "-"),
                     arm.get("heldout_mm_after", "-"), arm.get("image_coverage", "-"),
                     p.get("validate-arm", {}).get("position_rms_mm_after", "-"),
                     failure[:70]])
    print_table(f"bench worlds ({n} worlds, seeds {', '.join(map(str, result['seeds']))})",
                ["seed", "arm", "target-mount", "f", "f err %", "centre px", "model rms mm",
                 "model max mm", "held-out mm", "coverage", "validate mm", "failure"], rows,
                out)
    per_model = [[model, m["worlds"], m["failed"],
                  *((m["model_rms_mm"] or {}).get(k, "-") for k in ("median", "max"))]
                 for model, m in result["summary"]["by_arm_model"].items()]
    print_table("per arm model", ["arm", "worlds", "failed", "model rms median mm",
                                  "model rms worst mm"], per_model, out)
    out.print_json(json.dumps(result["summary"]))
    out.print(f"plot: {result.get('plot')}")
    if stopped:
        raise stopped


@bench_app.command("solve")
def bench_solve(run_dirs: list[Path] | None = typer.Argument(None, help="run directories"),
                as_json: bool = typer.Option(False, "--json"),
                records: Path = typer.Option(Path("demo-records"), "--records",
                                             help="without run directories: the newest "
                                                  "calibration runs here")) -> None:
    """Re-solve recorded runs (copies) and time each stage of each solve."""
    from rigctl.bench import solve
    from rigctl.bench.common import print_table

    try:
        with stdout_to_stderr() as real_stdout:
            result = solve.run(run_dirs, records)
    except RigError as exc:
        _fail(exc, as_json)
    if as_json:
        _print_json(result, real_stdout)
        return
    rows = []
    for r in result["runs"]:
        rows.append([r["run"], "to the recorded result", r["to_result_s"],
                     r["target_s"] or "-", {None: "-", True: "yes", False: "no"}[r["met"]]])
        rows += [["", stage, seconds, "", ""] for stage, seconds in r["stages_s"].items()]
        rows.append(["", "total, with the plots after the result", r["total_s"], "", ""])
    print_table("bench solve (s)", ["run", "stage", "seconds", "target", "met"], rows, out)


@bench_app.command("handeye")
def bench_handeye(as_json: bool = typer.Option(False, "--json"),
                  trials: int = typer.Option(200, "--trials", min=1)) -> None:
    """OpenCV calibrateHandEye methods against our joint refinement, 10 and 30 poses, on
    OpenCV's test noise (as run and as described) and on board-corner pixels."""
    from rigctl.bench import handeye
    from rigctl.bench.common import print_table

    result = handeye.run(trials, progress=lambda key, n: err.print(
        f"bench handeye: {key}, {n} poses, {trials} trials ..."))
    if as_json:
        _print_json(result)
        return
    for key in handeye.MODELS:
        block = result[key]
        rows = []
        for case in block["cases"]:
            for method, m in case.items():
                if isinstance(m, dict):
                    rows.append([case["poses"], method, m["rot_deg_median"], m["rot_deg_p95"],
                                 m["t_mm_median"], m["t_mm_p95"]])
        print_table(block["model"], ["poses", "method", "rot deg med", "rot deg p95",
                                     "t mm med", "t mm p95"], rows, out)
        for case in block["cases"]:
            line = (f"{case['poses']} poses: refined vs best closed form "
                    f"({case['best_closed_form']}) {case['refined_vs_best_t_pct']:+.1f} % "
                    "(median translation)")
            if "crlb_t_mm_rms" in case:
                line += (f"; Cramer-Rao bound {case['crlb_t_mm_rms']:.2f} mm RMS, refined "
                         f"{case['refined']['t_mm_rms']:.2f}, best closed form "
                         f"{case[case['best_closed_form']]['t_mm_rms']:.2f}; an efficient "
                         f"estimator's median {case['crlb_t_mm_median']:.2f} mm, at most "
                         f"{case['max_possible_median_gain_vs_best_pct']:+.1f} %")
            out.print(line)
    out.print(f"targets: {result['targets']}")


@bench_app.command("thesis-robot")
def bench_thesis_robot(as_json: bool = typer.Option(False, "--json"),
                       trials: int = typer.Option(20, "--trials")) -> None:
    """Table 5.6 (3-link PUMA) beside the thesis, and the camera-error sweeps."""
    from rigctl.bench import thesis_robot
    from rigctl.bench.common import print_table

    result = thesis_robot.run(trials)
    if as_json:
        _print_json(result)
        return
    print_table("Table 5.6: errors without noise (ours / thesis)",
                ["link", "dl mm", "dalpha deg", "dd mm", "dtheta deg"],
                [[r["link"]] + [f"{r['ours'][k]:.1e} / {r['thesis'][k]:.1e}"
                                for k in ("dl_mm", "dalpha_deg", "dd_mm", "dtheta_deg")]
                 for r in result["table_5_6"]], out)
    print_table("Figs 5.30-5.35: median error in l (mm), link 1/2/3",
                ["camera error", "sigma", "link-by-link", "refined"],
                [[r["error"], f"{r['sigma']} {r['unit']}",
                  " / ".join(f"{v:.3f}" for v in r["link_by_link_dl_mm"]),
                  " / ".join(f"{v:.3f}" for v in r["refined_dl_mm"])]
                 for r in result["sweeps"]], out)
    out.print(f"targets: {result['targets']}")


@bench_app.command("robot")
def bench_robot(as_json: bool = typer.Option(False, "--json"),
                trials: int = typer.Option(100, "--trials")) -> None:
    """UR5-class Monte Carlo: link-by-link, refinement, plain D-H vs the anchor."""
    from rigctl.bench import robot
    from rigctl.bench.common import print_table

    result = robot.run(trials)
    if as_json:
        _print_json(result)
        return
    print_table(f"bench robot: held-out position RMS, mm (median of {trials} trials)",
                ["noise", "poses", "anchor", "nominal", "link-by-link", "axis-based", "refined",
                 "plain DH", "cond", "z rms", "DH sv min/2nd"],
                [[r["noise"], r["poses"], r["anchor_mm"], r["nominal_mm"], r["link_by_link_mm"],
                  r["axis_based_mm"],
                  r["refined_mm"], r["plain_dh_mm"], r["condition_median"],
                  r["uncertainty_z_rms_median"],
                  f"{r['dh_smallest_sv_rel']:.1e} / {r['dh_second_sv_rel']:.1e}"]
                 for r in result["rows"]], out)
    out.print(f"targets: {result['targets']}")


@app.command()
def serve(rig: Path = typer.Option(..., "--rig"),
          host: str | None = typer.Option(None, "--host", help="default: service.bind"),
          port: int | None = typer.Option(None, "--port", help="default: service.port")) -> None:
    """HTTP API, run queue, scheduled recalibration and status page for the rig."""
    from rigctl import service

    try:
        config = load_rig(rig)
        service.check_bind(config, host or config.service.bind)
    except RigError as exc:
        _fail(exc, False)
    err.print(f"rigctl serve: rig {config.name} on http://{host or config.service.bind}:"
              f"{port or config.service.port}/", highlight=False)
    service.serve(config, host, port)


if __name__ == "__main__":  # pragma: no cover
    app()
