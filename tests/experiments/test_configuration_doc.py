"""docs/configuration.md is generated from the config schema and documents every accepted key."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest

from couplers.errors import InputError
from experiments import configdoc
from experiments.config import OPTIONAL_SECTIONS, SECTIONS, config_from_dict


def test_committed_page_is_what_the_generator_writes():
    assert configdoc.DOC_PATH.read_text() == configdoc.render(), (
        "docs/configuration.md is stale: run `python -m experiments.configdoc`")


def test_every_key_the_loader_accepts_is_documented():
    assert configdoc.undocumented() == []
    assert configdoc.stale() == []
    page = configdoc.render()
    for table, key in configdoc.accepted_keys():
        heading = f"## [[{table}]]\n" if "." in table else f"## [{table}]\n"
        section = page.split(heading, 1)[1].split("\n## ", 1)[0]
        assert f"| `{key}` |" in section, f"{table}.{key} missing from its table on the page"


def test_accepted_keys_are_the_loaders_schema(tmp_path: Path):
    """The generator's keys are the fields the loader checks tables against: one more is refused."""
    keys = configdoc.accepted_keys()
    assert [t for t in configdoc.schema() if "." not in t] == [*SECTIONS, *OPTIONAL_SECTIONS]
    for table, cls in configdoc.schema().items():
        assert [k for t, k in keys if t == table] == [f.name for f in dataclasses.fields(cls)]
        if "." in table:  # a list of tables: [[perception.sensors]]
            outer, inner = table.split(".")
            data, field = {outer: {inner: [{"no_such_key": 1}]}}, f"{table}[0].no_such_key"
        else:
            data, field = {table: {"no_such_key": 1}}, f"{table}.no_such_key"
        with pytest.raises(InputError) as exc:
            config_from_dict({"run": {"name": "x"}, **data}, tmp_path / "c.toml")
        assert field in str(exc.value)


def test_a_new_key_without_documentation_fails(monkeypatch):
    """What happens when config.py gains a field and nobody documents it."""
    @dataclasses.dataclass(frozen=True)
    class Report(configdoc.SECTIONS["report"]):
        new_key_m: float = 1.0

    monkeypatch.setitem(configdoc.SECTIONS, "report", Report)
    assert "report.new_key_m" in configdoc.undocumented()
    with pytest.raises(ValueError, match="report.new_key_m"):
        configdoc.render()


def test_numeric_key_needs_a_unit(monkeypatch):
    monkeypatch.setitem(configdoc.KEY_DOCS["infra"], "rsu_range_m", ("", "range"))
    assert "infra.rsu_range_m" in configdoc.undocumented()


def test_check_mode_reports_a_stale_page(tmp_path: Path, capsys):
    page = tmp_path / "configuration.md"
    page.write_text("# old\n")
    assert configdoc.main(["--check", "--out", str(page)]) == 1
    assert configdoc.main(["--out", str(page)]) == 0
    assert configdoc.main(["--check", "--out", str(page)]) == 0
    assert "up to date" in capsys.readouterr().out
