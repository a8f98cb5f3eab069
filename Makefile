# compd — set-up, demo, tests. Everything is installed from this repository's own files.
SHELL := /bin/bash
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
BASE_STAMP := $(VENV)/.base-installed
TEST_STAMP := $(VENV)/.test-installed
# Debian packages the tests need (serial ptys, an independent Modbus client, the systemd units'
# verify and security checks, headless Chromium for compd report's page, the MQTT broker of the plant tests,
# dpkg-dev and lintian to build and check the Debian package); COMMAND:PACKAGE where the command is not named like its package.
APT_PACKAGES := socat mbpoll systemd-analyze:systemd chromium-headless-shell mosquitto dpkg-shlibdeps:dpkg-dev lintian
# ... and those installed without their recommends: LinuxCNC (linuxcnc-uspace; its recommends would bring a
# desktop). Its standalone G-code interpreter `rs274` reads compd testplan's programs back; the same package's
# `linuxcnc`, `halcmd`, `halrun` and Python modules (hal, linuxcnc: compd.io.hal_modules) run the headless sim
# mill of tests/linuxcnc/sim.py, so `rs274` stands for them all here
APT_PACKAGES_BARE := rs274:linuxcnc-uspace

.PHONY: venv demo test accept bench lint sysdeps clean install deb deb-twice docs reliability

