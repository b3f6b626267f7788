"""Commands that need no running system: ``certs``, ``validate``, ``expand``, ``plan``, ``check``."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Iterable, Sequence
from typing import Any

from dyknow.cli.common import (
    DEFAULT_MANAGER,
    Commands,
    UsageError,
    name_list,
    parse_pairs,
    parse_value,
    print_json,
    read_limits,
    report_result,
    shipped,
    shown,
)


def _ontology(paths: Sequence[str]) -> Any:
    from dyknow.ontology import Ontology

    return Ontology.load(paths) if paths else None


def _load(args: argparse.Namespace) -> list[Any]:
    """The specs of ``args.paths``, expanded, their requirements held to a manager's default
    formula bounds (a manager refuses a spec it could not watch the requirements of)."""
    from dyknow.security import Limits
    from dyknow.spec import load_specs

    ontology = _ontology(getattr(args, "ontology", []))
    individuals = ontology.individuals if ontology is not None else None
    return load_specs(args.paths, individuals=individuals, max_expansions=args.max_expansions, limits=Limits())


def cmd_certs(args: argparse.Namespace) -> int:
    """write a development CA and certificates signed by it, for TLS with mutual authentication"""
    from dyknow.certs import write_dev_certs

    written = write_dev_certs(args.dir, args.names, hosts=args.hosts)
    report_result(args, {"written": [str(p) for p in written]}, [f"wrote {p}" for p in written])
    return 0


def cmd_paths(args: argparse.Namespace) -> int:
    """print where dyknow's shipped files are, and the names that reach them from any folder
    (@shipped, @testing, @pipeline: --specs @shipped --ontology @shipped/dyknow.ttl)

    examples:
      dyknow paths
      dyknow manager --specs @shipped --ontology @shipped/dyknow.ttl
      dyknow validate @testing/scenario-station.xml"""
    import sys as _sys
    from pathlib import Path

    import dyknow
    from dyknow.resources import SHIPPED_FILES, SHIPPED_NAMES, shipped_path

    folders = {name: shipped_path(name) for name in SHIPPED_NAMES}
    files = {name: sorted(p.name for p in Path(folder).iterdir() if p.suffix in SHIPPED_FILES) for name, folder in folders.items()}
    data = {
        "version": dyknow.__version__,
        "package": str(Path(dyknow.__file__).resolve().parent),
        "python": _sys.executable,
        "folders": {name: {"path": folders[name], "holds": what, "files": files[name]} for name, what in SHIPPED_NAMES.items()},
    }

    def text() -> Iterable[str]:
        yield f"dyknow {data['version']} in {data['package']} (python {data['python']})"
        for name, what in SHIPPED_NAMES.items():
            yield f"{name:<10} {folders[name]}"
            yield f"{'':<10} {what}: {', '.join(files[name])}"

    report_result(args, data, text)
    return 0


def cmd_validate(args: argparse.Namespace) -> int:
    """check spec files (requirements within a manager's default formula bounds), and that the
    module and class each <source> names can be found as a manager would find them (nothing is
    imported); exit 1 with one PATH:LINE: message per error

    examples:
      dyknow validate specs/ --path .                  # your specs, your units' package in this folder
      dyknow validate @shipped --ontology @shipped/dyknow.ttl
      dyknow validate specs/ --skip-sources            # away from the units' code: the specs alone"""
    from dyknow.errors import SpecError, SpecIssue
    from dyknow.spec.reader import template_sources
    from dyknow.spec.sources import SourceRef, source_issues

    found: list[SpecIssue] = []
    specs: list[Any] = []
    try:
        specs = _load(args)
    except SpecError as exc:
        found += exc.issues
    if not args.skip_sources:  # (also where a file has other mistakes: every error in one run)
        found += source_issues([SourceRef(*ref) for ref in template_sources(args.paths)], args.path)
    if found:
        order: dict[str, int] = {}  # (the files in the order their first issue came: the order given)
        for issue in found:
            order.setdefault(issue.path, len(order))
        found.sort(key=lambda i: (order[i.path], i.line))
        for issue in found:
            print(str(issue), file=sys.stderr)
        if args.json:
            print_json({"valid": False, "errors": [str(i) for i in found], "issues": [i.to_dict() for i in found]})
        return 1
    files = len({s.path for s in specs})
    report_result(
        args,
        {"valid": True, "transformations": len(specs), "files": files},
        f"ok: {len(specs)} transformations in {files} file{'s' if files != 1 else ''}",
    )
    return 0


def cmd_expand(args: argparse.Namespace) -> int:
    """print every transformation after template expansion"""
    specs = _load(args)

    def text() -> Iterable[str]:
        for s in specs:
            yield f"{s.label}  ({s.source})  {s.location}"
            for p in s.ports:
                tags = ", ".join(s.tags_for(p.name))
                yield f"    {p.direction:>3} {p.name}" + (f"  [{tags}]" if tags else "")
            for name, value in s.param_values().items():
                yield f"    param {name} = {value!r}"

    data = [
        {
            "label": s.label,
            "source": s.source,
            "params": s.param_values(),
            "ports": [{"name": p.name, "direction": p.direction} for p in s.ports],
            "tags": [{"port": t.port, "tag": t.tag} for t in s.tags],
        }
        for s in specs
    ]
    report_result(args, data, text)
    return 0


def cmd_plan(args: argparse.Namespace) -> int:
    """plan a configuration for a tag, offline; exit 1 with the explanation when none exists"""
    from dyknow.errors import PlanningError
    from dyknow.planner import plan
    from dyknow.resources import shipped_path
    from dyknow.spec import load_specs

    ontology = _ontology(args.ontology)
    specs = load_specs(args.specs, individuals=ontology.individuals if ontology is not None else None, max_expansions=args.max_expansions)
    measurements = {k: parse_value(v) for k, v in parse_pairs(args.measure, "--measure").items()}
    individuals = ontology.individuals if ontology is not None else None
    peers: dict[str, list[Any]] = {}
    for name, path in ((n, p) for item in args.peer for n, p in parse_pairs([item], "--peer").items()):
        try:
            path = shipped_path(path)
        except (ValueError, FileNotFoundError) as exc:
            raise UsageError(f"--peer {name}={path}: {exc}") from None
        peers.setdefault(name, []).extend(load_specs([path], individuals=individuals, max_expansions=args.max_expansions))
    try:
        result = plan(args.request, specs, ontology, (), set(args.unavailable), measurements, manager=args.manager, peers=peers)
    except PlanningError as exc:
        if args.json:
            print_json({"request": args.request, "error": str(exc), "rejection": exc.rejection.to_dict() if exc.rejection else None})
        print(str(exc), file=sys.stderr)
        return 1

    def text() -> Iterable[str]:
        yield f"{result.request}: {len(result.units)} units, output {result.output_unit}.{result.output_port} on {result.output_key}"
        for unit in result.units:
            yield f"  {'new ' if unit.new else 'reuse'} {unit.name} ({unit.label})" + (f" on {unit.manager}" if unit.remote else "")
        for c in result.connections:
            yield f"  {c.source} -> {c.target}  ({c.key})"

    report_result(args, result.to_dict(), text)
    return 0


def cmd_check(args: argparse.Namespace) -> int:
    """check a file of requirements over a recording, as live monitors would have judged it:
    exit 0 when every requirement held, 1 when one was false or could not be checked

    The file is TOML: [bindings] ("TERM" = "TOPIC", a topic's {ARG} making a template), then a
    [[requirement]] table each, with name, formula and, if need be, bindings and idle_ms of its
    own (see docs/howto/requirements-in-ci.md).

    examples:
      dyknow check requirements.toml --mcap run.mcap
      dyknow check requirements.toml --mcap run.mcap --ontology floor.ttl --junit report.xml
      dyknow check requirements.toml --mcap run.mcap --verdicts verdicts.mcap   # open both in Foxglove"""
    from pathlib import Path

    from dyknow.reasoning.requirements import check_recording, details, junit_xml, load_requirements, summary, write_verdicts

    requirements = load_requirements(args.requirements)
    ontology = _ontology(args.ontology)
    results = check_recording(requirements, args.mcap, individuals=ontology.individuals if ontology is not None else None, limits=read_limits(args))
    if args.junit is not None:
        try:
            Path(args.junit).write_text(junit_xml(results, recording=Path(args.mcap).name), encoding="utf-8")
        except OSError as exc:
            raise UsageError(f"--junit {args.junit}: cannot write the report: {exc.strerror or exc}") from None
    if args.verdicts is not None:
        write_verdicts(results, args.verdicts)
    held = sum(r.held for r in results)
    errors = sum(r.error is not None for r in results)
    if args.json:
        for r in results:
            print_json(r.to_dict())
    else:
        width = min(40, max(len(r.requirement.name) for r in results))
        for r in results:
            mark = "held " if r.held else "ERROR" if r.error is not None else "FALSE"
            print(shown(f"{mark}  {r.requirement.name:<{width}}  {summary(r)}"))
            if not r.held and r.error is None:
                for line in details(r).splitlines()[1:11]:
                    print(shown(f"       {line}"))
        false = len(results) - held - errors
        print(f"{len(results)} requirements: {held} held, {false} false, {errors} not checked", flush=True)
    return 0 if held == len(results) else 1


def add_commands(cmds: Commands) -> None:
    """Add this family's commands to the parser."""
    limit_options = cmds.limit_options

    def certs_options(p: argparse.ArgumentParser) -> None:
        p.add_argument("dir", metavar="DIR", help="where to write ca.pem, ca.key and NAME.pem, NAME.key (an existing CA there is reused)")
        p.add_argument("--names", required=True, type=name_list, metavar="A,B,C", help="the certificates' common names")
        p.add_argument("--hosts", type=name_list, default=["localhost", "127.0.0.1"], metavar="H,H",
                       help="host names and addresses the certificates are valid for (default localhost,127.0.0.1)")  # fmt: skip

    cmds.command("certs", cmd_certs, certs_options)
    cmds.command("paths", cmd_paths)

    def validate_options(p: argparse.ArgumentParser) -> None:
        limit_options(p)
        p.add_argument("--path", action="append", default=[], metavar="DIR",
                       help="a folder to find units' modules in, besides the spec files' own folders (as dyknow manager --path)")  # fmt: skip
        p.add_argument("--skip-sources", action="store_true", help="do not look for the modules of <source> (specs checked away from their code)")
        p.add_argument("paths", nargs="+", type=shipped, metavar="PATH", help="spec file or directory of .xml specs (@shipped: dyknow's own)")
        p.add_argument("--ontology", action="extend", nargs="+", default=[], type=shipped, metavar="FILE",
                       help="ontologies for <arg class=...> (@shipped/dyknow.ttl: the example ontology)")  # fmt: skip

    cmds.command("validate", cmd_validate, validate_options)

    def expand_options(p: argparse.ArgumentParser) -> None:
        limit_options(p)
        p.add_argument("paths", nargs="+", type=shipped, metavar="PATH", help="spec file or directory of .xml specs (@shipped: dyknow's own)")
        p.add_argument("--ontology", action="extend", nargs="+", default=[], type=shipped, metavar="FILE",
                       help="ontologies for <arg class=...> (@shipped/dyknow.ttl: the example ontology)")  # fmt: skip

    cmds.command("expand", cmd_expand, expand_options)

    def plan_options(p: argparse.ArgumentParser) -> None:
        limit_options(p)
        p.add_argument("--specs", action="extend", nargs="+", required=True, type=shipped, metavar="PATH",
                       help="spec files or directories (@shipped: dyknow's own, @testing: the scenario's, @pipeline: the pipeline robot's)")  # fmt: skip
        p.add_argument("--ontology", action="extend", nargs="+", default=[], type=shipped, metavar="FILE",
                       help="ontology files (@shipped/dyknow.ttl: the example ontology)")  # fmt: skip
        p.add_argument("--request", required=True, metavar="TAG", help="the tag to provide, e.g. 'BallPosition(field)'")
        p.add_argument("--unavailable", action="extend", nargs="+", default=[], metavar="LABEL", help="transformations not to use")
        p.add_argument("--measure", action="extend", nargs="+", default=[], metavar="NAME=VALUE", help="latest measurements")
        p.add_argument("--manager", default=DEFAULT_MANAGER, metavar="NAME", help="manager name used in the planned keys")
        p.add_argument("--peer", action="append", default=[], metavar="NAME=PATH",
                       help="another manager's library (spec file or directory), to plan across managers; repeatable")  # fmt: skip

    cmds.command("plan", cmd_plan, plan_options)

    def check_options(p: argparse.ArgumentParser) -> None:
        p.add_argument("requirements", metavar="REQUIREMENTS.toml", help="the requirements: [bindings] and [[requirement]] tables")
        p.add_argument("--mcap", required=True, metavar="FILE", help="the recording to check them over")
        p.add_argument("--ontology", action="extend", nargs="+", default=[], type=shipped, metavar="FILE",
                       help="ontologies whose individuals a forall ranges over (@shipped/dyknow.ttl: the example ontology)")  # fmt: skip
        p.add_argument("--junit", metavar="FILE.xml", help="also write a JUnit XML report (a test case per requirement), for CI")
        p.add_argument("--verdicts", metavar="FILE.mcap",
                       help="also write every verdict to an MCAP file, a topic per requirement and instance (verdicts/NAME[/INSTANCE]), "
                            "at the recording's times: Foxglove's State Transitions panel plots .state")  # fmt: skip
        cmds.mcap_limit_options(p)

    cmds.command("check", cmd_check, check_options)
