# o3d_mvps — `make demo`, `make test` and `make docs` set everything up on a fresh machine.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

.PHONY: setup system-libs demo test docs bench notebooks notebooks-run clean

setup: system-libs $(STAMP)

# System libraries: libusb-1.0 (Open3D needs it at import time), EGL + Mesa (pyvista's
# off-screen previews); and the chromium browser (the browser test of report.html, driven by
# playwright: its own browser download cannot work offline). Installed with apt-get when we are
# root; otherwise stop and say what to install.
SYSTEM_LIBS := libusb-1.0.so.0:libusb-1.0-0 libEGL.so.1:libegl1 libGL.so.1:libgl1 swrast_dri.so:libgl1-mesa-dri
SYSTEM_BINS := chromium:chromium

system-libs:
	@missing=""; \
	for pair in $(SYSTEM_LIBS); do \
	  lib=$${pair%%:*}; pkg=$${pair##*:}; \
	  if ! ldconfig -p 2>/dev/null | grep -q "$$lib" && ! ls /usr/lib/*/dri/$$lib >/dev/null 2>&1; then missing="$$missing $$pkg"; fi; \
	done; \
	for pair in $(SYSTEM_BINS); do \
	  bin=$${pair%%:*}; pkg=$${pair##*:}; \
	  if ! command -v "$$bin" >/dev/null 2>&1; then missing="$$missing $$pkg"; fi; \
	done; \
	if [ -n "$$missing" ]; then \
	  if [ "$$(id -u)" = "0" ] && command -v apt-get >/dev/null 2>&1; then \
	    echo "Installing system packages:$$missing (apt-get) ..."; \
	    (apt-get install -y -q $$missing >/dev/null 2>&1 || \
	     (apt-get update -q >/dev/null && apt-get install -y -q $$missing >/dev/null)) || \
	    { echo "error: apt-get could not install$$missing; install them by hand and rerun make." >&2; exit 1; }; \
	  else \
	    echo "error: missing system packages:$$missing (Open3D needs libusb-1.0; previews need EGL/Mesa;" >&2; \
	    echo "       the report page's browser test needs chromium)." >&2; \
	    echo "       Install them, e.g. 'sudo apt-get install$$missing' (Debian/Ubuntu), then rerun make." >&2; \
	    exit 1; \
	  fi; \
	fi

$(STAMP): pyproject.toml
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e ".[dev]"
	@$(PY) -c "import open3d, o3d_mvps" || { echo "error: the package installed but does not import; see above." >&2; exit 1; }
	@touch $(STAMP)

demo: setup
	$(VENV)/bin/o3d-mvps demo --out out/demo --overwrite

# The suite includes tests/test_docs.py, which builds the docs site (--strict, network refused).
test: setup
	$(PY) -m pytest -q

# The documentation site (mkdocs-material + mkdocstrings) into site/; warnings are errors.
docs: setup
	NO_MKDOCS_2_WARNING=1 $(PY) -m mkdocs build --strict --quiet
	@echo "wrote site/ (open site/index.html)"

bench: setup
	$(PY) -m benchmarks all

# Open the notebooks in JupyterLab (they are saved with their outputs; tests/test_notebooks.py runs them).
notebooks: setup
	$(VENV)/bin/jupyter lab notebooks/

# Run every notebook top to bottom and save it with its outputs (commit the result); CI=1 saves
# the 3D views as static images (an interactive viewer is ~2 MB of output).
notebooks-run: setup
	CI=1 $(VENV)/bin/jupyter nbconvert --to notebook --execute --inplace --ExecutePreprocessor.timeout=300 notebooks/*.ipynb

clean:
	rm -rf $(VENV) out site .pytest_cache
