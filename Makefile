# ooi_seg_ros — the two commands a new user needs: `make demo` and `make test`.
PYTHON ?= python3
VENV := .venv
STAMP := $(VENV)/.installed
OUT ?= out
DEMO_BAG := bags/demo.mcap

.PHONY: setup demo test bench demo-bag lint clean

setup: $(STAMP)

$(STAMP): requirements.txt requirements-ros.txt setup.py tools/setup_env.sh
	@PYTHON=$(PYTHON) bash tools/setup_env.sh
	@touch $@

# The main job on the bundled bag: SfM -> segmentation -> object-only splat training.
demo: $(STAMP)
	$(VENV)/bin/ooi-seg run $(DEMO_BAG) --out $(OUT)/demo

test: $(STAMP)
	$(VENV)/bin/python -m pytest -q test

lint: $(STAMP)
	$(VENV)/bin/python -m flake8 ooi_seg_ros test benchmarks

bench: $(STAMP)
	@for b in benchmarks/bench_*.py; do echo "== $$b"; $(VENV)/bin/python $$b || exit 1; done

# Regenerates the bundled demo capture deterministically (same bytes on the same CPU type).
demo-bag: $(STAMP)
	$(VENV)/bin/ooi-seg simulate --scene aircraft --views 60 --size 320x240 --seed 0 \
		--out $(DEMO_BAG)

clean:
	rm -rf $(OUT) .pytest_cache
