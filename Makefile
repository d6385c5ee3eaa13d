# o3d_mvps — `make demo` and `make test` set everything up on a fresh machine.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

.PHONY: setup system-libs demo test bench clean

setup: system-libs $(STAMP)

# Open3D needs libusb-1.0 at import time. Install it with apt-get when we are root;
# otherwise stop and say exactly what to install.
system-libs:
	@if ! ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then \
	  if [ "$$(id -u)" = "0" ] && command -v apt-get >/dev/null 2>&1; then \
	    echo "Installing libusb-1.0-0 (needed by Open3D) with apt-get ..."; \
	    (apt-get install -y -q libusb-1.0-0 >/dev/null 2>&1 || \
	     (apt-get update -q >/dev/null && apt-get install -y -q libusb-1.0-0 >/dev/null)) || \
	    { echo "error: apt-get could not install libusb-1.0-0; install it by hand and rerun." >&2; exit 1; }; \
	  else \
	    echo "error: Open3D needs the system library libusb-1.0." >&2; \
	    echo "       Install it, e.g. 'sudo apt-get install libusb-1.0-0' (Debian/Ubuntu)," >&2; \
	    echo "       'sudo dnf install libusbx' (Fedora) or 'brew install libusb' (macOS), then rerun make." >&2; \
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
	$(VENV)/bin/o3d-mvps demo --out out/demo

test: setup
	$(PY) -m pytest -q

bench: setup
	$(VENV)/bin/o3d-mvps bench

clean:
	rm -rf $(VENV) out .pytest_cache
