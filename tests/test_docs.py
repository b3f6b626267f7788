"""The documentation site says only what is true: it builds cleanly, and every code block in it runs.

What each kind of block gets (``docs/**/*.md``):

Every block runs from a folder outside the checkout, as a user who installed dyknow runs it: the
shipped specs are named ``@shipped`` and ``@testing`` on the command line (``dyknow paths``), and
:func:`dyknow.resources.specs_dir` from Python.

- ``python``: executed in a fresh interpreter in a folder of its own (its asserts are part of the
  test), except a file of a tutorial (its first line names it, ``# mypkg/doubler.py``), which
  ``test_the_first_tutorial_runs_outside_the_checkout`` writes out and runs, and the few listed in
  ``NOT_RUN`` with the reason (none today). Blocks that listen on ``tcp/127.0.0.1:7447`` get a
  free port instead, so that a manager another test (or engineer) runs on the default port cannot
  collide.
- ``sh``: every ``dyknow`` line is parsed by the command line's own parser (options, choices,
  types); ``dyknow validate|expand|plan`` lines, which need no manager, run; ``python
  tools/...`` and ``python benchmarks/...`` (in blocks and in the prose) name scripts that exist,
  with options they define; ``make`` targets exist; no ``dyknow`` line names a file of the
  checkout (``specs/vision.xml``) that a user's folder would not have. A block after ``<!-- docs-test: bash -->``
  (a session with a manager in the background) runs as a bash script in an empty folder, one after
  ``<!-- docs-test: bash, in the tutorial's folder -->`` in the tutorial's folder, and one after
  ``<!-- docs-test: run in the tutorial's folder -->`` line by line there. A manager session gets
  a free port instead of the default 7447 (``--listen``, ``--connect``). The two-host example of
  ``tutorials/two-hosts.md`` (three machines) runs in ``tests/test_hosts.py``, in network
  namespaces with the page's addresses.
- ``xml``: read by :func:`dyknow.spec.parse_specs` (and a whole transformation is valid against
  ``specs/transformation.xsd``); ``json5``: an ACL that :meth:`dyknow.AccessControl.from_dict`
  accepts.

Besides: the site builds with warnings as errors (``-W --keep-going -n``), and the ``>>>``
examples of every module's docstrings (the API reference shows them) run. Nothing here is
skipped, under ``CI=true`` or not.
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import io
import os
import re
import shlex
import signal
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path
from unittest import mock

import pytest

from tests.conftest import REPO, free_port

DOCS = REPO / "docs"
PAGES = sorted(p for p in DOCS.rglob("*.md") if "_build" not in p.parts)
TUTORIAL = DOCS / "tutorials" / "first-unit.md"
IN_TUTORIAL_FOLDER = "<!-- docs-test: run in the tutorial's folder -->"
BASH = "<!-- docs-test: bash -->"
BASH_IN_TUTORIAL_FOLDER = "<!-- docs-test: bash, in the tutorial's folder -->"

#: Python blocks that are not run, by page and first line, with the reason (e.g. one that needs
#: another host). Keep it short: today every block runs.
NOT_RUN: dict[tuple[str, str], str] = {}

#: A first line that names the file a tutorial block is (``# mypkg/doubler.py``, ``<!-- specs/doubler.xml -->``).
FILE_NAME = re.compile(r"^(?:# |<!-- )([\w./-]+\.(?:py|xml))(?: -->)?$")


@dataclass(frozen=True, slots=True)
class Block:
    """A fenced code block of a page."""

    page: str  # relative to docs/
    line: int  # of the opening fence
    language: str
    text: str
    marker: str  # the line before the fence when it is a docs-test comment, else ""

    @property
    def first_line(self) -> str:
        return self.text.splitlines()[0] if self.text else ""

    @property
    def file_name(self) -> str | None:
        match = FILE_NAME.match(self.first_line)
        return match.group(1) if match else None

    def __str__(self) -> str:
        return f"{self.page}:{self.line}"


def _blocks(page: Path) -> list[Block]:
    found = []
    lines = page.read_text(encoding="utf-8").splitlines()
    i = 0
    while i < len(lines):
        fence = re.match(r"^(`{3,})([\w{}-]*)", lines[i])
        if not fence:
            i += 1
            continue
        end = next(j for j in range(i + 1, len(lines)) if lines[j].startswith(fence.group(1)) and not lines[j].strip("`"))
        previous = lines[i - 1].strip() if i else ""
        marker = previous if previous.startswith("<!-- docs-test:") else ""
        where = str(page.relative_to(DOCS) if page.is_relative_to(DOCS) else page.relative_to(REPO))
        found.append(Block(where, i + 1, fence.group(2), "\n".join(lines[i + 1 : end]) + "\n", marker))
        i = end + 1
    return found


def _included(page: Path) -> list[Path]:
    """The files a page includes (``{include}``: CHANGELOG.md, CONTRIBUTING.md), whose blocks are the page's too."""
    return [
        (page.parent / name).resolve() for name in re.findall(r"^```\{include\} (\S+)$", page.read_text(encoding="utf-8"), re.MULTILINE)
    ]


