"""The house as it grows (STYLE.md, rules 16 and 23): a module holds one concept a reader can take
in at once, says what it holds on its first line, and no module reaches into another's privates or
imports in a circle."""

from __future__ import annotations

import ast
import subprocess

import pytest

from tests.conftest import REPO, under_ci

MODULES = sorted(p for folder in ("dyknow", "transformations") for p in (REPO / folder).rglob("*.py"))
MAX_LINES = 1000


def test_no_module_is_past_a_thousand_lines() -> None:
    """Past about 1,000 lines a concept has parts: split along them into a subpackage (rule 23)."""
    long = {str(p.relative_to(REPO)): n for p in MODULES if (n := len(p.read_text(encoding="utf-8").splitlines())) > MAX_LINES}
    assert long == {}, f"modules over {MAX_LINES} lines: {long}; split each by concept (STYLE.md, rule 23)"


def test_every_module_says_what_it_holds_on_its_first_line() -> None:
    missing = []
    for path in MODULES:
        doc = ast.get_docstring(ast.parse(path.read_text(encoding="utf-8")))
        if not doc or not doc.splitlines()[0].strip():
            missing.append(str(path.relative_to(REPO)))
    assert missing == [], f"modules without a first docstring line saying what they hold: {missing}"


@pytest.mark.process
def test_no_import_circle_and_no_reach_into_anothers_privates() -> None:
    """The shared structure check (``../shared/tools/structure-check``, beside the checkout in CI)."""
    check = REPO.parent / "shared" / "tools" / "structure-check"
    if not check.is_file():
        message = f"the structure check is not at {check}"
        if under_ci():
            pytest.fail(message)
        pytest.skip(message)
    done = subprocess.run(["bash", str(check)], capture_output=True, text=True, timeout=300, cwd=REPO)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-2000:]
    assert "0 import circles" in done.stdout and "0 reaches into another object's private members" in done.stdout
