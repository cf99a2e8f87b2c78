"""A run's rows streamed to disk as the run goes: estimates, association and feature rows.

The runner hands every step's truth and estimates to :class:`StreamLog`; every ``flush_rows`` buffered
rows (and at the end) they go to spill files in a folder of the run's staging folder, one Arrow IPC
stream per method and kind, as record batches. Memory in the loop is one flush of rows, whatever
the run's length. After the loop, :meth:`StreamLog.finish` reads the spill files back batch by
batch and writes the published files, then removes the spill folder.

The published files are the bytes the whole-table writer gave (``pq.write_table`` of the concatenated
table; :class:`EstimateLog` of :mod:`experiments.runner` is that in-memory path, kept as the
reference of the tests): the same rows in the same order (method by method, each in step order),
the same schema, and row groups of :data:`ROW_GROUP` rows. Parquet pages do not depend on how the
rows of a row group were split in memory once each column is one contiguous array (a float
column's dictionary outgrows its 1 MB limit and the writer falls back to plain encoding at a point
that depends on the chunks; checked with pyarrow 23), so the files are written through a buffer of
one row group, made contiguous before it is written (two row groups in memory for that moment,
about 2 x 220 MB of estimates rows).

The summary blocks are computed from the spill files, equal to the whole-table ones, bit for bit
(:mod:`experiments.streamstats`: numpy's pairwise sums in numpy's order, the percentiles from the
values of their histogram bins), each method's file read twice, batch by batch: memory after the loop
does not grow with the rows:

* estimates: err_pos, err_vel, err_along, err_cross and the position NEES (computed per flush by
  :func:`position_nees` from the file's var_px, var_py, cov_pxy), per method, per zone and per area
  (under ``[infra]`` on the covered rows, per area and per RSU);
* association: the (track, true feature) pair counts are summed per flush (the track labels come
  from the counts only), then the spilled V2F rows are scored batch by batch: per step counts (24
  bytes per step and method) and per-zone counts;
* feature errors: the spilled track rows are scored batch by batch with the labels, twice. The true
  feature positions are kept in memory only when they change (static landmarks: once; moving or
  appearing features: one copy per step, as before).
"""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from coloc.core.frame import Frame, StepEstimate
from experiments.scoring import (
    label_arrays,
    labelled,
    labels_from_pairs,
    scored_mask,
    DETECTION_KINDS,
    detection_kinds,
    _correct_rows,
    along_cross_errors,
    association_summary,
)
from experiments.streamstats import Sample

if TYPE_CHECKING:
    import pandas as pd
    import pyarrow as pa

# Vehicle-steps, V2F rows and feature-track rows buffered before they go to the spill files
# (64 Ki rows: about 14 MB of estimates rows per method).
FLUSH_ROWS = 1 << 16
# Rows per row group of the published files: pq.write_table's default (1024 * 1024), the layout the
# files had when they were written from the whole table.
ROW_GROUP = 1 << 20
# The options of experiments.runner.write_parquet (the defaults of pq.write_table otherwise).
PARQUET_OPTIONS = {"compression": "zstd", "write_statistics": True}

ESTIMATE_EXTRA = ("nees",)  # spilled beside the estimates.parquet columns, for the summary only
FEATURE_COLUMNS = {"method": "string", "t": "float64", "track": "int64", "feature": "int64", "err_pos": "float64"}


def position_nees(ex: np.ndarray, ey: np.ndarray, var_px: np.ndarray, var_py: np.ndarray,
                  cov_pxy: np.ndarray) -> np.ndarray:
    """2-D position NEES e^T P^-1 e per sample, P = [[var_px, cov_pxy], [cov_pxy, var_py]] (2 on average for
    a consistent estimator; NaN or inf where P is singular). From estimates.parquet:
    ``position_nees(px - px_true, py - py_true, var_px, var_py, cov_pxy)``."""
    det = var_px * var_py - cov_pxy * cov_pxy
    with np.errstate(divide="ignore", invalid="ignore"):
        return (var_py * ex * ex - 2.0 * cov_pxy * ex * ey + var_px * ey * ey) / det