BLOCKS = [block for page in PAGES for source in [page, *_included(page)] for block in _blocks(source)]


def _of(language: str) -> list[Block]:
    return [b for b in BLOCKS if b.language == language]


def _lines(block: Block) -> list[tuple[str, str]]:
    """The command lines of an sh block (continuations joined), with their comment."""
    found = []
    for line in block.text.replace("\\\n", " ").splitlines():
        command, _, comment = line.partition("  #")
        if command.strip() and not command.lstrip().startswith("#"):
            found.append((command.strip(), comment.strip()))
    return found


def _commands(block: Block) -> list[tuple[list[str], str]]:
    """The command lines of an sh block, as words, with their comment."""
    return [(shlex.split(command), comment) for command, comment in _lines(block)]


def _dyknow_lines() -> list[tuple[str, str]]:
    """Every ``dyknow ...`` command line of every sh block (what follows ``dyknow``), with where it is."""
    found = []
    for block in _of("sh"):
        for command, _ in _lines(block):
            command = re.sub(r"^(! )?([A-Z_]+=\S*\s+)*", "", command).removesuffix(" &")  # PYTHONPATH=. dyknow ... &, ! dyknow ...
            command = re.sub(r"\s+>\s*\S+$", "", command)  # dyknow echo ... > FILE
            if command.startswith("dyknow "):
                found.append((str(block), command.removeprefix("dyknow ")))
    return found


# ------------------------------------------------------------------------------------------- the site


@pytest.mark.process
def test_the_site_builds_with_warnings_as_errors(tmp_path: Path, graphviz: str) -> None:
    """``make docs`` as it runs on a fresh clone, where only the ``docs`` extra is installed
    (``tests/docs_extra_only.py``: what the other extras bring cannot be imported): a warning, a
    broken link or an unresolved reference fails."""
    result = subprocess.run(
        [sys.executable, "-m", "tests.docs_extra_only", "-b", "html", "-W", "--keep-going", "-n", "-q", str(DOCS), str(tmp_path / "site")],
        capture_output=True, text=True, timeout=300, cwd=REPO, env=dict(os.environ, PYTHONPATH=str(REPO)),
    )  # fmt: skip
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-5000:]
    site = tmp_path / "site"
    for page in PAGES:
        assert (site / page.relative_to(DOCS)).with_suffix(".html").is_file(), page
    api = (site / "reference" / "api" / "dyknow.html").read_text(encoding="utf-8")
    import dyknow

    for name in dyknow.__all__:  # every public name has its entry in the API reference
        assert f'id="dyknow.{name}"' in api, name
    where = {name: api.index(f'id="dyknow.{name}"') for name in ("Manager", "Unit", "Client", "AccessControl", "DyKnowError", "UnitError")}
    assert where["Manager"] < where["Unit"] < where["Client"] < where["AccessControl"] < where["DyKnowError"] < where["UnitError"]  # by first use
    reasoning = (site / "reference" / "api" / "reasoning.html").read_text(encoding="utf-8")
    assert 'id="dyknow.reasoning.Monitor.push"' in reasoning  # compiled by mypyc: its docstring from the source
    assert "Hand over one sample of" in reasoning
    cli = (site / "reference" / "cli.html").read_text(encoding="utf-8")
    assert "dyknow manager" in cli and "--allow-source" in cli and "dyknow mcap cat" in cli
    assert (site / "_images" / "ui.png").is_file()
    for page, figures in (("architecture", 2), ("adaptation", 1), ("federation", 1)):  # drawn by Graphviz at build time
        html = (site / "concepts" / f"{page}.html").read_text(encoding="utf-8")
        drawn = re.findall(r'src="\.\./_images/(graphviz-[0-9a-f]+\.svg)"', html) or re.findall(r'data="\.\./_images/(graphviz-[0-9a-f]+\.svg)"', html)
        assert len(drawn) == figures, page
        for svg in drawn:
            assert "<svg" in (site / "_images" / svg).read_text(encoding="utf-8")
    changelog = (site / "changelog.html").read_text(encoding="utf-8")
    assert "0.1.0" in changelog and "Changelog" in changelog  # CHANGELOG.md, included


