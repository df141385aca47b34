"""Importers on small fixtures in each ORIGINAL layout, and on the real shared files."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from fixtures_data import (
    NGSIM_PAIRS,
    OPENACC_DIR,
    ngsim_pairs_frame,
    require_file,
    write_ngsim_csv,
    write_openacc,
)

from safeil_sumo.data.importers import (
    FT,
    MIN_GAP,
    import_ngsim_csv,
    import_ngsim_pairs,
    import_openacc,
    import_openacc_files,
    openacc_recording_prefix,
)
from safeil_sumo.data.schema import SchemaError, load_drive, save_drive, validate_drive


def _round_trip(df: pd.DataFrame, tmp_path) -> pd.DataFrame:
    """Importers' output must pass the file validation unchanged."""
    save_drive(df, tmp_path / "drive.parquet")
    back = load_drive(tmp_path / "drive.parquet")
    pd.testing.assert_frame_equal(back, validate_drive(df), check_dtype=False)
    return back


# ---------------------------------------------------------------------------------- NGSIM CSV


def test_ngsim_csv_units_and_pairs(tmp_path):
    df = import_ngsim_csv(write_ngsim_csv(tmp_path / "trajectories.csv"))
    ids = list(pd.unique(df["recording_id"]))
    assert ids == ["2-1", "3-2", "3-1"]  # 3 follows 2 until 2 leaves, then 1
    a = df[df["recording_id"] == "2-1"]
    assert len(a) == 60
    np.testing.assert_allclose(a["v_x"], 30 * FT)
    np.testing.assert_allclose(a["lead_x"], (50.0 - 15.0) * FT, atol=1e-9)  # bumper gap
    np.testing.assert_allclose(a["lead_y"], 0.0, atol=1e-9)
    np.testing.assert_allclose(a["left_c0"], 6 * FT, atol=1e-9)  # 18 ft in a 12..24 ft lane
    np.testing.assert_allclose(a["right_c0"], -6 * FT, atol=1e-9)
    np.testing.assert_allclose(a[["left_c1", "left_c2", "left_c3"]], 0.0, atol=1e-9)
    np.testing.assert_allclose(a["lead_v"], 30 * FT)
    np.testing.assert_allclose(np.diff(a["time"]), 0.1)
    assert (a["lane_index"] == 2).all()
    b = df[df["recording_id"] == "3-1"]
    np.testing.assert_allclose(b["lead_x"], (100.0 - 15.0) * FT, atol=1e-9)
    _round_trip(df, tmp_path)


def test_ngsim_csv_missing_column_is_named(tmp_path):
    with pytest.raises(SchemaError, match="Preceding"):
        import_ngsim_csv(write_ngsim_csv(tmp_path / "t.csv", drop="Preceding"))


def test_ngsim_csv_non_numeric_value_names_row(tmp_path):
    path = write_ngsim_csv(tmp_path / "t.csv")
    text = path.read_text().splitlines()
    parts = text[5].split(",")
    parts[5] = "abc"  # Local_Y of data row 4
    text[5] = ",".join(parts)
    path.write_text("\n".join(text) + "\n")
    with pytest.raises(SchemaError, match=r"t\.csv.*'Local_Y'.*row 4"):
        import_ngsim_csv(path)


# ------------------------------------------------------------------------------ NGSIM pairs


def test_ngsim_pairs_fixture(tmp_path):
    raw = ngsim_pairs_frame()
    path = tmp_path / "pairs.parquet"
    raw.to_parquet(path)
    df = import_ngsim_pairs(path)
    assert list(pd.unique(df["recording_id"])) == ["2-1", "5-4"]
    np.testing.assert_allclose(df["lead_x"], 20.0 - 4.5, atol=1e-9)
    one = df[df["recording_id"] == "5-4"]
    # lane 1 from the road edge, the grid shifted by the median offset of the vehicles from
    # their 12 ft lane centres: 1.83 - 1.8288 and 5.49 - 5.4864 -> 0.0024 m
    assert df.attrs["import_stats"]["lane_grid_offset_m"] == pytest.approx(0.0024, abs=1e-9)
    np.testing.assert_allclose(one["left_c0"], 1.83 - 0.0024, atol=1e-9)
    np.testing.assert_allclose(one["right_c0"], 1.83 - 0.0024 - 12 * FT, atol=1e-9)
    np.testing.assert_allclose(df["y"], -raw["local_x"])  # y is LEFT
    np.testing.assert_allclose(df["yaw"], 0.0, atol=1e-9)
    assert df.attrs["import_stats"]["lead_lateral_from_lane_centre"] == len(df)
    _round_trip(df, tmp_path)


