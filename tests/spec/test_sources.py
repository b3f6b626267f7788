"""dyknow.spec.sources: a spec's <source> found as a manager would find it, with nothing imported."""

from __future__ import annotations

import sys
import textwrap
from pathlib import Path

import pytest

from dyknow.spec import load_specs
from dyknow.spec.sources import source_issues
from tests.conftest import run_cli

SPEC = """<transformation><label>{label}</label><source>{source}</source>
  <ports><port type="in">in</port><port type="out">out</port></ports></transformation>"""

#: A module whose top level leaves a mark when it runs: validate must never run it.
MODULE = textwrap.dedent('''
    from pathlib import Path
    Path(__file__).with_name("ran").write_text("imported")
    from dyknow import Unit

    class Doubler(Unit):
        pass
''')


def _project(tmp_path: Path) -> Path:
    (tmp_path / "mypkg").mkdir()
    (tmp_path / "mypkg" / "__init__.py").write_text('from pathlib import Path\nPath(__file__).with_name("ran").write_text("init")\n')
    (tmp_path / "mypkg" / "doubler.py").write_text(MODULE)
    (tmp_path / "specs").mkdir()
    return tmp_path


def test_a_module_found_in_a_path_folder_and_its_class_pass_without_running_anything(tmp_path: Path) -> None:
    project = _project(tmp_path)
    (project / "specs" / "ok.xml").write_text(SPEC.format(label="double", source="mypkg.doubler:Doubler"))
    specs = load_specs([project / "specs" / "ok.xml"])
    assert source_issues(specs, [project]) == []
    assert not (project / "mypkg" / "ran").exists() and "mypkg" not in sys.modules  # neither __init__ nor the module ran


def test_a_module_not_found_and_a_class_not_defined_are_located_issues(tmp_path: Path) -> None:
    project = _project(tmp_path)
    path = project / "specs" / "bad.xml"
    path.write_text("<transformations>\n" + SPEC.format(label="a", source="mypkg.doubler:Dubler") + "\n"
                    + SPEC.format(label="b", source="mypkg.tripler:Tripler") + "\n"
                    + SPEC.format(label="c", source="otherpkg.units:Thing") + "\n</transformations>")  # fmt: skip
    specs = load_specs([path])
    without_path = [str(i) for i in source_issues(specs)]
    assert len(without_path) == 3 and all(i.startswith(f"{path}:") for i in without_path)
    assert "no module 'mypkg.doubler' found" in without_path[0] and "--path DIR" in without_path[0]  # mypkg is not beside the spec
    found = [str(i) for i in source_issues(specs, [project])]
    assert found[0] == (
        f"{path}:2: <source>: module 'mypkg.doubler' ({project / 'mypkg' / 'doubler.py'}) defines no 'Dubler'; "
        "expected a Unit subclass of that name, such as Doubler (did you mean 'Doubler'?)"  # (not Unit, Path: imported from elsewhere)
    )
    assert found[1].startswith(f"{path}:4: <source>: no module 'mypkg.tripler': package 'mypkg' ({project / 'mypkg'}) has no 'tripler'")
    assert found[2].startswith(f"{path}:6: <source>: no module 'otherpkg.units' found")
    assert not (project / "mypkg" / "ran").exists()


def test_installed_and_built_in_sources_pass(tmp_path: Path) -> None:
    path = tmp_path / "installed.xml"
    path.write_text("<transformations>" + SPEC.format(label="r", source="transformations.generic:Relay")
                    + SPEC.format(label="s", source="dyknow.testing:Sink") + "</transformations>")  # fmt: skip
    assert source_issues(load_specs([path])) == []


@pytest.mark.process
def test_validate_checks_sources_unless_told_not_to(tmp_path: Path) -> None:
    project = _project(tmp_path)
    (project / "specs" / "ok.xml").write_text(SPEC.format(label="double", source="mypkg.doubler:Doubler"))
    spec = str(project / "specs" / "ok.xml")
    missing = run_cli("validate", spec)
    assert missing.returncode == 1 and "<source>: no module 'mypkg.doubler' found" in missing.stderr
    assert run_cli("validate", spec, "--path", str(project)).returncode == 0
    assert run_cli("validate", spec, "--skip-sources").returncode == 0
    assert not (project / "mypkg" / "ran").exists()


TYPOS_A = """<transformations>
  <transformation type="unit">
    <label>one</label>
    <source>mypkg.doubler:Dubler</source>
    <params><param name="rate_hz" type="flaot">20</param></params>
    <ports><port type="out">out</port></ports>
  </transformation>
  <transformation type="unit">
    <label>two</label>
    <source>dyknow.testing:Source</source>
    <ports><port type="out">out</port><port type="inn">in</port></ports>
    <tags><tag port="ot">Fresh(y)</tag></tags>
  </transformation>
</transformations>
"""
TYPOS_B = """<transformations>
  <transformation type="unit">
    <label>three(${C})</label>
    <source>dyknow.testing:Sink</source>
    <args><arg label="C" class="dk:Camra"/></args>
    <ports><port type="in">in</port></ports>
  </transformation>
  <transformation type="unit">
    <label>four(${C})</label>
    <source>dyknow.testing:Snk</source>
    <args><arg label="C" class="dk:Camra"/></args>
    <ports><port type="out">out</port></ports>
  </transformation>
</transformations>
"""


@pytest.mark.process
def test_validate_reports_every_error_of_every_file_in_one_run(tmp_path: Path) -> None:
    """Issue 54 item 10: three typos took three runs (the tag's port was checked only once the
    ports were right, the sources only once the whole file was). Now one run names all six:
    a source whose class is misspelt (suggesting the module's own class, never the Unit it
    imports), a param type, a port direction, a tag's port, the same unknown class in two
    transformations (once, naming the other line), another misspelt class; nothing follows from
    an error on a line already flagged (the misspelt type's value is not also 'not a valid
    flaot')."""
    project = _project(tmp_path)
    (project / "specs" / "a.xml").write_text(TYPOS_A)
    (project / "specs" / "b.xml").write_text(TYPOS_B)
    a, b = project / "specs" / "a.xml", project / "specs" / "b.xml"
    done = run_cli("validate", str(a), str(b), "--path", str(project), "--ontology", "@shipped/dyknow.ttl")
    assert done.returncode == 1
    lines = done.stderr.strip().splitlines()
    assert [line.split(": ")[0] for line in lines] == [f"{a}:4", f"{a}:5", f"{a}:11", f"{a}:12", f"{b}:5", f"{b}:10"], lines
    assert "defines no 'Dubler'; expected a Unit subclass of that name, such as Doubler (did you mean 'Doubler'?)" in lines[0]
    assert "<param> @type: unknown type 'flaot'" in lines[1] and "<port> @type: unknown direction 'inn'" in lines[2]
    assert "<tag> @port: no port named 'ot'" in lines[3]
    assert "unknown ontology class 'dk:Camra'" in lines[4] and "(also at line 11)" in lines[4]
    assert "defines no 'Snk'" in lines[5] and "did you mean 'Sink'?" in lines[5]
    assert not (project / "mypkg" / "ran").exists()