def test_the_docs_extra_alone_lacks_what_the_other_extras_bring() -> None:
    """The environment the site's build test makes: Hypothesis (test), rosbags (ros2), pyzmq
    (bench) refused; Sphinx, myst, furo and dyknow's own requirements kept."""
    from tests.docs_extra_only import allowed_distributions, refused_modules

    allowed = allowed_distributions()
    assert {"sphinx", "myst-parser", "furo", "eclipse-zenoh", "numpy", "rdflib"} <= allowed
    assert not {"hypothesis", "pytest", "rosbags", "pyzmq", "selenium"} & allowed
    refused = refused_modules()
    assert {"hypothesis", "pytest", "rosbags", "zmq"} <= set(refused)
    assert not {"sphinx", "numpy", "zenoh", "dyknow", "transformations", "docutils"} & set(refused)


def test_the_makefile_builds_the_site_as_the_test_does() -> None:
    makefile = (REPO / "Makefile").read_text()
    assert "sphinx-build -b html -E -W --keep-going -n -q docs site" in makefile
    assert "/site/" in (REPO / ".gitignore").read_text().splitlines()


def test_the_pages_have_blocks_of_each_kind() -> None:
    kinds = {b.language for b in BLOCKS}
    assert {"python", "sh", "xml", "json5"} <= kinds
    assert len(_of("python")) >= 10
    assert {page for page, _ in NOT_RUN} <= {b.page for b in _of("python")}


# ------------------------------------------------------------------------------------------- python


def _runnable_python() -> list[Block]:
    return [b for b in _of("python") if b.file_name is None and (b.page, b.first_line) not in NOT_RUN]


def test_every_marker_is_one_the_test_knows() -> None:
    """A misspelt ``<!-- docs-test: ... -->`` would leave its block run by nothing."""
    known = {"", IN_TUTORIAL_FOLDER, BASH, BASH_IN_TUTORIAL_FOLDER}
    assert [str(b) for b in BLOCKS if b.marker not in known] == []
    for page in PAGES:
        for number, line in enumerate(page.read_text(encoding="utf-8").splitlines(), 1):
            if line.lstrip().startswith("<!-- docs-test"):
                assert line.strip() in known, f"{page.relative_to(DOCS)}:{number}: {line}"
    assert {b.language for b in BLOCKS if b.marker} == {"sh"}


def test_the_exceptions_are_few_and_still_there() -> None:
    """Each block of NOT_RUN exists as listed (an edited block must be run again or listed again)."""
    listed = {(b.page, b.first_line) for b in _of("python")}
    assert set(NOT_RUN) <= listed
    assert len(NOT_RUN) <= 3


@functools.cache
def _outside_env() -> dict[str, str]:
    """The environment of a user outside the checkout: no PYTHONPATH, so ``dyknow`` is the installed
    package. Where the dyknow under test is not the one this interpreter imports without
    PYTHONPATH (a developer's worktree beside a shared environment), its folder alone goes first."""
    import dyknow

    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    ours = Path(dyknow.__file__).resolve().parent
    found = subprocess.run([sys.executable, "-c", "import dyknow; print(dyknow.__file__)"], capture_output=True, text=True, cwd="/", env=env)
    if Path(found.stdout.strip() or "/").resolve().parent != ours:
        env["PYTHONPATH"] = str(ours.parent)
    return env


@pytest.mark.process
@pytest.mark.parametrize("block", _runnable_python(), ids=str)
def test_python_blocks_run_as_written(block: Block, tmp_path: Path) -> None:
    """From a folder of their own, outside the checkout."""
    code = block.text.replace("tcp/127.0.0.1:7447", f"tcp/127.0.0.1:{free_port()}")
    result = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=tmp_path, env=_outside_env()
    )  # fmt: skip
    assert result.returncode == 0, f"{block}\n{result.stdout[-2000:]}\n{result.stderr[-4000:]}"


