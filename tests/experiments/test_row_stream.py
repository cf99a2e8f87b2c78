"""Rows streamed to spill files as the run goes (experiments.rowstream): the published Parquet files are
the bytes of the whole-table writer whatever the flush size, and the summary equals the one computed
from the whole tables (EstimateLog, the in-memory path)."""

import hashlib
import io
import json
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

from experiments import rowstream, runner
from experiments.config import load_config
from experiments.scoring import (
    association_by_group,
    association_summary,
    coverage_summary,
    feature_summary,
    method_summary,
    nees_summary,
)

PROJECT = Path(__file__).resolve().parents[2]
FILES = ("estimates.parquet", "association.parquet", "features.parquet")

CROSS = """
[run]
name = "cross"
seed = 2
duration_s = 40.0
methods = ["gnss", "icp_known_da", "icp_da_lc"]

[scenario]
kind = "crossroad"

[crossroad]
n_features = 10
"""


def _whole_table_outputs(log: runner.EstimateLog, cfg) -> tuple[dict[str, bytes], dict]:
    """The files and summary blocks as the runner made them from the whole tables (before streaming)."""
    methods = list(cfg.run.methods)
    estimates = log.table(cfg.run.name)
    scores = log.association_scores()
    features = log.feature_table(methods, scores)
    files = {}
    for name, df in (("estimates.parquet", estimates), ("association.parquet", log.association_table(methods, scores)),
                     ("features.parquet", features)):
        if name == "features.parquet" and not len(features):
            continue
        buf = io.BytesIO()
        runner.write_parquet(df, buf)
        files[name] = buf.getvalue()
    blocks, assoc = {}, {}
    for method in methods:
        rows = estimates[estimates["method"] == method]
        block = method_summary(rows)
        block["nees_pos"] = nees_summary(log.position_nees(method), rows["zone"].to_numpy())
        feat = features[features["method"] == method]["err_pos"].to_numpy()
        if feat.size:
            block["features"] = feature_summary(feat)
        blocks[method] = block
        if method in scores:
            assoc[method] = association_summary(*scores[method][1].sum(axis=0).tolist())
            assoc[method]["by_zone"] = association_by_group(
                [(a, f) for _, a, f in log.assoc_parts[method]], log.assoc_zone_parts[method], scores[method][2])
    out = {"methods": blocks, "association": assoc}
    if log.infra_parts:
        out["within_rsu_coverage"] = coverage_summary(estimates, methods)
    return files, out


def _run(cfg, out: Path, flush_rows: int, monkeypatch, reference: list | None = None) -> dict:
    """One run with ``flush_rows``; with ``reference``, an EstimateLog is fed the same steps and appended."""

    class Logged(rowstream.StreamLog):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, flush_rows=flush_rows)
            self.whole = runner.EstimateLog()
            if reference is not None:
                reference.append(self.whole)

        def add_truth(self, frame):
            super().add_truth(frame)
            self.whole.add_truth(frame)

        def add(self, method, est):
            super().add(method, est)
            self.whole.add(method, est)

        def add_association(self, method, frame, est):
            super().add_association(method, frame, est)
            self.whole.add_association(method, frame, est)

        def add_features(self, method, frame, est):
            super().add_features(method, frame, est)
            self.whole.add_features(method, frame, est)

    monkeypatch.setattr(runner, "StreamLog", Logged)
    return runner.run_experiment(cfg, out, progress=False, write_report=False)


def _summary_blocks(summary: dict) -> dict:
    """The summary blocks that come from the rows (the estimator seconds and comm tallies do not)."""
    methods = {m: {k: v for k, v in b.items() if k not in ("seconds", "comm", "stats")}
               for m, b in summary["methods"].items()}
    out = {"methods": methods, "association": summary["association"]}
    if "within_rsu_coverage" in summary:
        cov = json.loads(json.dumps(summary["within_rsu_coverage"]))
        for b in cov["methods"].values():
            b.pop("stats", None)
        out["within_rsu_coverage"] = cov
    return out


def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.fixture(scope="module")
def cross_cfg(tmp_path_factory):
    path = tmp_path_factory.mktemp("cfg") / "cross.toml"
    path.write_text(CROSS)
    return load_config(path)


