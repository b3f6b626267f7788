"""The README is a front page that stays true: short, its two quick-start commands real, its
links into the documentation live. What it used to teach is in ``docs/``, whose blocks
``tests/test_docs.py`` runs."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from tests.conftest import REPO

README = (REPO / "README.md").read_text(encoding="utf-8")

#: ``[text](target)`` links, images included; the target up to a space or ``)``.
LINK = re.compile(r"\]\(([^)\s]+)\)")


def _section(title: str) -> str:
    match = re.search(rf"^## {re.escape(title)}\n(.*?)(?=^## |\Z)", README, re.MULTILINE | re.DOTALL)
    assert match, f"the README has no section '## {title}'"
    return match.group(1)


def _slug(heading: str) -> str:
    """The anchor GitHub gives a Markdown heading (MyST gives the same with ``myst_heading_anchors``)."""
    text = re.sub(r"[`*_]", "", heading.strip().lower())
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


def _anchors(page: Path) -> set[str]:
    text = re.sub(r"^```.*?^```", "", page.read_text(encoding="utf-8"), flags=re.MULTILINE | re.DOTALL)
    return {_slug(m.group(1)) for m in re.finditer(r"^#{1,6} (.+)$", text, re.MULTILINE)}


def _local_links() -> list[str]:
    return [t for t in LINK.findall(README) if not re.match(r"^[a-z]+:", t)]


def test_the_readme_fits_on_a_screen_or_two() -> None:
    assert len(README.splitlines()) < 200


def test_the_quick_start_is_the_two_make_commands() -> None:
    (block,) = re.findall(r"```sh\n(.*?)```", _section("Quick start"), re.DOTALL)
    commands = [line.partition("#")[0].split() for line in block.splitlines() if line.strip()]
    assert commands == [["make", "demo"], ["make", "test"]]
    makefile = (REPO / "Makefile").read_text(encoding="utf-8")
    for target in ("demo", "test", "docs"):  # docs: the README says `make docs` builds the site
        assert re.search(rf"^{target}:", makefile, re.MULTILINE), f"the Makefile has no target '{target}'"
    assert "`make docs`" in README


def test_the_picture_is_the_browser_tool() -> None:
    assert "](docs/ui.png)" in README and (REPO / "docs" / "ui.png").is_file()


def test_the_readme_links_into_the_site() -> None:
    pages = {t.partition("#")[0] for t in _local_links()}
    for needed in ("docs/getting-started.md", "docs/tutorials/first-unit.md", "docs/howto/security.md", "docs/performance.md"):
        assert needed in pages, needed


@pytest.mark.parametrize("target", _local_links())
def test_every_local_link_resolves(target: str) -> None:
    """A file that exists, and for ``page.md#anchor`` a heading of that page with that anchor."""
    path, _, anchor = target.partition("#")
    assert path, f"{target}: a link to a README section, which the README no longer has"
    file = REPO / path
    assert file.exists(), f"{target}: no such file"
    if anchor:
        assert file.suffix == ".md", target
        assert anchor in _anchors(file), f"{target}: no heading with that anchor; expected one of {sorted(_anchors(file))}"


def test_the_peers_are_the_ones_the_benchmarks_measure() -> None:
    """The comparison names the peers of benchmarks/chain.py, and its figures are the docs' own."""
    comparison = _section("What it gives, against the peers")
    for peer in ("Zenoh alone", "Cyclone DDS", "dora-rs"):
        assert peer in comparison
    performance = (REPO / "docs" / "performance.md").read_text(encoding="utf-8")
    row = re.search(r"^\| median per hop.*$", comparison, re.MULTILINE)
    assert row
    figures = re.findall(r"\d+", row.group(0).split("|", 2)[2])
    variants = ("dyknow-process", "zenoh-process", "dds-process", "dora-process")
    for variant, (b2b, paced) in zip(variants, zip(figures[::2], figures[1::2], strict=True), strict=True):
        line = next(line for line in performance.splitlines() if f"(`{variant}`)" in line)
        cells = [c.strip(" *") for c in line.split("|")[2:-1]]
        assert (cells[0], cells[2]) == (b2b, paced), (variant, cells)