@pytest.mark.process
def test_the_first_tutorial_runs_outside_the_checkout(tmp_path: Path) -> None:
    """Its files written to a folder of their own, its commands run there as written, no PYTHONPATH."""
    blocks = _blocks(TUTORIAL)
    files = {b.file_name: b.text for b in blocks if b.file_name}
    assert set(files) == {"mypkg/doubler.py", "specs/doubler.xml", "test_doubler.py", "run_doubler.py"}
    folder = tmp_path / "myproject"
    assert REPO not in folder.parents
    for name, text in files.items():
        (folder / name).parent.mkdir(parents=True, exist_ok=True)
        (folder / name).write_text(text)
    (folder / "mypkg" / "__init__.py").write_text("")  # the page's layout lists it, empty
    env = _outside_env()
    _run_in_folder(blocks, folder, env)
    _run_with_bash(blocks, folder, env)


def _run_in_folder(blocks: list[Block], folder: Path, env: dict[str, str]) -> None:
    """The tutorial's block of commands that end by themselves, one by one."""
    (block,) = [b for b in blocks if b.marker == IN_TUTORIAL_FOLDER]
    commands = _commands(block)
    assert [words[:2] for words, _ in commands] == [["dyknow", "validate"], ["python", "-m"], ["python", "run_doubler.py"]]
    for words, comment in commands:
        argv = [sys.executable, "-m", "dyknow.cli", *words[1:]] if words[0] == "dyknow" else [sys.executable, *words[1:]]
        result = subprocess.run(argv, capture_output=True, text=True, timeout=120, cwd=folder, env=env)
        assert result.returncode == 0, f"{' '.join(words)}\n{result.stdout[-3000:]}\n{result.stderr[-3000:]}"
        if comment == "1 passed":
            assert "1 passed" in result.stdout
        if words[1] == "validate":
            assert result.stdout.startswith("ok: 1 transformation")
        if words[1] == "run_doubler.py":
            assert "'messages'" in result.stdout


def _run_with_bash(blocks: list[Block], folder: Path, env: dict[str, str]) -> None:
    """The tutorial's manager session, in its folder."""
    (block,) = [b for b in blocks if b.marker == BASH_IN_TUTORIAL_FOLDER]
    result = _bash(block, folder, env)
    assert result.stdout.count("dyknow/robot/double/out") >= 3, result.stdout  # echo printed three messages
    assert "double (doubler) running" in result.stdout  # stats


def _bash(block: Block, cwd: Path, env: dict[str, str]) -> subprocess.CompletedProcess[str]:
    """A manager session as a bash script (``bash -e``), with the venv's ``dyknow`` and ``python``
    first on PATH. The one change: a free port instead of the default 7447, in the manager's
    ``--listen`` and each client's ``--connect`` (added where the page leaves them to their
    default), so that no other manager on this machine answers."""
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    script = block.text.replace("\\\n", " ").replace("127.0.0.1:7447", f"127.0.0.1:{port}")
    metrics = str(free_port())  # (the documented --metrics-port, likewise)
    script = script.replace("--metrics-port 9464", f"--metrics-port {metrics}").replace("127.0.0.1:9464", f"127.0.0.1:{metrics}")
    script = re.sub(r"^((?:\S+=\S+ )*dyknow manager (?:(?! --listen ).)*) &$", rf"\1 --listen {endpoint} &", script, flags=re.MULTILINE)
    assert len(re.findall(rf"dyknow manager .* --listen \w+/127\.0\.0\.1:{port}", script)) == 1, script
    client = r"^((?:! |until )?dyknow (?:spawn|destroy|model|managers|config|stats|add-spec|remove-spec|request|release|measure|adaptations|monitor|echo|record|replay|hz|top|doctor))(?!.* --connect )"
    script = re.sub(client, rf"\1 --connect {endpoint}", script, flags=re.MULTILINE)
    assert re.search(rf"--connect \w+/127\.0\.0\.1:{port}", script), script
    env = dict(env, PATH=f"{Path(sys.executable).parent}{os.pathsep}{env.get('PATH', '')}")
    # a session of its own, killed whole at the end: a failed line (bash -e) or a timeout must not
    # leave its manager running in the background
    proc = subprocess.Popen(
        ["bash", "-e", "-c", script], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=cwd, env=env, start_new_session=True
    )
    try:
        stdout, stderr = proc.communicate(timeout=90)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        stdout, stderr = proc.communicate()
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
    result = subprocess.CompletedProcess(proc.args, proc.returncode, stdout, stderr)
    assert result.returncode == 0, f"{block}\n{script}\n{result.stdout[-3000:]}\n{result.stderr[-3000:]}"
    assert "Traceback" not in result.stderr and f"/127.0.0.1:{port} with" in result.stdout and "stopped" in result.stdout
    return result


