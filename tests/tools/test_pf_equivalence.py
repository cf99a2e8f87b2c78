"""tools/pf_equivalence.py: the paired tables of every recorded approximation against the exact tree."""

import pytest
from scriptload import load_script

pe = load_script("tools/pf_equivalence.py")


def _rec(case, seed, kernel, mse, rmse=1.0):
    return {"case": case, "seed": seed, "kernel": kernel, "window_mse": [mse, mse], "rmse": rmse, "p95": 2 * rmse,
            "shares": [100.0, 0.0, 0.0], "v2f_rows": 10, "step_s_mean": 0.5, "step_s_max": 1.0}


def test_tables_of_each_variant_and_the_arterial_limits():
    recs = {}
    for seed in (1, 2, 3):
        for kernel, mse in (("tree", 1.0 + 0.1 * seed), ("fast", 1.0 + 0.1 * seed + 0.01 * (-1) ** seed),
                            ("fast_component", 1.0 + 0.1 * seed)):
            recs[("single_road_df0.5", seed, kernel)] = _rec("single_road_df0.5", seed, kernel, mse)
    recs[("arterial", 1, "tree")] = _rec("arterial", 1, "tree", 0.0, rmse=1.00)
    recs[("arterial", 1, "fast")] = _rec("arterial", 1, "fast", 0.0, rmse=1.01)
    recs[("arterial", 1, "fast_component")] = _rec("arterial", 1, "fast_component", 0.0, rmse=1.03)
    lines, ok = pe.paired_table(recs)
    text = "\n".join(lines)
    assert "=== fast (pf.kernel = fast)" in text
    assert "=== fast_component (pf.kernel = fast, pf.bpa_stop = component)" in text
    art = [ln for ln in lines if ln.startswith("   1 ")]
    assert len(art) == 2 and art[0].rstrip().endswith("yes") and art[1].rstrip().endswith("NO")  # +1 % / +3 %
    assert not ok


def test_unknown_variant_is_refused(tmp_path):
    with pytest.raises(SystemExit) as exc:
        pe.main(["--variants", "fgt", "--table-only", "--out", str(tmp_path)])
    assert exc.value.code == 2


def test_arterial_floor_table_compares_the_reseeded_tree_with_the_tree():
    recs = {("arterial", 1, "tree"): _rec("arterial", 1, "tree", 0.0, rmse=1.00),
            ("arterial", 1, pe.NULL): _rec("arterial", 1, pe.NULL, 0.0, rmse=1.03),
            ("arterial", 2, pe.NULL): _rec("arterial", 2, pe.NULL, 0.0, rmse=1.0)}  # no tree run: not listed
    lines, _ = pe.paired_table(recs)
    i = next(k for k, ln in enumerate(lines) if "Monte Carlo floor" in ln and "arterial" in ln)
    rows = [ln for ln in lines[i + 2:] if ln.strip()[:1].isdigit()]
    assert len(rows) == 1 and rows[0].split()[0] == "1" and "+3.00%" in rows[0]