def estimate_rows(run_name: str, method: str, truth: tuple, infra: tuple | None, est: tuple) -> pd.DataFrame:
    """The estimates.parquet rows of one method over some steps (docs/outputs.md), built once for the
    streamed log and for :class:`experiments.runner.EstimateLog`. ``truth``: (t, vehicle, x_true, heading,
    zone, area) concatenated over the steps (vehicle, zone and area as str); ``infra``: (covered, rsu) or
    None; ``est``: (mean (R, 4), var_px, var_py, cov_pxy) of the method in the same rows."""
    import pandas as pd

    t, vid, x_true, heading, zone, area = truth
    mean, vx_, vy_, cxy = est
    err = mean - x_true
    along, cross = along_cross_errors(err[:, :2], heading)
    infra_cols = {} if infra is None else {"covered": infra[0].astype(bool), "rsu": infra[1].astype(str)}
    return pd.DataFrame(
        {
            "run": run_name,
            "method": method,
            "t": t,
            "vehicle": vid,
            "px": mean[:, 0], "py": mean[:, 1], "vx": mean[:, 2], "vy": mean[:, 3],
            "px_true": x_true[:, 0], "py_true": x_true[:, 1],
            "vx_true": x_true[:, 2], "vy_true": x_true[:, 3],
            "err_pos": np.hypot(err[:, 0], err[:, 1]),
            "err_vel": np.hypot(err[:, 2], err[:, 3]),
            "err_along": along, "err_cross": cross,
            "zone": zone, "area": area,
            "var_px": vx_, "var_py": vy_, "cov_pxy": cxy,
            **infra_cols,
        }
    )


def concat_steps(truth_parts: list, infra_parts: list) -> tuple[tuple, tuple | None]:
    """The per-step truth parts (t, vehicle ids, x_true, heading, zone, area) and infrastructure parts
    (covered, home RSU) concatenated for :func:`estimate_rows`, the strings as str once for every method."""
    t, vid, x_true, heading, zone, area = (np.concatenate(c) for c in zip(*truth_parts))
    infra = tuple(np.concatenate(c) for c in zip(*infra_parts)) if infra_parts else None
    return (t, vid.astype(str), x_true, heading, zone.astype(str), area.astype(str)), infra


def _arrow_table(df: pd.DataFrame) -> pa.Table:
    """The Arrow table :func:`experiments.runner.write_parquet` makes of a frame."""
    import pyarrow as pa

    return pa.Table.from_pandas(df, preserve_index=False).replace_schema_metadata(None)


class _Spill:
    """One Arrow IPC stream file (lz4 frames), appended to as the run goes and read back batch by batch."""

    def __init__(self, path: Path):
        self.path = path
        self.rows = 0
        self._sink = None
        self._writer = None

    def write(self, table: pa.Table) -> None:
        import pyarrow as pa

        if table.num_rows == 0:
            return
        if self._writer is None:
            self._sink = pa.OSFile(str(self.path), "wb")
            self._writer = pa.ipc.new_stream(self._sink, table.schema,
                                             options=pa.ipc.IpcWriteOptions(compression="lz4"))
        self._writer.write_table(table)
        self.rows += table.num_rows

    def close(self) -> None:
        if self._writer is not None:
            self._writer.close()
            self._sink.close()
            self._writer = self._sink = None

    def batches(self):
        """The record batches written, in order (none if nothing was written)."""
        import pyarrow as pa

        self.close()
        if not self.path.exists():
            return
        with pa.OSFile(str(self.path), "rb") as f:
            yield from pa.ipc.open_stream(f)


class RowGroupWriter:
    """A Parquet file written as :func:`experiments.runner.write_parquet` writes a whole table (zstd,
    statistics, row groups of :data:`ROW_GROUP` rows), from tables appended in row order; holds at
    most one row group and one appended table. Nothing is written when no row comes."""

    def __init__(self, path: Path):
        self.path = path
        self.rows = 0
        self._parts: list = []
        self._buffered = 0
        self._writer = None

    def append(self, table: pa.Table) -> None:
        if table.num_rows == 0:
            return
        self._parts.append(table)
        self._buffered += table.num_rows
        self.rows += table.num_rows
        while self._buffered >= ROW_GROUP:
            self._write(ROW_GROUP)

    def _write(self, n: int) -> None:
        import pyarrow as pa
        import pyarrow.parquet as pq

        buffered = pa.concat_tables(self._parts)
        # One contiguous array per column, as the whole table had: where a column's dictionary outgrows
        # its limit (float columns), the writer falls back to plain encoding at a point that depends
        # on the chunks it is given.
        head = buffered.slice(0, n).combine_chunks()
        rest = buffered.slice(n)
        self._parts = [rest] if rest.num_rows else []
        self._buffered = rest.num_rows
        del buffered
        if self._writer is None:
            self._writer = pq.ParquetWriter(str(self.path), head.schema, **PARQUET_OPTIONS)
        self._writer.write_table(head, row_group_size=ROW_GROUP)

    def close(self) -> None:
        if self._buffered:
            self._write(self._buffered)
        if self._writer is not None:
            self._writer.close()
            self._writer = None