$(BASE_STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e '.[plot,metrics,plant]'
	touch $@

$(TEST_STAMP): pyproject.toml $(BASE_STAMP)
	$(PY) -m pip install -q -e '.[test]'
	touch $@

venv: $(BASE_STAMP)

demo: $(BASE_STAMP)
	$(VENV)/bin/compd run configs/demo.yaml

sysdeps:
	@missing=""; for p in $(APT_PACKAGES); do command -v $${p%%:*} >/dev/null || missing="$$missing $${p##*:}"; done; \
	bare=""; for p in $(APT_PACKAGES_BARE); do command -v $${p%%:*} >/dev/null || bare="$$bare $${p##*:}"; done; \
	if [ -n "$$missing$$bare" ]; then \
	  echo "installing Debian packages:$$missing$$bare"; \
	  if [ "$$(id -u)" = 0 ]; then SUDO=""; else SUDO="sudo"; fi; \
	  $$SUDO apt-get update -qq || exit 1; \
	  if [ -n "$$missing" ]; then DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -qq $$missing >/dev/null || exit 1; fi; \
	  if [ -n "$$bare" ]; then DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -qq --no-install-recommends $$bare >/dev/null || exit 1; fi; \
	fi

# checkers of the standards compd speaks, that compd's code does not share, for the tests:
# promtool (`promtool check metrics`) from Debian's prometheus package, unpacked, not installed
PROMTOOL := build/tools/promtool
$(PROMTOOL):
	rm -rf build/tools/deb && mkdir -p build/tools/deb
	cd build/tools/deb && { apt-get download prometheus >/dev/null 2>&1 || \
	  { if [ "$$(id -u)" = 0 ]; then SUDO=""; else SUDO="sudo"; fi; $$SUDO apt-get update -qq && apt-get download prometheus >/dev/null 2>&1; }; }
	dpkg -x build/tools/deb/prometheus_*.deb build/tools/deb/x
	cp build/tools/deb/x/usr/bin/promtool $@
	rm -rf build/tools/deb

# Eclipse Tahu's Sparkplug B payload library (npm), pinned, to decode what compd publishes
TAHU := build/tools/node/node_modules/sparkplug-payload/package.json
$(TAHU):
	mkdir -p build/tools/node
	npm install --prefix build/tools/node --no-save --no-audit --no-fund --silent sparkplug-payload@1.0.3

# node-opcua's client (npm), pinned, an OPC UA stack that shares no code with compd's asyncua, to browse and
# read compd's server; in a prefix of its own (an `npm install --no-save` into Tahu's would remove Tahu)
NODE_OPCUA := build/tools/node-opcua/node_modules/node-opcua-client/package.json
$(NODE_OPCUA):
	mkdir -p build/tools/node-opcua
	npm install --prefix build/tools/node-opcua --no-save --no-audit --no-fund --silent \
	  node-opcua-client@2.186.4 node-opcua-certificate-manager@2.186.4

# the suite on one more worker than the machine has cores (pytest-xdist: most tests wait on compd's
# processes, sockets and brokers more than they compute; TEST_WORKERS=N to choose), the
# tests of tests/linuxcnc on one worker (tests/conftest.py's pytest_xdist_make_scheduler); the 25 slowest
# setups, calls and teardowns listed at the end. The checkout's byte code is compiled first: under
# PYTHONDONTWRITEBYTECODE=1 every `compd` and `hil_sim` process the tests start would compile it again
# (about 0.3 s of CPU each; Python reads the .pyc files whatever that variable says)
TEST_WORKERS ?= $(shell echo $$(( $$(nproc) + 1 )))
test: $(TEST_STAMP) sysdeps $(PROMTOOL) $(TAHU) $(NODE_OPCUA)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .
	$(VENV)/bin/lint-imports --no-cache
	$(VENV)/bin/mypy
	$(PY) -m compileall -q compd hil_sim rig
	$(PY) -m pytest -q -m "not accept and not bench" -n $(TEST_WORKERS) --dist loadgroup --durations=25

# the randomized family: 20 machines per type, fitted on a training day and replayed on an unseen one,
# gated on issue 40's goals with compd testplan's plan as each machine's training day, beside the
# drawn training day (not gated: the comparison) (scripts/family.py); closed loop on every machine's unseen day (issue 5):
# hil_sim serve + compd run over Modbus TCP; the vmc's spindle and column contributions summed on Z, in
# closed loop and with a sensor unplugged (issue 32, scripts/accept_contributions.py); then 200 telemetry
# publishers into one mosquitto for 10 min, and with the broker killed for 60 s (issue 20); the closed loop on a
# headless LinuxCNC over compd testplan's 24 h test beside the same plan in process (issue 41); the Debian
# packages built twice, the same bytes (issue 42, make deb-twice). Every step runs; any that fails fails accept.
accept: $(TEST_STAMP) sysdeps
	@status=0; \
	$(PY) scripts/family.py --seeds 1-20 --train plan --workdir build/accept/family-plan \
	  --json build/accept/family-plan.json --gate || status=1; \
	$(PY) scripts/family.py --seeds 1-20 --workdir build/accept/family --json build/accept/family.json || status=1; \
	$(PY) scripts/accept.py --json build/accept/results.json || status=1; \
	$(PY) scripts/accept_contributions.py --workdir build/accept/contributions \
	  --json build/accept/contributions.json || status=1; \
	$(PY) scripts/plant_scale.py --json build/accept/plant.json || status=1; \
	$(PY) scripts/plant_scale.py --duration-s 300 --outage-at-s 120 --outage-s 60 \
	  --workdir build/accept/plant_outage --json build/accept/plant_outage.json || status=1; \
	$(PY) scripts/accept_linuxcnc.py --workdir build/accept/linuxcnc --json build/accept/linuxcnc.json || status=1; \
	scripts/deb_twice.sh --out build/accept/deb-twice || status=1; \
	exit $$status

bench: $(TEST_STAMP) sysdeps
	$(PY) -m pytest -q -s -m bench tests/bench
	$(VENV)/bin/compd bench --cycles 20000 --json bench.json
	$(VENV)/bin/compd bench --cycles 20000 --scheduler fifo --json bench_fifo.json

# installs the service: venv (every runtime extra, with pip) under /opt/compd, /usr/bin/compd, systemd
# units, /etc/compd/compd.yaml, user compd. DESTDIR=/some/dir stages instead (no user, no systemctl;
# the staged files name only their final paths); PREFIX=... moves the venv, BINDIR=... the symlink.
install: $(BASE_STAMP)
	PYTHON="$(abspath $(PY))" scripts/install.sh

# builds build/compd_<version>-1_<arch>.deb, the daemon, and build/compd-commissioning_<version>-1_<arch>.deb
# (scripts/build_deb.sh, packaging/deb/; split.py's table decides which file goes where): `make install`
# staged at /opt/compd on Debian's python3, plus a postinst that creates the user and never starts compd
deb:
	scripts/build_deb.sh --out build

# builds both packages twice and compares their sha256: the same commit gives the same bytes (make accept runs it)
deb-twice:
	scripts/deb_twice.sh --out build/deb-twice

# regenerates the configuration reference from the config schema and the metrics reference
# from compd/service/metrics.py (tests check both are current)
docs: $(BASE_STAMP)
	$(VENV)/bin/compd docs --out docs/configuration.md
	$(VENV)/bin/compd docs --metrics --out docs/metrics.md

# reruns the fault-injection matrix and the lvr degraded-mode table into docs/reliability.md
reliability: $(TEST_STAMP) sysdeps
	rm -rf build/faults
	COMPD_FAULTS_OUT=build/faults $(PY) -m pytest -q tests/faults --ignore=tests/faults/test_reliability_doc.py
	$(PY) -m compd.commissioning.faultdoc build/faults --doc docs/reliability.md
	$(PY) scripts/degraded_table.py --doc docs/reliability.md

lint: $(TEST_STAMP)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .
	$(VENV)/bin/lint-imports --no-cache
	$(VENV)/bin/mypy

clean:
	rm -rf $(VENV) .pytest_cache build *.egg-info