@pytest.mark.process
@pytest.mark.parametrize("block", [b for b in BLOCKS if b.marker == BASH], ids=str)
def test_manager_sessions_run_as_written(block: Block, tmp_path: Path) -> None:
    """The sessions with a manager, in an empty folder outside the checkout."""
    assert REPO not in tmp_path.parents
    result = _bash(block, tmp_path, _outside_env())
    if "dyknow echo 'dyknow/robot/requests" in block.text:
        track = [line for line in result.stdout.splitlines() if line.startswith("dyknow/robot/requests/BallTrack(field) ")]
        assert len(track) == 5, result.stdout  # echo: five messages of the track
    if "spawn relay r1 --bind" in block.text:
        assert "r1 (relay) running" in result.stdout and "dyknow/robot/src/out #" in result.stdout
    if "dyknow certs" in block.text:  # roles: the admin spawned, the viewer was refused and reads the model
        assert "spawned src (periodic-source): running" in result.stdout and "src (periodic-source) running" in result.stdout
        assert "dropped the call to 'spawn' without a reply: the manager's --acl does not let this client's certificate" in result.stderr
    if "dyknow monitor" in block.text:
        assert "dyknow/robot/monitors/1" in result.stdout and " true" in result.stdout  # verdicts as decided
    if "dyknow measure" in block.text:
        assert "measurement battery = 0.2" in result.stdout  # the adaptation, listed with its cause
    if "dyknow hz" in block.text:  # the operator's tools: rates, a view of every unit, a clean bill of health, a scrape
        assert re.search(r"^dyknow/robot/fwd/out: \d+\.\d\d Hz ", result.stdout, re.MULTILINE), result.stdout
        assert "manager robot: cpu" in result.stdout and "relay" in result.stdout
        assert "0 failed" in result.stdout and 'dyknow_port_messages_total{direction="in"' in result.stdout
    if "dyknow record" in block.text:
        assert (tmp_path / "run.mcap").is_file() and "recorded 20 messages on 1 key" in result.stdout
        assert "replayed 20 messages" in result.stdout and (tmp_path / "replayed.txt").read_text().count("replayed/track #") == 20


# ------------------------------------------------------------------------------------------- sh


class _Parsed(Exception):
    pass


def _parse_error(argv: list[str]) -> str | None:
    """None when the command line's own parser accepts ``dyknow ARGV``, else what it said."""
    from dyknow.cli import main

    original = argparse.ArgumentParser.parse_args

    def parse_only(self: argparse.ArgumentParser, args: list[str] | None = None, namespace: object = None) -> object:
        raise _Parsed(original(self, args, namespace))  # type: ignore[arg-type]

    err = io.StringIO()
    with mock.patch.object(argparse.ArgumentParser, "parse_args", parse_only), contextlib.redirect_stderr(err):
        try:
            main(argv)
        except _Parsed:
            return None
        except SystemExit:
            return err.getvalue() or "exit"
    return "the command ran instead of being parsed"


def _as_parsed(command: str) -> tuple[list[str], list[str]]:
    """A documented line as the parser gets it, and the options of its optional groups.

    ``[--duration S]`` and ``[KEYEXPR ...]`` groups are left out (their options are checked on
    their own), and so is a ``...`` that stands for options given elsewhere.
    """
    optional: list[str] = []
    for group in re.findall(r"(?<=\s)\[(--[^\]]*|[A-Z][A-Z_]* \.\.\.)\]", command):
        optional += [w for w in group.split() if w.startswith("--")]
    command = re.sub(r"(?<=\s)\[(--[^\]]*|[A-Z][A-Z_]* \.\.\.)\]", "", command)
    return [w for w in shlex.split(command) if w != "..."], optional