class _Codes:
    """Small integer codes of a few distinct strings (GNSS zones, areas, RSU ids), in first-seen order."""

    def __init__(self):
        self.names: list[str] = []
        self._index: dict[str, int] = {}

    def encode(self, values) -> np.ndarray:
        values = np.asarray(values).astype(str)
        if values.size == 0:
            return np.empty(0, dtype=np.int32)
        uniq, inv = np.unique(values, return_inverse=True)
        codes = np.array([self._index.setdefault(u, len(self._index)) for u in uniq.tolist()], dtype=np.int32)
        self.names = list(self._index)
        return codes[inv.reshape(-1)]

    def categorical(self, codes: np.ndarray):
        """``codes`` as a pandas Categorical whose categories are sorted, so that a sorted groupby
        visits the groups in the order of the strings."""
        import pandas as pd

        order = sorted(range(len(self.names)), key=lambda i: self.names[i])
        rank = np.empty(len(order), dtype=np.int32)
        rank[order] = np.arange(len(order), dtype=np.int32)
        return pd.Categorical.from_codes(rank[codes] if codes.size else codes, [self.names[i] for i in order])


def _merge_pair_counts(acc: tuple[np.ndarray, np.ndarray], track: np.ndarray, feature: np.ndarray):
    """(pairs (P, 2), counts (P,)) of distinct (track, feature) pairs, with ``track``/``feature`` rows added."""
    pairs = np.concatenate([acc[0], np.stack([track, feature], axis=1)])
    counts = np.concatenate([acc[1], np.ones(track.size, dtype=np.int64)])
    if pairs.shape[0] == 0:
        return acc
    order = np.lexsort((pairs[:, 1], pairs[:, 0]))
    pairs, counts = pairs[order], counts[order]
    first = np.ones(pairs.shape[0], dtype=bool)
    first[1:] = (pairs[1:, 0] != pairs[:-1, 0]) | (pairs[1:, 1] != pairs[:-1, 1])
    starts = np.flatnonzero(first)
    return pairs[starts], np.add.reduceat(counts, starts)


def association_rows(method: str, frame: Frame, est: StepEstimate):
    """(assignment (O,), true feature (O,), GNSS zone of each row's vehicle (O,)) of the V2F rows of a method
    that reports a pairing, else None; a pairing of the wrong shape raises ValueError."""
    if est.v2f_assignment is None:
        return None
    assign = np.asarray(est.v2f_assignment, dtype=np.int64)
    truth = np.asarray(frame.truth.v2f_feature, dtype=np.int64)
    if assign.shape != truth.shape:
        raise ValueError(f"{method}: v2f_assignment has shape {assign.shape}, the frame has {truth.shape[0]} V2F rows")
    return assign, truth, np.asarray(frame.truth.zone)[np.asarray(frame.v2f_owner)]


