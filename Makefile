# All set-up lives here: a fresh machine needs only python3 (3.11) and make.
VENV  ?= .venv
PY    := $(VENV)/bin/python
STAMP := $(VENV)/.installed-stamp

.PHONY: install demo test bench clean

$(STAMP): pyproject.toml constraints.txt
	test -x $(PY) || python3 -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -c constraints.txt -e ".[dev]"
	touch $(STAMP)

install: $(STAMP)

# The main job on the embedded default: PyBullet on CPU -> labeled failure/success pairs -> shards,
# then one keyframe strip per failure type found (outputs/demo_strips/*.png).
demo: $(STAMP)
	$(PY) scripts/generate.py backend=pybullet num_episodes=48 out_dir=outputs/demo_shards seed=0 workers=2
	$(PY) scripts/render_strips.py outputs/demo_shards outputs/demo_strips

test: $(STAMP)
	$(PY) -m pytest -q tests

bench: $(STAMP)
	$(PY) scripts/bench_sim.py

clean:
	rm -rf outputs