def test_ngsim_pairs_negative_gap_is_clipped_and_counted(tmp_path):
    raw = ngsim_pairs_frame()
    raw.loc[[3, 4], "preceding_local_y"] = raw.loc[[3, 4], "local_y"] + 4.0  # 4 m < 4.5 m length
    raw.to_parquet(tmp_path / "p.parquet")
    df = import_ngsim_pairs(tmp_path / "p.parquet")
    assert df.loc[3, "lead_x"] == pytest.approx(MIN_GAP)
    assert df.attrs["import_stats"]["gap_clipped"] == 2
    df2 = import_ngsim_pairs(tmp_path / "p.parquet", headway_source="space_headway")
    assert df2.loc[3, "lead_x"] == pytest.approx(15.5)


def test_ngsim_pairs_missing_column(tmp_path):
    ngsim_pairs_frame().drop(columns=["preceding_length"]).to_parquet(tmp_path / "p.parquet")
    with pytest.raises(SchemaError, match="preceding_length"):
        import_ngsim_pairs(tmp_path / "p.parquet")


# ---------------------------------------------------------------------------------- OpenACC


def test_openacc_human_followers(tmp_path):
    path = write_openacc(tmp_path / "JRC-VC_280219_part2.csv.gz", gz=True)
    df = import_openacc(path)
    assert list(pd.unique(df["recording_id"])) == [f"JRC-VC_280219_part2_f{k}" for k in (2, 3, 4, 5)]
    np.testing.assert_allclose(df["lead_x"], 35.5)
    np.testing.assert_allclose(df["lead_y"], 0.0)
    np.testing.assert_allclose(df["lead_v"], 30.0)
    np.testing.assert_allclose(df["yaw"], np.pi / 4, atol=1e-9)
    np.testing.assert_allclose(df["left_c0"], 1.75)
    np.testing.assert_allclose(df["right_c0"], -1.75)
    np.testing.assert_allclose(df[["left_c2", "right_c2"]], 0.0, atol=1e-9)  # straight path
    _round_trip(df, tmp_path)


def test_openacc_without_optional_columns_for_one_vehicle(tmp_path):
    path = write_openacc(tmp_path / "JRC-VC_280219_part3.csv", no_optional_for=3)
    df = import_openacc(path)
    assert df["recording_id"].nunique() == 4


def test_openacc_acc_followers_skipped_unless_asked(tmp_path):
    drivers = ("Human", "ACC", "ACC", "Human", "ACC")
    path = write_openacc(tmp_path / "JRC-VC_260219_part3.csv", drivers=drivers)
    df = import_openacc(path)
    assert list(pd.unique(df["recording_id"])) == ["JRC-VC_260219_part3_f4"]
    assert import_openacc(path, include_acc=True)["recording_id"].nunique() == 4
    all_acc = write_openacc(tmp_path / "JRC-VC_260219_part4.csv", drivers=("Human",) + ("ACC",) * 4)
    empty = import_openacc(all_acc)
    assert len(empty) == 0 and empty.attrs["import_stats"]["followers_acc_skipped"] == 4