class StreamLog:
    """Per-step rows of one run, streamed to spill files in ``folder`` (created; removed by
    :meth:`finish` or :meth:`discard`). ``methods``: the order of the methods in the files."""

    def __init__(self, folder: Path, run_name: str, methods: list[str], flush_rows: int | None = None):
        self.folder = Path(folder)
        self.folder.mkdir()
        self.run_name = run_name
        self.methods = list(methods)
        self.flush_rows = FLUSH_ROWS if flush_rows is None else int(flush_rows)
        self.vehicle_steps = 0
        # [analysis] warmup_s: the summaries score rows with t >= scored_from only (None: every row); the files
        # keep every row (experiments.scoring.scored_mask)
        self.scored_from: float | None = None
        # V2F rows by what they truly are (experiments.runner DETECTION_KINDS order), summed over the run
        self.kind_counts = np.zeros(len(DETECTION_KINDS), dtype=np.int64)
        self.infra = False
        self.zones, self.areas, self.rsus = _Codes(), _Codes(), _Codes()
        self._truth: list = []
        self._infra: list = []
        self._est: dict[str, list] = {}
        self._assoc: dict[str, list] = {}
        self._tracks: dict[str, list] = {}
        self._buffered = 0
        self._est_spill: dict[str, _Spill] = {}
        self._assoc_spill: dict[str, _Spill] = {}
        self._track_spill: dict[str, _Spill] = {}
        # association: per method, t of every step with a V2F pairing and the (track, feature) pair counts
        self._assoc_t: dict[str, list] = {}
        self._pairs: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        # true feature positions (K, 2), a new copy only when they change
        self._feature_truth: list[np.ndarray] = []

    # ----------------------------------------------------------------- the loop
    def add_truth(self, frame: Frame) -> None:
        if self._buffered >= self.flush_rows:
            self.flush()
        tr = frame.truth
        self.kind_counts += detection_kinds(tr)
        self._truth.append((np.full(frame.n_vehicles, frame.t), frame.vehicle_ids, tr.x_true, tr.heading, tr.zone,
                            tr.area))
        self._buffered += frame.n_vehicles
        self.vehicle_steps += frame.n_vehicles
        if frame.infra is not None:
            from coloc.methods.infra import home_rsu

            self.infra = True
            home = home_rsu(frame.infra.v2i) if frame.n_vehicles else np.empty(0, dtype=np.int64)
            names = np.append(frame.infra.rsu_ids.astype(str), "")[home]
            self._infra.append((home >= 0, names))

    def add(self, method: str, est: StepEstimate) -> None:
        self._est.setdefault(method, []).append((est.mean, est.cov[:, 0, 0], est.cov[:, 1, 1], est.cov[:, 0, 1]))

    def add_association(self, method: str, frame: Frame, est: StepEstimate) -> None:
        """Keep the V2F pairing of a method that reports one, with the truth, for scoring at the end."""
        rows = association_rows(method, frame, est)
        if rows is None:
            return
        assign, truth, zone = rows
        steps = self._assoc_t.setdefault(method, [])
        self._assoc.setdefault(method, []).append((len(steps), assign, truth, zone))
        steps.append(frame.t)
        self._buffered += assign.size

    def add_features(self, method: str, frame: Frame, est: StepEstimate) -> None:
        """Feature-track estimates; scored against the truth once the track labels are known."""
        if est.feature_mean is None or est.feature_track_ids is None or est.feature_mean.shape[0] == 0:
            return
        ids = np.asarray(est.feature_track_ids, dtype=np.int64)
        truth_xy = frame.truth.features_true[:, :2]
        last = self._feature_truth[-1] if self._feature_truth else None
        if last is None or last.shape != truth_xy.shape or not np.array_equal(last, truth_xy, equal_nan=True):
            self._feature_truth.append(truth_xy.copy())
        self._tracks.setdefault(method, []).append(
            (frame.t, ids, est.feature_mean[:, :2].copy(), len(self._feature_truth) - 1))
        self._buffered += ids.size

    def flush(self) -> None:
        """Write the buffered steps to the spill files."""
        import pandas as pd
        import pyarrow as pa

        if self._truth:
            truth, infra = concat_steps(self._truth, self._infra)
            x_true = truth[2]
            for method, parts in self._est.items():
                est = tuple(np.concatenate(c) for c in zip(*parts))
                df = estimate_rows(self.run_name, method, truth, infra, est)
                mean = est[0]
                df["nees"] = position_nees(mean[:, 0] - x_true[:, 0], mean[:, 1] - x_true[:, 1], *est[1:])
                self._spill(self._est_spill, "estimates", method).write(_arrow_table(df))
        for method, parts in self._assoc.items():
            step = np.concatenate([np.full(a.size, s, dtype=np.int64) for s, a, _, _ in parts])
            assign = np.concatenate([a for _, a, _, _ in parts])
            truth = np.concatenate([f for _, _, f, _ in parts])
            zone = self.zones.encode(np.concatenate([z.astype(str) for _, _, _, z in parts]))
            kept = assign >= 0
            acc = self._pairs.get(method, (np.empty((0, 2), dtype=np.int64), np.empty(0, dtype=np.int64)))
            self._pairs[method] = _merge_pair_counts(acc, assign[kept], truth[kept])
            self._spill(self._assoc_spill, "association", method).write(
                pa.table({"step": step, "assign": assign, "truth": truth, "zone": zone}))
        for method, parts in self._tracks.items():
            self._spill(self._track_spill, "tracks", method).write(pa.table({
                "t": np.concatenate([np.full(ids.size, t) for t, ids, _, _ in parts]),
                "track": np.concatenate([ids for _, ids, _, _ in parts]),
                "x": np.concatenate([xy[:, 0] for _, _, xy, _ in parts]),
                "y": np.concatenate([xy[:, 1] for _, _, xy, _ in parts]),
                "truth": np.concatenate([np.full(ids.size, v, dtype=np.int64) for _, ids, _, v in parts]),
            }))
        self._truth, self._infra, self._est, self._assoc, self._tracks = [], [], {}, {}, {}
        self._buffered = 0

    def _spill(self, spills: dict, kind: str, method: str) -> _Spill:
        if method not in spills:
            spills[method] = _Spill(self.folder / f"{kind}-{len(spills)}.arrows")
        return spills[method]

    # ----------------------------------------------------------------- after the loop
    @property
    def rows(self) -> int:
        """Estimates rows spilled (all methods)."""
        return sum(s.rows for s in self._est_spill.values())

    def association_scores(self) -> dict[str, tuple[np.ndarray, np.ndarray, dict[int, int]]]:
        """method -> (t (S,), counts (S, 3) [correct, wrong, discarded], track labels), as
        :meth:`experiments.runner.EstimateLog.association_scores`; with :attr:`association_by_zone`."""
        out = {}
        self.association_by_zone = {}
        for method, steps in self._assoc_t.items():
            pairs = self._pairs.get(method, (np.empty((0, 2), dtype=np.int64), np.empty(0, dtype=np.int64)))
            labels = labels_from_pairs(*pairs)
            n = len(steps)
            counts = np.zeros((n, 3), dtype=np.int64)
            by_zone = np.zeros((len(self.zones.names), 3), dtype=np.int64)
            for batch in self._assoc_spill[method].batches() if method in self._assoc_spill else ():
                step, assign, truth, zone = (batch.column(c).to_numpy() for c in ("step", "assign", "truth", "zone"))
                correct = _correct_rows(assign, truth, labels)
                kept = assign >= 0
                scored = scored_mask(np.asarray(steps, dtype=float)[step], self.scored_from)
                for j, sel in enumerate((correct, kept & ~correct, ~kept)):
                    counts[:, j] += np.bincount(step[sel], minlength=n)
                    by_zone[:, j] += np.bincount(zone[sel & scored], minlength=len(self.zones.names))
            out[method] = (np.array(steps, dtype=float), counts, labels)
            seen = by_zone.sum(axis=1) > 0
            self.association_by_zone[method] = {
                self.zones.names[i]: association_summary(*by_zone[i].tolist())
                for i in sorted(np.flatnonzero(seen).tolist(), key=lambda i: self.zones.names[i])}
        return out

    def write_estimates(self, path: Path) -> dict:
        """Write estimates.parquet; returns per method its summary blocks (method_summary with
        ``nees_pos``) and, under ``[infra]``, summary["within_rsu_coverage"] as ``"_coverage"``."""
        import pyarrow as pa

        from experiments.streamstats import EstimateStats

        out = RowGroupWriter(path)
        blocks: dict = {}
        coverage = {"methods": {}, "rsu_vehicle_steps": {}}
        for method in self.methods:
            if method not in self._est_spill:
                continue
            stats = EstimateStats(self.infra)
            # two passes over the method's spill file: the first writes the rows and counts (sizes,
            # histograms), the second sums in numpy's order and keeps the values at the percentiles
            # (experiments.streamstats): the statistics of the whole array, in memory independent of the rows
            for second in (False, True):
                for batch in self._est_spill[method].batches():
                    if not second:
                        names = [c for c in batch.schema.names if c not in ESTIMATE_EXTRA]
                        out.append(pa.Table.from_batches([batch.select(names)]))
                    stats.feed(self._scored_columns(batch), second)
            block, cov, rsu_steps = stats.blocks(self.zones.names, self.areas.names, self.rsus.names)
            blocks[method] = block
            if self.infra:
                coverage["methods"][method] = cov
                if method == self.methods[0]:
                    coverage["rsu_vehicle_steps"] = rsu_steps
        out.close()
        if self.infra:
            blocks["_coverage"] = coverage
        return blocks

    def _scored_columns(self, batch) -> dict:
        """The columns of an estimates spill batch the statistics need, on the scored rows only
        ([analysis] warmup_s); zone, area and rsu as codes of :class:`_Codes`."""
        cols = {c: batch.column(c).to_numpy() for c in ("err_pos", "err_vel", "err_along", "err_cross", "nees")}
        cols["zone"] = self.zones.encode(batch.column("zone").to_numpy(zero_copy_only=False))
        cols["area"] = self.areas.encode(batch.column("area").to_numpy(zero_copy_only=False))
        if self.infra:
            cols["covered"] = batch.column("covered").to_numpy(zero_copy_only=False)
            cols["rsu"] = self.rsus.encode(batch.column("rsu").to_numpy(zero_copy_only=False))
        if self.scored_from is not None:
            scored = scored_mask(batch.column("t").to_numpy(), self.scored_from)
            cols = {c: v[scored] for c, v in cols.items()}
        return cols

    def write_features(self, path: Path, scores: dict, known: frozenset) -> dict[str, dict]:
        """Write features.parquet (not written when there is no row; the rules of
        :meth:`experiments.runner.EstimateLog.feature_table`); returns method -> summary["features"]."""
        import pandas as pd

        out = RowGroupWriter(path)
        blocks = {}
        sizes = np.array([v.shape[0] for v in self._feature_truth], dtype=np.int64)
        for m in self.methods:
            if m not in self._track_spill:
                continue
            if m in known:
                label_of = None
            elif m in scores:
                label_of = label_arrays(scores[m][2])
                if label_of[0].size == 0:
                    continue
            else:
                continue  # tracks without any pairing cannot be scored
            sample = Sample(quantiles=(0.95,))
            # two passes (experiments.streamstats): the first writes the rows and counts, the second sums
            for second in (False, True):
                for t, ids, feat, err in self._scored_tracks(m, label_of, sizes):
                    scored = err[scored_mask(t, self.scored_from)]  # [analysis] warmup_s: the scored rows
                    if second:
                        sample.second(scored)
                        continue
                    sample.first(scored)
                    out.append(_arrow_table(pd.DataFrame({
                        "method": np.full(err.size, m, dtype=object), "t": t, "track": ids, "feature": feat,
                        "err_pos": err}).astype(FEATURE_COLUMNS)))
            if sample.n:
                sample.finish()
                # experiments.scoring.feature_summary
                blocks[m] = {"rmse_pos_m": sample.rmse(), "p95_pos_m": sample.quantile(0.95), "n": int(sample.n)}
        out.close()
        return blocks

    def _scored_tracks(self, m: str, label_of, sizes: np.ndarray):
        """Per spill batch of method ``m``'s feature tracks: (t, track, feature, err_pos) of the rows that
        can be scored (the rules of :meth:`write_features`)."""
        for batch in self._track_spill[m].batches():
            t, ids, x, y, version = (batch.column(c).to_numpy() for c in ("t", "track", "x", "y", "truth"))
            if label_of is None:
                feat = ids
                ok = np.ones(ids.size, dtype=bool)
            else:
                ok, feat = labelled(ids, *label_of)
            # SUMO pedestrians: a label registered after this step (couplers.sensing.pedestrians)
            ok &= feat < sizes[version]
            tx = np.full((ids.size, 2), np.nan)
            for v in np.unique(version[ok]).tolist():
                sel = ok & (version == v)
                tx[sel] = self._feature_truth[v][feat[sel]]
            # SUMO pedestrians: a person that has left (NaN state) has no error to score
            ok &= np.isfinite(tx).all(axis=1)
            if not ok.any():
                continue
            ex, ey = x[ok] - tx[ok, 0], y[ok] - tx[ok, 1]
            yield t[ok], ids[ok], feat[ok], np.hypot(ex, ey)

    def discard(self) -> None:
        """Close and remove the spill files."""
        for spills in (self._est_spill, self._assoc_spill, self._track_spill):
            for s in spills.values():
                s.close()
        shutil.rmtree(self.folder, ignore_errors=True)

