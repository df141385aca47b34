"""Drive schema validation: errors name file, column and first bad row; fuzzing."""

from __future__ import annotations

from contextlib import suppress

import numpy as np
import pandas as pd
import pytest
from fixtures_data import straight_drive
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from safeil_sumo.data.schema import (
    COLUMNS,
    REQUIRED_COLUMNS,
    SchemaError,
    load_drive,
    save_drive,
    validate_drive,
)


def _drive() -> pd.DataFrame:
    a = straight_drive("a", duration=2.0)
    b = straight_drive("b", duration=2.0)
    return pd.concat([a, b], ignore_index=True)


def test_round_trip_parquet_and_csv(tmp_path):
    df = _drive()
    save_drive(df, tmp_path / "d.parquet")
    back = load_drive(tmp_path / "d.parquet")
    assert list(back.columns) == [c for c in COLUMNS if c in df.columns]
    pd.testing.assert_frame_equal(back, validate_drive(df))
    df.to_csv(tmp_path / "d.csv", index=False)
    pd.testing.assert_frame_equal(load_drive(tmp_path / "d.csv"), back)
    df.to_csv(tmp_path / "d.csv.gz", index=False)
    assert len(load_drive(tmp_path / "d.csv.gz")) == len(df)
    assert not list(tmp_path.glob("*.tmp"))


def test_recording_id_digits_stay_strings(tmp_path):
    df = _drive().assign(recording_id=np.repeat(["0012", "7"], 21))
    df.to_csv(tmp_path / "d.csv", index=False)
    assert list(load_drive(tmp_path / "d.csv")["recording_id"].unique()) == ["0012", "7"]


def _error(tmp_path, df: pd.DataFrame, name: str = "bad.parquet") -> str:
    path = tmp_path / name
    if name.endswith(".csv"):
        df.to_csv(path, index=False)
    else:
        df.to_parquet(path)
    with pytest.raises(SchemaError) as info:
        load_drive(path)
    msg = str(info.value)
    assert name in msg
    return msg


def test_missing_column(tmp_path):
    msg = _error(tmp_path, _drive().drop(columns=["right_c2"]))
    assert "'right_c2'" in msg and "missing" in msg


def test_nan_where_required_names_row(tmp_path):
    df = _drive()
    df.loc[7, "v_x"] = np.nan
    msg = _error(tmp_path, df)
    assert "'v_x'" in msg and "row 7" in msg


def test_lead_x_without_lead_y(tmp_path):
    df = _drive()
    df.loc[3, "lead_y"] = np.nan
    msg = _error(tmp_path, df)
    assert "'lead_y'" in msg and "row 3" in msg


def test_duplicate_and_decreasing_time(tmp_path):
    df = _drive()
    df.loc[5, "time"] = df.loc[4, "time"]
    msg = _error(tmp_path, df)
    assert "'time'" in msg and "row 5" in msg
    df = _drive()
    df.loc[30, "time"] = 0.05
    assert "row 30" in _error(tmp_path, df, "dec.csv")


def test_non_contiguous_recording(tmp_path):
    df = _drive()
    df = pd.concat([df.iloc[:10], df.iloc[21:], df.iloc[10:21]], ignore_index=True)
    msg = _error(tmp_path, df)
    assert "'recording_id'" in msg and "not contiguous" in msg


@pytest.mark.parametrize("factor, hint", [(3.6, "km/h"), (1 / 0.3048, "ft/s")])
def test_speed_units(tmp_path, factor, hint):
    df = _drive()
    df["v_x"] *= factor * 1.2  # 24 m/s -> 86 km/h or 79 ft/s
    msg = _error(tmp_path, df)
    assert "'v_x'" in msg and hint in msg


def test_degrees_and_milliseconds(tmp_path):
    df = _drive().assign(yaw=90.0)
    assert "degrees" in _error(tmp_path, df)
    df = _drive()
    df["time"] *= 1000.0
    assert "milliseconds" in _error(tmp_path, df)


def test_non_numeric_value_names_row(tmp_path):
    path = tmp_path / "bad.csv"
    df = _drive()
    df.to_csv(path, index=False)
    lines = path.read_text().splitlines()
    cells = lines[13].split(",")
    cells[list(df.columns).index("lead_x")] = "n/a?"
    lines[13] = ",".join(cells)
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(SchemaError, match=r"bad\.csv, column 'lead_x', row 12: not a number"):
        load_drive(path)


def test_empty_truncated_and_wrong_format_files(tmp_path):
    (tmp_path / "empty.parquet").write_bytes(b"")
    (tmp_path / "empty.csv").write_text("")
    (tmp_path / "header.csv").write_text(",".join(REQUIRED_COLUMNS) + "\n")
    save_drive(_drive(), tmp_path / "full.parquet")
    data = (tmp_path / "full.parquet").read_bytes()
    (tmp_path / "trunc.parquet").write_bytes(data[: len(data) // 2])
    (tmp_path / "text.parquet").write_text("time,x\n1,2\n")
    (tmp_path / "bin.csv").write_bytes(data)
    for name in ("empty.parquet", "empty.csv", "header.csv", "trunc.parquet", "text.parquet",
                 "bin.csv", "missing.parquet"):
        with pytest.raises(SchemaError, match=name.replace(".", r"\.")):
            load_drive(tmp_path / name)


def test_save_refuses_invalid(tmp_path):
    with pytest.raises(SchemaError):
        save_drive(_drive().drop(columns=["yaw"]), tmp_path / "x.parquet")
    assert not (tmp_path / "x.parquet").exists()


# ------------------------------------------------------------------------------------ fuzzing

_values = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True, width=64),
    st.integers(-10**6, 10**6),
    st.text(max_size=4),
    st.none(),
    st.booleans(),
)


@st.composite
def _frames(draw) -> pd.DataFrame:
    base = _drive().iloc[: draw(st.integers(0, 6))].reset_index(drop=True)
    cols = draw(st.lists(st.sampled_from(list(base.columns)), unique=True))
    df = base[[c for c in base.columns if c not in cols[:1]]].astype(object)
    for _ in range(draw(st.integers(0, 4))):
        if len(df) == 0 or len(df.columns) == 0:
            break
        r = draw(st.integers(0, len(df) - 1))
        c = draw(st.sampled_from(list(df.columns)))
        df.iat[r, df.columns.get_loc(c)] = draw(_values)
    return df


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(df=_frames())
def test_fuzz_validate_only_raises_schema_error(df):
    try:
        out = validate_drive(df, "fuzz")
    except SchemaError:
        return
    assert len(out) == len(df)


@settings(max_examples=60, deadline=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
@given(df=_frames(), fmt=st.sampled_from(["csv", "parquet"]), cut=st.integers(0, 64))
def test_fuzz_load_only_raises_schema_error(tmp_path, df, fmt, cut):
    path = tmp_path / f"f.{fmt}"
    try:
        if fmt == "csv":
            df.to_csv(path, index=False)
        else:
            df.astype(str).to_parquet(path)
    except Exception:  # noqa: BLE001 - the writer refuses this frame: nothing to load
        return
    if cut:  # also truncate the file
        data = path.read_bytes()
        path.write_bytes(data[: max(len(data) - cut, 0)])
    with suppress(SchemaError):
        load_drive(path)
