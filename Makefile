# Two commands on a fresh machine: `make demo` and `make test`.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
DEMO_OUT ?= demo-out
ACCURACY_OUT ?= accuracy-out
JOBS ?= 2
# Test files run on this many processes (a file's tests stay together: module fixtures
# are built once); most of the suite's wall time is real-time daemon runs that wait.
TEST_JOBS ?= 2

.PHONY: demo test lint typecheck pytest chromium accuracy paper fuzz overload navloss soak page-bench clean

$(STAMP): pyproject.toml Makefile
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[test]'
	# The independent Oculus log reader for the compatibility test; its own requirements
	# pin the GUI build of OpenCV, which would clash with opencv-python-headless.
	$(BIN)/python -m pip install --quiet --no-deps 'oculus-python==0.0.2a1'
	touch $(STAMP)

DEMO_WEB ?= 127.0.0.1:8080
demo: $(STAMP)
	$(BIN)/seamap demo --out $(DEMO_OUT) --web $(DEMO_WEB)

test: $(STAMP) lint typecheck pytest

lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/lint-imports

typecheck: $(STAMP)
	$(BIN)/mypy

pytest: $(STAMP) chromium
	$(BIN)/pytest -q -n $(TEST_JOBS) --dist loadfile

# The live map page's browser tests run Debian's Chromium (Playwright's own download needs
# the internet); as root, install it when missing. Without it those tests skip, saying why.
chromium:
	@if [ "$$(id -u)" = 0 ] && [ ! -x /usr/bin/chromium ]; then \
		(apt-get update -qq && apt-get install -y -qq --no-install-recommends chromium) \
			>/dev/null 2>&1 || echo "chromium not installed: the browser tests will skip"; \
	fi

# The accuracy matrix: simulated surveys replayed in every mode (hours; not in `make test`).
accuracy: $(STAMP)
	$(BIN)/python -m tools.accuracy --out $(ACCURACY_OUT) --jobs $(JOBS)

# The paper's Tables I-V by `seamap evaluate` over simulated quadrat surveys, beside the
# paper's numbers (paper-out/summary.md; about 15 minutes a survey on one core).
PAPER_OUT ?= paper-out
paper: $(STAMP)
	$(BIN)/python -m tools.paper --out $(PAPER_OUT) --jobs $(JOBS)

# Fuzzing at depth: the framer and message parsers, the log readers (.oculus v1/v2, .tlog,
# .bin) and the config loader, FUZZ_EXAMPLES generated and mutated inputs each (not in
# `make test`, which runs the same tests with a few hundred).
FUZZ_EXAMPLES ?= 100000
fuzz: $(STAMP)
	SEAMAP_FUZZ_EXAMPLES=$(FUZZ_EXAMPLES) $(BIN)/pytest -q -m fuzz -n $(TEST_JOBS) -p no:cacheprovider

# The daemon under overload: 40 Hz pings, its core shared with a CPU hog (a minute; the
# figures go in the notes, not a test).
overload: $(STAMP)
	$(BIN)/python -m tools.overload --out overload-out

# The autopilot link silent for 30 s (and 120 s) mid-survey: the live map and the survey-end
# pass against the truth, 7 surveys by 3 places (about 20 minutes on 2 cores).
navloss: $(STAMP)
	$(BIN)/python -m tools.navloss --out navloss-out --jobs $(JOBS) --where turn mid start
	$(BIN)/python -m tools.navloss --out navloss-out/120s --jobs $(JOBS) --where turn mid --gap 120 \
		--surveys quadrats-s5-2hz quadrats-s1

# The daemon for hours: the two-hour hectare played at 4x, its memory, descriptors and
# threads sampled through the survey-end pass (hours, and about 40 GB of disk).
soak: $(STAMP)
	$(BIN)/python -m tools.soak --out soak-out

# The shore's live map page at a hectare's tiles (400 at 256 px x 2 cm) in headless Chromium:
# load time of the whole site and the browser's memory (a few minutes; not in `make test`).
page-bench: $(STAMP) chromium
	$(BIN)/python -m tools.page_bench

clean:
	rm -rf $(VENV) build *.egg-info .mypy_cache .pytest_cache .ruff_cache .import_linter_cache $(DEMO_OUT) overload-out navloss-out soak-out $(PAPER_OUT)