@pytest.mark.parametrize(("where", "command"), _dyknow_lines(), ids=lambda v: v[:60])
def test_every_dyknow_command_line_parses(where: str, command: str) -> None:
    kept, optional = _as_parsed(command)
    assert _parse_error(kept) is None, f"{where}: dyknow {command}: {_parse_error(kept)}"
    if optional:
        out = io.StringIO()
        with contextlib.redirect_stdout(out), contextlib.suppress(SystemExit):
            from dyknow.cli import main

            main([w for w in kept if not w.startswith("-")][:1] + ["--help"])
        for option in optional:
            assert option in out.getvalue(), f"{where}: {option} is not an option of dyknow {kept[0]}"


#: The files a page's own commands write before naming them (the tutorial's spec, the two-host
#: example's station.xml and robot.xml, copied there from another page's section).
PAGE_FILES = {"specs/doubler.xml", "station.xml", "robot.xml", "acl.json5", "run.mcap"}


@pytest.mark.parametrize(("where", "command"), _dyknow_lines(), ids=lambda v: v[:60])
def test_no_command_line_needs_the_checkout(where: str, command: str) -> None:
    """A path in a documented command line is a shipped name (``@shipped/vision.xml``), a file the
    page makes, or a folder of the user's: never one of the checkout (``specs/``, ``dyknow/testing/``)."""
    for word in shlex.split(command):
        value = word.partition("=")[2] if word.startswith("--") or re.match(r"^\w+=", word) else word
        checkout_file = re.match(r"^(specs|dyknow|transformations|tests)(/[\w./-]*\.(xml|ttl|xsd|py)|/?)$", value)
        if checkout_file and value not in PAGE_FILES:
            raise AssertionError(f"{where}: dyknow {command}: {value} is a file of the checkout; name it @shipped/... or @testing/...")


def _offline_commands() -> list[tuple[str, str, str]]:
    found = []
    for block in _of("sh"):
        if block.marker == IN_TUTORIAL_FOLDER:
            continue  # run by the tutorial's own test, in its folder
        for words, comment in _commands(block):
            if words[:1] == ["dyknow"] and words[1:2] and words[1] in ("validate", "expand", "plan"):
                found.append((str(block), " ".join(shlex.quote(w) for w in words[1:]), comment))
    return found


def test_the_pages_have_offline_commands() -> None:
    assert {shlex.split(c)[0] for _, c, _ in _offline_commands()} == {"validate", "expand", "plan"}


@pytest.mark.process
@pytest.mark.parametrize(("where", "command", "comment"), _offline_commands(), ids=lambda v: v[:60])
def test_offline_commands_run_as_written(where: str, command: str, comment: str, tmp_path: Path) -> None:
    """From an empty folder outside the checkout."""
    result = subprocess.run([sys.executable, "-m", "dyknow.cli", *shlex.split(command)], capture_output=True, text=True, timeout=120,
                            cwd=tmp_path, env=_outside_env())  # fmt: skip
    expected = 1 if "exit 1" in comment and not command.startswith("validate") else 0
    assert result.returncode == expected, f"{where}: {result.stderr[-2000:]}"
    assert "Traceback" not in result.stderr
    if command.startswith("plan") and expected == 0 and "--peer" in command:
        assert '"label":"robot-camera","new":true,"manager":"robot"' in result.stdout  # the camera runs on the robot
    elif command.startswith("plan") and expected == 0:
        assert "ceiling-camera" in result.stdout  # the low battery rules out the robot camera
    if expected == 1:
        assert "robot-camera (port out): constraint violated: battery = 0.1, needs >= 0.25" in result.stderr


def _other_commands() -> list[tuple[str, list[str]]]:
    """``python ...`` and ``make ...`` lines of sh blocks, and ``python tools|benchmarks/...`` in the prose."""
    found = [(str(b), words) for b in _of("sh") for words, _ in _commands(b) if words[:1] in (["python"], ["make"])]
    for page in PAGES:
        for span in re.findall(r"`(python (?:tools|benchmarks)/[^`]+)`", page.read_text(encoding="utf-8")):
            found.append((str(page.relative_to(DOCS)), shlex.split(re.sub(r"\[[^\]]*\]", "", span.replace("\n", " ")))))
    return found


@pytest.mark.parametrize(("where", "words"), _other_commands(), ids=lambda v: v if isinstance(v, str) else " ".join(v)[:60])
def test_scripts_and_make_targets_exist(where: str, words: list[str]) -> None:
    if words[0] == "make":
        assert re.search(rf"^{re.escape(words[1])}:", (REPO / "Makefile").read_text(), re.MULTILINE), where
        return
    if words[1] == "-m" or not words[1].startswith(("tools/", "benchmarks/")):
        return  # python -m pytest, python run_doubler.py: run by the tutorial's test
    script = REPO / words[1]
    assert script.is_file(), f"{where}: {words[1]}"
    source = script.read_text()
    for word in words[2:]:
        if word.startswith("--"):
            assert f'"{word.split("=")[0]}"' in source, f"{where}: {words[1]} has no option {word}"


