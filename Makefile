# The commands of the README's quick start, and what they need.
#   make demo   sets up .venv and runs the demo
#   make test   sets up .venv (with test tools) and runs the whole test suite
#   make docs   sets up .venv (with the documentation tools) and builds the site into site/
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin

.PHONY: demo test docs bench clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip

# setup.py compiles these with mypyc, in place: an edit to one of them needs a new install
COMPILED := $(shell sed -n 's/^    "\(dyknow\/[a-z_/]*\.py\)",$$/\1/p' setup.py)

# tools/install.py runs pip quietly but shows the progress of the compilation (the first install
# compiles the hot-path modules with mypyc: 2 to 6 minutes); DYKNOW_PURE_PYTHON=1 skips it
$(VENV)/.installed: pyproject.toml setup.py $(COMPILED) | $(BIN)/python
	$(BIN)/python tools/install.py "-e ."
	touch $@

$(VENV)/.installed-test: pyproject.toml setup.py $(COMPILED) | $(BIN)/python
	$(BIN)/python tools/install.py "-e .[test]"
	touch $@ $(VENV)/.installed $(VENV)/.installed-docs  # the test extra includes the docs one

$(VENV)/.installed-docs: pyproject.toml setup.py $(COMPILED) | $(BIN)/python
	$(BIN)/python tools/install.py "-e .[docs]"
	touch $@ $(VENV)/.installed

demo: $(VENV)/.installed
	$(BIN)/dyknow demo

# The suite runs in JOBS workers at once (pytest-xdist): its tests wait on processes, links and
# leases more than they compute, so more workers than cores; each worker has its own ports and DDS
# domains (tests/conftest.py). It ends with the 25 slowest tests. PYTEST_ARGS adds options: one tier
# (-m unit, -m process, -m namespaces, -m browser), -k NAME, -x; JOBS=0 runs it in this one process.
# pytest exits 5 when it collects no tests: that means the suite is missing, so say so and fail.
JOBS ?= 4
test: $(VENV)/.installed-test
	@$(BIN)/python -m pytest -n $(JOBS) --dist worksteal --durations=25 $(PYTEST_ARGS); rc=$$?; \
	if [ $$rc -eq 5 ]; then echo "pytest collected no tests: the test suite is missing or cannot be imported" >&2; fi; \
	exit $$rc

# warnings, broken links and unresolved references fail the build (-W --keep-going -n); offline;
# -E reads every page again: Sphinx does not notice a docstring or an extension that changed
docs: $(VENV)/.installed-docs
	@command -v dot >/dev/null || { echo "make docs draws the site's figures with Graphviz's dot: install it (Debian, Ubuntu: sudo apt-get install graphviz; macOS: brew install graphviz)" >&2; exit 1; }
	$(BIN)/sphinx-build -b html -E -W --keep-going -n -q docs site

bench: $(VENV)/.installed-test
	$(BIN)/python benchmarks/chain.py --quick --json out/chain.json --plot out/chain.png

clean:
	rm -rf $(VENV) out .pytest_cache site