def test_openacc_curvature_on_a_circle(tmp_path):
    path = write_openacc(tmp_path / "JRC-VC_280219_part2.csv", n=400)
    raw = pd.read_csv(path, skiprows=5)
    radius = 800.0
    for k in range(1, 6):  # bend the straight platoon onto a circle (arc length preserved)
        s = np.hypot(raw[f"E{k}"], raw[f"N{k}"]) * np.sign(raw[f"E{k}"])
        raw[f"E{k}"], raw[f"N{k}"] = radius * np.sin(s / radius), radius * (1 - np.cos(s / radius))
    meta = "".join(path.read_text().splitlines(keepends=True)[:5])
    path.write_text(meta + raw.to_csv(index=False))
    df = import_openacc(path)
    mid = df[(df["time"] > df["time"].min() + 5) & (df["time"] < df["time"].max() - 5)]
    np.testing.assert_allclose(mid["left_c2"], 0.5 / radius, rtol=0.02)


# a missing Driver{k} falls back to the metadata ACC flag: tests/data/test_openacc_variations.py
@pytest.mark.parametrize("drop", ["IVS2", "E4", "Speed2"])
def test_openacc_missing_column_is_named(tmp_path, drop):
    path = write_openacc(tmp_path / "x.csv", drop=drop)
    with pytest.raises(SchemaError, match=drop):
        import_openacc(path)


def test_openacc_without_metadata_rows_is_rejected(tmp_path):
    text = write_openacc(tmp_path / "x.csv").read_text().splitlines(keepends=True)[5:]
    (tmp_path / "y.csv").write_text("".join(text))
    with pytest.raises(SchemaError, match="Time"):
        import_openacc(tmp_path / "y.csv")


def test_openacc_recording_prefix():
    # one rule for every campaign's file naming: the name without extensions
    assert openacc_recording_prefix("a/JRC-VC_280219_part2.csv.gz") == "JRC-VC_280219_part2"
    assert openacc_recording_prefix("JRC-VC_280219_part3.csv") == "JRC-VC_280219_part3"
    assert (openacc_recording_prefix("Cher-JRC_240918_rec2_part1.csv")
            == "Cher-JRC_240918_rec2_part1")
    assert openacc_recording_prefix("ASta platoon 1.csv") == "ASta_platoon_1"


def test_missing_file_is_schema_error(tmp_path):
    for fn in (import_ngsim_csv, import_ngsim_pairs, import_openacc):
        with pytest.raises(SchemaError, match="no such file"):
            fn(tmp_path / "nope.csv")


# ------------------------------------------------------------------------------- real files


def test_real_ngsim_pairs_142(tmp_path):
    df = import_ngsim_pairs(require_file(NGSIM_PAIRS))
    assert df["recording_id"].nunique() == 142
    assert len(df) == 68_339
    assert df["lead_x"].min() >= MIN_GAP and df["lead_x"].notna().all()
    # the lane grid shifted to centre the vehicles (every lane's median sits ~0.36 m left of
    # the 12 ft grid); the front centre is then between its lane's lines on all but 33 rows,
    # the ends of lane changes the pair filter missed (the pipeline drops them)
    assert df.attrs["import_stats"]["lane_grid_offset_m"] == pytest.approx(-0.356, abs=1e-3)
    assert ((df["left_c0"] <= 0) | (df["right_c0"] >= 0)).sum() == 33
    _round_trip(df, tmp_path)


def test_real_openacc_vicolungo_8_human_pairs(tmp_path):
    paths = [require_file(OPENACC_DIR / f"JRC-VC_280219_part{i}.csv.gz") for i in (2, 3)]
    df = import_openacc_files(paths)
    ids = sorted(df["recording_id"].unique())
    assert ids == sorted(f"JRC-VC_280219_part{p}_f{k}" for p in (2, 3)
                        for k in (2, 3, 4, 5))
    assert 15 < df["v_x"].median() < 40
    _round_trip(df, tmp_path)


def test_real_openacc_acc_day_has_no_human_pairs():
    path = require_file(OPENACC_DIR / "JRC-VC_260219_part3.csv.gz")
    assert len(import_openacc(path)) == 0
    assert import_openacc(path, include_acc=True)["recording_id"].nunique() == 4