def test_streamed_files_and_summary_equal_the_whole_tables(tmp_path, monkeypatch, cross_cfg):
    """Flushed every step, with row groups of 200 rows (the layout crosses method boundaries) and
    dictionary fallbacks: the three files are the whole-table writer's bytes at that row group size, and the summary
    blocks equal those computed from the whole tables (exactly: the same reductions)."""
    monkeypatch.setattr(rowstream, "ROW_GROUP", 200)
    # a dictionary page limit of 1 KiB: the float columns fall back to plain encoding within a row
    # group (the arterial hour's do at 1 MB), at a point that depends on how the rows are chunked
    options = {**rowstream.PARQUET_OPTIONS, "dictionary_pagesize_limit": 1024}
    monkeypatch.setattr(rowstream, "PARQUET_OPTIONS", options)
    monkeypatch.setattr(runner, "write_parquet", _write_parquet_row_groups(200, options))
    ref = []
    summary = _run(cross_cfg, tmp_path / "out", 1, monkeypatch, ref)
    files, blocks = _whole_table_outputs(ref[0], cross_cfg)
    assert set(files) == set(FILES)  # icp_da_lc pairs rows and has feature tracks: all three written
    md = pq.ParquetFile(tmp_path / "out" / "estimates.parquet").metadata
    assert md.num_row_groups > 3 and md.num_rows % 200 != 0
    for name, data in files.items():
        assert (tmp_path / "out" / name).read_bytes() == data, name
    assert _summary_blocks(summary) == blocks
    assert not (tmp_path / "out" / ".rows").exists()


def _write_parquet_row_groups(n: int, options: dict):
    def write(df, path):
        import pyarrow as pa

        table = pa.Table.from_pandas(df, preserve_index=False).replace_schema_metadata(None)
        pq.write_table(table, path, row_group_size=n, **options)
    return write


def test_files_do_not_depend_on_the_flush_size(tmp_path, monkeypatch, cross_cfg):
    """Flushed every step, every 37 rows, and once at the end: the same bytes and summary blocks
    (twice the same flush size: the same bytes, determinism)."""
    hashes, blocks = [], []
    for k, flush in enumerate((1, 37, 10**9, 1)):
        summary = _run(cross_cfg, tmp_path / f"out{k}", flush, monkeypatch)
        hashes.append({name: _sha(tmp_path / f"out{k}" / name) for name in FILES})
        blocks.append(_summary_blocks(summary))
    assert all(h == hashes[0] for h in hashes) and all(b == blocks[0] for b in blocks)


@pytest.mark.parametrize("config, seconds", [
    ("arterial_tlr.toml", 60.0),  # GNSS zones and areas, V2F clutter
    ("arterial_tlr_infra.toml", 30.0),  # covered / rsu columns, summary["within_rsu_coverage"]
    ("arterial_ped_tlr.toml", 30.0),  # pedestrian features: appear, move and leave
])
def test_short_arterial_runs_equal_the_whole_tables(tmp_path, monkeypatch, config, seconds):
    """Shipped SUMO configs, flushed every 300 rows: estimates / association / features bytes and the
    summary blocks equal the whole-table path."""
    cfg = load_config(PROJECT / "experiments" / config, {"run.duration_s": seconds})
    ref = []
    summary = _run(cfg, tmp_path / "out", 300, monkeypatch, ref)
    files, blocks = _whole_table_outputs(ref[0], cfg)
    assert "estimates.parquet" in files
    for name in FILES:
        assert (tmp_path / "out" / name).exists() == (name in files), name
    for name, data in files.items():
        assert (tmp_path / "out" / name).read_bytes() == data, name
    assert _summary_blocks(summary) == blocks
    assert len(next(iter(blocks["methods"].values()))["by_area"]) > 1
    assert ("within_rsu_coverage" in blocks) == ("infra" in config)


def test_pair_counts_merged_per_flush_give_the_labels_of_the_whole_run():
    """Pair counts summed over chunks, then labelled, equal scoring.track_labels on all rows (ties too)."""
    from experiments.scoring import labels_from_pairs, track_labels

    rng = np.random.default_rng(5)
    track = rng.integers(0, 30, 5000)
    feature = rng.integers(-1, 6, 5000)
    acc = (np.empty((0, 2), dtype=np.int64), np.empty(0, dtype=np.int64))
    for lo in range(0, 5000, 777):
        acc = rowstream._merge_pair_counts(acc, track[lo:lo + 777], feature[lo:lo + 777])
    assert labels_from_pairs(*acc) == track_labels(track, feature)
    assert int(acc[1].sum()) == 5000
