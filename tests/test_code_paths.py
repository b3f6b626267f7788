"""Where a unit's code comes from: an installed package, PYTHONPATH, or (for a user's own units)
a module beside the spec file that names it, or in a folder the operator gives with ``--path``;
found without PYTHONPATH and without changing ``sys.path``, and only for modules the operator's
own specs name (a spec sent over the network still cannot load code)."""

from __future__ import annotations

import sys
from collections.abc import Callable
from pathlib import Path

import pytest

from dyknow import AccessError, Client, Manager, UnitError
from tests.conftest import ManagerProcess, wait_until

UNIT = '''from dyknow import Unit


class Temperature(Unit):
    def setup(self):
        self.create_timer(0.02, lambda: self.publish("out", {"celsius": 90.0}))
'''


def spec(module: str) -> str:
    return f"""<transformation>
  <label>{module}-temperature</label>
  <source>{module}:Temperature</source>
  <ports><port type="out">out</port></ports>
  <tags><tag port="out">Temperature({module})</tag></tags>
</transformation>
"""


def test_a_module_beside_its_spec_file_is_found_without_pythonpath(make_manager: Callable[..., Manager], tmp_path: Path) -> None:
    (tmp_path / "thermo_beside.py").write_text(UNIT)
    (tmp_path / "thermo.xml").write_text(spec("thermo_beside"))
    path_before = list(sys.path)
    manager = make_manager(specs=[tmp_path / "thermo.xml"])
    manager.request("Temperature(thermo_beside)")
    wait_until(lambda: manager.get_statistics("thermo_beside-temperature").ports[0].messages > 3, "the unit to publish")
    assert sys.path == path_before and sys.modules["thermo_beside"].__file__ == str(tmp_path / "thermo_beside.py")


@pytest.mark.process
def test_a_module_elsewhere_is_found_through_path_and_its_absence_says_where_it_was_looked_for(
    manager_process: Callable[..., ManagerProcess], tmp_path: Path
) -> None:
    (tmp_path / "code").mkdir()
    (tmp_path / "specs").mkdir()
    (tmp_path / "code" / "thermo_elsewhere.py").write_text(UNIT)
    (tmp_path / "specs" / "thermo.xml").write_text(spec("thermo_elsewhere"))
    lost = manager_process("--specs", str(tmp_path / "specs" / "thermo.xml"))
    with Client(lost.name, connect=[lost.endpoint]) as client, pytest.raises(UnitError) as caught:
        client.spawn("thermo_elsewhere-temperature", "t")
    message = str(caught.value)
    assert "cannot import module 'thermo_elsewhere'" in message and "(looked beside the specs and in --path folders: " in message
    assert f"{tmp_path / 'specs'})" in message and str(tmp_path / "code") not in message
    assert "thermo_elsewhere.py (or a package of that name) beside the spec file or in a folder given with --path DIR" in message
    found = manager_process("--specs", str(tmp_path / "specs" / "thermo.xml"), "--path", str(tmp_path / "code"))
    with Client(found.name, connect=[found.endpoint]) as client:
        client.request("Temperature(thermo_elsewhere)")
        wait_until(lambda: client.get_statistics("thermo_elsewhere-temperature")["ports"]["out"]["messages"] > 3, "the unit to publish")


def test_a_spec_sent_over_the_network_cannot_load_a_module_from_a_code_path(make_manager: Callable[..., Manager], tmp_path: Path) -> None:
    (tmp_path / "planted.py").write_text(UNIT)  # in a folder the operator named, but no operator's spec names it
    manager = make_manager(code_paths=[tmp_path])
    with Client(manager.name, connect=manager.endpoints) as client, pytest.raises(AccessError, match="source 'planted:Temperature' is not allowed"):
        client.add_transformation(spec("planted"))
    assert "planted" not in sys.modules


def test_a_code_path_that_is_no_folder_is_refused_at_start(tmp_path: Path) -> None:
    with pytest.raises(Exception, match=r"code path .*nowhere' is not a folder; expected a folder holding unit modules \(--path DIR\)"):
        Manager("m", code_paths=[tmp_path / "nowhere"], serve=False)
