# The README's two set-up commands: `make demo` and `make test`. Each installs everything it needs.
PYTHON ?= python3.11
VENV   ?= .venv
BIN    := $(VENV)/bin
SUDO   := $(shell [ "$$(id -u)" = 0 ] || echo sudo)
APT_DEMO := libusb-1.0-0
APT_TEST := libusb-1.0-0 chromium

.PHONY: demo test install clean

demo: $(VENV)/.installed
	@dpkg -s $(APT_DEMO) >/dev/null 2>&1 || { $(SUDO) apt-get update -qq && $(SUDO) apt-get install -y -qq $(APT_DEMO); }
	$(BIN)/mvrecon demo -o out/demo

test: $(VENV)/.installed
	@dpkg -s $(APT_TEST) >/dev/null 2>&1 || { $(SUDO) apt-get update -qq && $(SUDO) apt-get install -y -qq $(APT_TEST); }
	$(BIN)/python -m pytest -q -n 2 --dist loadscope  # 2 worker processes, each test module whole in one

install: $(VENV)/.installed

$(VENV)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	$(BIN)/pip install -q -e '.[dev]'
	$(BIN)/python -m compileall -q mvrecon  # as pip does for a non-editable install: every run starts faster
	touch $@

clean:
	rm -rf $(VENV) out
