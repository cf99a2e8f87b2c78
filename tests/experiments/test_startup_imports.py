"""What `coloc` imports before it works: heavy libraries only for the configs and commands that use them.

Start-up: the command line imports no estimator library; ``coloc run`` reaches its first
simulation step without gtsam, dask, matplotlib, pandas, pyarrow or tqdm, and without the modules
of methods the config does not run. Each check runs in a fresh interpreter (``sys.modules`` of
this one holds whatever other tests imported). How long start-up takes is measured by
``bench/startup.py``, not here.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

PROJECT = Path(__file__).resolve().parents[2]

#: never imported by `import experiments.cli`, nor by `coloc run` up to its first step for a config
#: that runs none of the methods needing them
HEAVY = ("gtsam", "dask", "distributed", "matplotlib", "pandas", "pyarrow", "tqdm")
UNUSED_METHOD_MODULES = ("coloc.methods.infra", "coloc.methods.fg_topology", "coloc.methods.sme",
                         "coloc.methods.rsu_bp")


def _loaded(code: str, names: tuple[str, ...]) -> list[str]:
    """The modules of ``names`` that are in ``sys.modules`` after ``code`` ran in a fresh interpreter."""
    probe = f"{code}\nimport json, sys\nprint(json.dumps([m for m in {list(names)!r} if m in sys.modules]))"
    out = subprocess.run([sys.executable, "-c", probe], cwd=PROJECT, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_command_line_imports_no_heavy_library():
    assert _loaded("import experiments.cli", HEAVY + ("numba", "scipy", "libsumo")) == []


def test_run_modules_import_no_heavy_library():
    """The modules `coloc run` imports (config, runner, studies) leave the heavy ones to their use."""
    code = "import experiments.config, experiments.runner, experiments.studies"
    assert _loaded(code, HEAVY + UNUSED_METHOD_MODULES) == []


FIRST_STEP = """
import sys
from coloc.methods.registry import METHODS
from experiments.config import load_config
from experiments.runner import build_estimators, frame_source

cfg = load_config({config!r}, {{"run.duration_s": 10.0}})
source = frame_source(cfg)
estimators = build_estimators(cfg)
with source:
    for frame in source.frames():
        blind = frame.without_truth()
        for est in estimators:
            if METHODS[est.name].known_association:
                est.step_with_association(blind, frame.truth.v2f_feature)
            else:
                est.step(blind)
        if frame.n_vehicles:
            break
"""


@pytest.mark.parametrize("config", ["single_road.toml", "arterial_tlr.toml"])
def test_first_step_imports_no_heavy_library(config):
    """Up to the first step with vehicles (SUMO started, frames, estimators): none of the heavy
    libraries, none of the methods the config does not run."""
    code = FIRST_STEP.format(config=str(PROJECT / "experiments" / config))
    assert _loaded(code, HEAVY + UNUSED_METHOD_MODULES) == []
