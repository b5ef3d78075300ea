# Two commands on a fresh machine: `make demo` and `make test`.
# Both create .venv, install the package (compiling the Rust core) and run.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
export VIRTUAL_ENV := $(abspath $(VENV))
export PATH := $(abspath $(BIN)):$(PATH)

.PHONY: demo test lint install build docs bench wheel train codebooks clean

$(BIN)/maturin:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet "maturin>=1.8,<2"

# The package alone, as `pip install edgepose` gives it: enough for the demo,
# building codebooks and estimating poses.
install: $(BIN)/maturin
	$(BIN)/maturin develop --release --quiet

# Everything the tests and training need too: they cover training and export,
# so the `export` extra (torch, CPU use only; a large download the first time),
# and catalogue builds on a local Ray instance, so the `dist` extra (ray); the
# `test-hooks` feature adds the core's deliberate-panic hook the tests call.
build: $(BIN)/maturin
	$(BIN)/maturin develop --release --quiet --extras test,export,dist,lint --features test-hooks

# ruff (format and lint) over the Python trees, mypy on the package, rustfmt
# and clippy with warnings as errors. CI runs it before the tests.
lint: build
	$(BIN)/ruff format --check python benches export tests
	$(BIN)/ruff check python benches export tests
	$(BIN)/mypy
	cargo fmt --all --check
	cargo clippy --workspace --all-targets --features test-hooks -- -D warnings

demo: install
	$(BIN)/edgepose demo

test: build
	cargo test --workspace
	$(BIN)/python -m pytest -q

# The documentation site (mkdocs-material; the API reference by mkdocstrings,
# which reads the sources statically, so the compiled core is not needed) into
# site/, strict: a broken link or an unreadable docstring fails the build. The
# pins are the `docs` extra's in pyproject.toml: change both together.
DOCS_PACKAGES := "mkdocs==1.6.1" "mkdocs-material==9.8.2" "mkdocstrings[python]==1.0.8" "mkdocstrings-python==2.0.11"
docs: $(BIN)/maturin
	$(BIN)/python -m pip install --quiet $(DOCS_PACKAGES)
	NO_MKDOCS_2_WARNING=1 $(BIN)/mkdocs build --strict --site-dir site

# The shipped example codebooks (codebooks/ links to python/edgepose/codebooks/,
# so they install with the package); rebuild them after the encoder changes.
codebooks: install
	$(BIN)/edgepose build ../shared/data/ycb -o codebooks

bench: build
	cargo bench --workspace
	$(BIN)/python benches/bench_maps.py

train: build
	$(BIN)/python -m export.train
	$(BIN)/python -m export.evaluate

wheel: $(BIN)/maturin
	$(BIN)/maturin build --release --out dist

clean:
	rm -rf $(VENV) target dist
