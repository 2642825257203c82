"""The results store: append, resume, atomic cells, format and config checks."""

import sqlite3

import numpy as np
import pytest

from sysid_bench.bench.store import (
    RESULT_COLUMNS,
    STORE_FORMAT,
    Row,
    Store,
    StoreConfigError,
    StoreCorruptError,
    StoreFormatError,
)

CFG = {"seed": 1, "lengths": [10, 20]}
KEY = {"experiment": "identification", "method": "lsq", "input": "video", "condition": "", "case": 3}


def _rows(case=3):
    return [Row(case, 10, "se", 0.5), Row(case, 20, "se", 0.25), Row(case, 20, "wall_s", float("nan"))]


def test_append_and_read_back(tmp_path):
    with Store(tmp_path / "r.sqlite", CFG) as s:
        assert s.add_cell("c3", KEY, _rows(), wall_s=1.5, artifacts={"a": np.arange(6.0).reshape(3, 2)})
        df = s.results()
        assert list(df.columns) == list(RESULT_COLUMNS)
        assert len(df) == 3
        se = df[df.metric == "se"].sort_values("n_frames")
        assert se.value.tolist() == [0.5, 0.25]
        assert se.status.unique().tolist() == ["ok"]
        assert np.isnan(df[df.metric == "wall_s"].value.iloc[0])  # NaN survives as missing
        assert (df.wall_s == 1.5).all()
        np.testing.assert_array_equal(s.artifact("c3", "a"), np.arange(6.0).reshape(3, 2))
        assert s.artifact("c3", "nope") is None
        assert s.done_cells() == {"c3"}
        assert s.grid_config == CFG


def test_resume_skips_stored_cells_without_duplicates(tmp_path):
    path = tmp_path / "r.sqlite"
    with Store(path, CFG) as s:
        s.add_cell("c3", KEY, _rows())
    with Store(path, CFG) as s:  # a restarted run re-opens the same store
        assert s.done_cells() == {"c3"}
        assert s.add_cell("c3", KEY, _rows()) is False
        assert len(s.results()) == 3
        assert len(s.cells()) == 1


def test_error_and_na_cells_are_rows_with_their_text(tmp_path):
    with Store(tmp_path / "r.sqlite", CFG) as s:
        s.add_cell("e", {**KEY, "case": 4}, [], status="error", error="RuntimeError: boom")
        s.add_cell("n", {**KEY, "method": "dmd", "case": 4}, [], status="n/a",
                   error="dmd identifies no parameters")
        df = s.results().set_index("cell_id")
        assert df.loc["e", "metric"] == "error" and df.loc["e", "error"] == "RuntimeError: boom"
        assert df.loc["n", "metric"] == "n/a" and df.loc["n", "status"] == "n/a"
        assert df.loc["e", "case"] == 4
        with pytest.raises(ValueError, match="status"):
            s.add_cell("x", KEY, [], status="weird")


def test_a_failing_cell_write_leaves_nothing_behind(tmp_path):
    with Store(tmp_path / "r.sqlite", CFG) as s:
        dup = [Row(3, 10, "se", 0.1), Row(3, 10, "se", 0.2)]  # violates the unique key
        with pytest.raises(sqlite3.IntegrityError):
            s.add_cell("c3", KEY, dup)
        assert s.done_cells() == set()
        assert len(s.results()) == 0
        assert s.add_cell("c3", KEY, _rows())  # and the cell can still be written afterwards


def test_other_store_format_is_a_clear_error(tmp_path):
    path = tmp_path / "r.sqlite"
    Store(path, CFG).close()
    con = sqlite3.connect(path)
    con.execute("UPDATE meta SET value=? WHERE key='store_format'", (str(STORE_FORMAT + 1),))
    con.commit()
    con.close()
    for cfg in (CFG, None):
        with pytest.raises(StoreFormatError, match=f"store format {STORE_FORMAT + 1}.*reads format {STORE_FORMAT}"):
            Store(path, cfg)


def test_foreign_sqlite_file_and_missing_store(tmp_path):
    path = tmp_path / "other.sqlite"
    con = sqlite3.connect(path)
    con.execute("CREATE TABLE meta (key TEXT, value TEXT)")
    con.commit()
    con.close()
    with pytest.raises(StoreFormatError, match="store format none"):
        Store(path, CFG)
    with pytest.raises(FileNotFoundError, match="path"):
        Store(tmp_path / "missing.sqlite")


def test_other_grid_config_is_refused(tmp_path):
    path = tmp_path / "r.sqlite"
    with Store(path, CFG) as s:
        s.add_cell("c3", KEY, _rows())
    with pytest.raises(StoreConfigError, match="grid_config"):
        Store(path, {**CFG, "seed": 2})
    with Store(path) as s:  # read-only use needs no config
        assert len(s.results()) == 3


@pytest.mark.parametrize("garbage", ["{not json", "[1, 2]", "null", None])
def test_a_damaged_grid_config_is_refused_reading_or_writing(tmp_path, garbage):
    """Issue 37: ``report --from-store`` of a store whose grid_config was garbage rendered it
    (exit 0). The config says which cases the cells are of: without it they cannot be trusted."""
    path = tmp_path / "r.sqlite"
    with Store(path, CFG) as s:
        s.add_cell("c3", KEY, _rows())
    con = sqlite3.connect(path)
    if garbage is None:
        con.execute("DELETE FROM meta WHERE key='grid_config'")
    else:
        con.execute("UPDATE meta SET value=? WHERE key='grid_config'", (garbage,))
    con.commit()
    con.close()
    for cfg in (None, CFG):
        with pytest.raises(StoreCorruptError, match="grid_config") as e:
            Store(path, cfg)
        assert "\n" not in str(e.value) and str(path) in str(e.value)


def test_report_from_a_store_with_a_garbage_grid_config_exits_non_zero(tmp_path, capsys):
    from sysid_bench.apps.cli import main

    path = tmp_path / "r.sqlite"
    with Store(path, CFG) as s:
        s.add_cell("c3", KEY, _rows())
    con = sqlite3.connect(path)
    con.execute("UPDATE meta SET value='{garbage' WHERE key='grid_config'")
    con.commit()
    con.close()
    assert main(["report", "--from-store", str(path), "--out", str(tmp_path / "rep")]) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "grid_config" in err[0] and str(path) in err[0]
    assert not (tmp_path / "rep" / "REPORT.md").exists()


def test_invocations_are_recorded(tmp_path):
    with Store(tmp_path / "r.sqlite", CFG) as s:
        i1 = s.record_invocation({"argv": ["a"], "git_commit": "abc"})
        i2 = s.record_invocation({"argv": ["b"]})
        inv = s.invocations()
        assert [v["id"] for v in inv] == [i1, i2]
        assert inv[0]["git_commit"] == "abc" and "host" in inv[0]


def test_drop_cells_forgets_failed_cells_only(tmp_path):
    with Store(tmp_path / "r.sqlite", CFG) as s:
        s.add_cell("ok", KEY, _rows(), artifacts={"a": np.zeros(2)})
        s.add_cell("bad", {**KEY, "case": 4}, [], status="error", error="boom")
        assert s.drop_cells("error") == 1
        assert s.done_cells() == {"ok"}
        assert set(s.results().cell_id) == {"ok"}
        assert s.artifact("ok", "a") is not None
        assert s.drop_cells("error") == 0
