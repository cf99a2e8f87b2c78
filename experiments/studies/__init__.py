"""Study configs of the other source papers (Fröhle, Zhang, Gulati): synthetic scenarios of their own.

A config with a top-level ``[study]`` table (``kind = "rsu_bp" | "sme" | "fg_topology"``) is run by
``coloc run CONFIG --out DIR [--seed N]`` through this module instead of the frame runner. Each study
module exposes ``run(data: dict, path: Path, out: Path, seed: int | None, progress: bool) -> dict``:
it validates ``data`` (an :class:`couplers.errors.InputError` naming ``path`` and the field on bad
input), writes its results into ``out`` atomically (config.toml fully resolved, summary.json,
results Parquet, report.html with figures) and returns the summary, whose ``"lines"`` entry is a list
of strings the command line prints.
"""

from __future__ import annotations

import importlib
from pathlib import Path

from couplers.errors import InputError

STUDY_MODULES = {
    "rsu_bp": "experiments.studies.rsu_bp",
    "sme": "experiments.studies.sme",
    "fg_topology": "experiments.studies.fg_topology",
}


def is_study(data: dict) -> bool:
    return "study" in data


def run_study(data: dict, path: Path, out: Path, seed: int | None = None, progress: bool = True,
              force: bool = False) -> dict:
    study = data["study"]
    if not isinstance(study, dict) or "kind" not in study:
        raise InputError(path, "study.kind", "missing (one of: " + ", ".join(STUDY_MODULES) + ")")
    kind = study["kind"]
    if kind not in STUDY_MODULES:
        raise InputError(path, "study.kind", f"unknown study {kind!r} (available: {', '.join(STUDY_MODULES)})")
    module = importlib.import_module(STUDY_MODULES[kind])
    return module.run(data, Path(path), Path(out), seed, progress, force)