# ------------------------------------------------------------------------------------------- xml, json5


@pytest.mark.parametrize("block", _of("xml"), ids=str)
def test_xml_blocks_are_specs(block: Block, tmp_path: Path) -> None:
    import xmlschema

    from dyknow.spec import load_specs, parse_specs

    if 'modes="modes.yaml"' in block.text:  # a <system> reading its mode file: the pipeline robot's, beside it
        (tmp_path / "modes.yaml").write_text((REPO / "dyknow" / "demo" / "pipeline" / "modes.yaml").read_text())
        (tmp_path / "spec.xml").write_text(block.text)
        specs = load_specs(tmp_path / "spec.xml")
    else:
        specs = parse_specs(block.text, f"docs/{block.page}")
    assert specs, block
    if block.text.lstrip().startswith(("<transformation", "<node", "<system", "<!--")):
        xmlschema.XMLSchema(REPO / "specs" / "transformation.xsd").validate(block.text)


def test_the_spec_format_example_reads_as_the_page_says() -> None:
    """The spec format's example expands to one spec per camera, its requirement included."""
    from dyknow.spec import parse_specs

    block = [b for b in _of("xml") if b.page == "reference/spec-format.md"][0]
    specs = parse_specs(block.text, "spec-format.md")
    assert [s.label for s in specs] == ["undistort(cam1)", "undistort(cam2)", "undistort(cam3)"]
    assert specs[1].requirements == ("not historically[0, 1s] UndistortedImage(cam2).blank",)
    assert specs[1].priority == 1 and specs[1].port("undist").deadline_ms == 500


def test_the_node_example_reads_as_the_page_says() -> None:
    """The spec format's <node> example reads as the managed node's transformation the page describes."""
    from dyknow.spec import parse_specs

    block = [b for b in _of("xml") if b.page == "reference/spec-format.md"][1]
    (spec,) = parse_specs(block.text, "spec-format.md")
    assert spec.source == "dyknow.ros2.managed:ManagedNode" and spec.tags_for("out") == ("RawImage(top)",)
    assert spec.param_values() == {
        "node": "/camera_top",
        "lifecycle": True,
        "timeout_s": 5.0,
        "binding": "ros2dds:/camera_top/image_raw?type=sensor_msgs/msg/Image",
        "ros.exposure": 0.5,
        "ros.frame_id": "top",
    }
    assert spec.priority == 1 and spec.port("out").deadline_ms == 500


@pytest.mark.parametrize("block", _of("json5"), ids=str)
def test_json5_blocks_are_acls(block: Block) -> None:
    import json5

    from dyknow import AccessControl

    acl = AccessControl.from_dict(json5.loads(block.text), where=str(block))
    assert acl.role_of("dashboard") == "viewer"
    if acl.defined:  # a role of the file's own: reads and requests, changes nothing
        assert acl.may_call("robot-ui", "request") and not acl.may_call("robot-ui", "destroy")
    else:
        assert acl.role_of("alice") == "admin"


# ------------------------------------------------------------------------------------------- docstrings


def _documented_modules() -> list[str]:
    """Every module of dyknow whose docstrings the API reference shows or links to."""
    import pkgutil

    import dyknow

    return sorted(m.name for m in pkgutil.walk_packages(dyknow.__path__, "dyknow.") if not m.name.endswith("__main__"))


def test_the_examples_in_docstrings_run() -> None:
    """``>>>`` examples of every module (the API reference shows them) give what they say."""
    import doctest
    import importlib

    attempted, failures = 0, []
    for name in _documented_modules():
        module = importlib.import_module(name)
        finder = doctest.DocTestFinder(exclude_empty=True)
        runner = doctest.DocTestRunner(optionflags=doctest.ELLIPSIS)
        for test in finder.find(module, name):
            out = io.StringIO()
            result = runner.run(test, out=out.write)
            attempted += result.attempted
            if result.failed:
                failures.append(out.getvalue())
    assert failures == []
    assert attempted >= 7  # reasoning, syntax, errors, codecs, player: an example lost would show here
