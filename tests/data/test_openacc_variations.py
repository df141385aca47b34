"""The OpenACC importer on the documented layout variations: missing Driver columns (the metadata
ACC flag stands in), vehicles without columns, numbering gaps, NaN stretches and time jumps (each
contiguous run smoothed alone), files without their metadata rows; on the shared Vicolungo and
ZalaZone files and on small synthetic platoons."""

from __future__ import annotations

import gzip
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from fixtures_data import OPENACC_DIR, SHARED, require_file, write_ngsim_csv, write_openacc

from safeil_sumo.data.importers import (
    MAX_PATH_CURVATURE,
    import_openacc,
    import_openacc_files,
    openacc_heading_curvature,
    openacc_runs,
)
from safeil_sumo.data.pipeline import PipelineConfig, leader_speed, run_pipeline
from safeil_sumo.data.schema import SchemaError

ZALAZONE_DIR = SHARED / "openacc_zalazone"
ZALAZONE_PAIRS = {22: 7, 26: 7, 35: 6, 40: 4}  # human follower pairs per handling_part<i> file
VICOLUNGO_HUMAN = OPENACC_DIR / "JRC-VC_280219_part2.csv.gz"
VICOLUNGO_ACC = OPENACC_DIR / "JRC-VC_260219_part3.csv.gz"
DT = 0.1  # [s] the fixtures' sample step


def _split(path: Path) -> tuple[list[str], pd.DataFrame]:
    """The 5 metadata lines (verbatim, line ends kept) and the table of an OpenACC file."""
    opener = gzip.open if path.name.endswith(".gz") else open
    with opener(path, "rt", newline="") as fh:
        meta = [next(fh) for _ in range(5)]
    return meta, pd.read_csv(path, skiprows=5)


def _write(path: Path, meta: list[str], table: pd.DataFrame) -> Path:
    """An OpenACC file from metadata lines and a table (gzip-compressed when named .gz)."""
    opener = gzip.open if path.name.endswith(".gz") else open
    with opener(path, "wt", newline="") as fh:
        fh.write("".join(meta) + table.to_csv(index=False))
    return path


def _modified_copy(src: Path, dst: Path, drop=(), acc_line: str | None = None) -> Path:
    """``src`` with columns dropped (a callable picks them from the columns) and, with
    ``acc_line``, the metadata row 'ACC,...' replaced by that line."""
    meta, table = _split(src)
    cols = [c for c in table.columns if drop(c)] if callable(drop) else list(drop)
    if acc_line is not None:
        meta = [acc_line + "\n" if line.startswith("ACC") else line for line in meta]
    return _write(dst, meta, table.drop(columns=cols))


def _wrap(angle: np.ndarray) -> np.ndarray:
    """Angles into [-pi, pi) (the drive's yaw is wrapped, the filters' heading unwrapped)."""
    return (np.asarray(angle) + np.pi) % (2 * np.pi) - np.pi


def _vehicle_columns(k: int):
    """Picks every column of vehicle ``k`` (not its IVS)."""
    names = ("Speed", "Lat", "Lon", "Alt", "E", "N", "U", "VE", "VN", "VU", "Driver")
    return lambda c: c in {f"{n}{k}" for n in names}


def _circle_platoon(path: Path, n: int = 600, radius: float = 300.0, **kwargs) -> Path:
    """The fixture platoon (10 Hz, 30 m/s, 40 m apart) bent onto a circle of ``radius`` [m], arc
    length preserved; returns the path after writing (edit the table with ``_split``)."""
    path = write_openacc(path, n=n, **kwargs)
    meta, raw = _split(path)
    for k in range(1, 6):
        if f"E{k}" not in raw:
            continue
        s = np.hypot(raw[f"E{k}"], raw[f"N{k}"]) * np.sign(raw[f"E{k}"])
        raw[f"E{k}"] = radius * np.sin(s / radius)
        raw[f"N{k}"] = radius * (1 - np.cos(s / radius))
    return _write(path, meta, raw)


# ----------------------------------------------------------------------------- real ZalaZone


def _zalazone(i: int) -> Path:
    return require_file(ZALAZONE_DIR / f"handling_part{i}.csv.gz")


def test_real_zalazone_24_human_pairs():
    """No Driver columns (ACC,0), no columns for the target car 1, no vehicle 9, NaN dropouts."""
    paths = [_zalazone(i) for i in ZALAZONE_PAIRS]
    df = import_openacc_files(paths)
    stats = df.attrs["import_stats"]["files"]
    assert [s["pairs"] for s in stats] == list(ZALAZONE_PAIRS.values())  # 24 in all
    assert [s["driver_from_metadata"] for s in stats] == list(ZALAZONE_PAIRS.values())
    assert [s["lead_speed_missing"] for s in stats] == [0, 0, 0, 0]
    # the rows are decided by NaN patterns and run lengths only (no float arithmetic)
    assert [s["rows"] for s in stats] == [21_835, 19_179, 18_977, 11_016]
    followers = {p.name.split(".")[0]: sorted({int(r.split("_f")[1].split("_")[0])
                                               for r in df["recording_id"]
                                               if r.startswith(p.name.split(".")[0] + "_")})
                 for p in paths}
    # car 2 follows the target car 1, which has no columns and no IVS1: never a follower here;
    # car 10 follows no car 9 (there is none), so no IVS9: the pair (10, 11) is there
    assert followers == {"handling_part22": [3, 4, 5, 6, 7, 8, 11],
                         "handling_part26": [3, 4, 5, 6, 7, 8, 11],
                         "handling_part35": [3, 4, 5, 6, 7, 8],
                         "handling_part40": [3, 4, 5, 6]}
    # a follower with a receiver dropout has one recording per run, one without keeps its id
    assert "handling_part22_f3" in set(df["recording_id"])
    assert {"handling_part22_f7_s1", "handling_part22_f7_s2"} <= set(df["recording_id"])
    assert df["time"].diff()[df["recording_id"].eq(df["recording_id"].shift())].max() \
        == pytest.approx(DT, abs=1e-6)  # no run reaches across a dropout
    assert 10 < df["v_x"].median() < 17


def test_real_zalazone_through_the_pipeline():
    df = import_openacc_files([_zalazone(i) for i in ZALAZONE_PAIRS])
    tup, rep = run_pipeline(df, PipelineConfig(), source="openacc_zalazone")
    # 60 maneuvers, 26,515 tuples on the development machine; a little slack for other CPUs
    assert 50 <= rep.maneuvers_kept <= 70
    assert 20_000 <= rep.tuples <= 30_000
    assert np.isfinite(tup.features).all()


def test_real_zalazone_curvature_clip_option():
    """The motorway clip (R >= 250 m) bends the handling course's lanes far too little."""
    path = _zalazone(40)
    motorway = import_openacc(path)
    track = import_openacc(path, max_curvature=1 / 40)
    assert motorway.attrs["import_stats"]["curvature_clipped"] > 0.5 * len(motorway)
    assert track.attrs["import_stats"]["curvature_clipped"] < 0.15 * len(track)
    assert motorway["left_c2"].abs().max() == pytest.approx(0.5 * MAX_PATH_CURVATURE)
    assert track["left_c2"].abs().max() > 2 * motorway["left_c2"].abs().max()
    pd.testing.assert_series_equal(motorway["lead_x"], track["lead_x"])


# ----------------------------------------------------------------- real Vicolungo, modified


def test_real_vicolungo_without_driver1(tmp_path):
    """The platoon leader's driver is never used: its column may be missing."""
    src = require_file(VICOLUNGO_HUMAN)
    path = _modified_copy(src, tmp_path / "JRC-VC_280219_part2.csv", drop=["Driver1"])
    df = import_openacc(path)
    assert df.attrs["import_stats"]["pairs"] == 4
    assert df.attrs["import_stats"]["driver_from_metadata"] == 0
    pd.testing.assert_frame_equal(df, import_openacc(src))


def test_real_vicolungo_without_any_driver_uses_acc0(tmp_path):
    src = require_file(VICOLUNGO_HUMAN)
    assert _split(src)[0][3].startswith("ACC,0")  # the file's own metadata row
    path = _modified_copy(src, tmp_path / "JRC-VC_280219_part2.csv.gz",
                          drop=lambda c: c.startswith("Driver"))
    df = import_openacc(path)
    assert sorted(df["recording_id"].unique()) == [f"JRC-VC_280219_part2_f{k}"
                                                   for k in (2, 3, 4, 5)]
    assert df.attrs["import_stats"]["driver_from_metadata"] == 4
    pd.testing.assert_frame_equal(df, import_openacc(src))


def test_real_vicolungo_acc_day_without_driver_uses_acc1(tmp_path):
    src = require_file(VICOLUNGO_ACC)
    path = _modified_copy(src, tmp_path / "acc.csv", drop=lambda c: c.startswith("Driver"))
    df = import_openacc(path)
    assert len(df) == 0 and df.attrs["import_stats"]["followers_acc_skipped"] == 4
    assert import_openacc(path, include_acc=True)["recording_id"].nunique() == 4


@pytest.mark.parametrize("acc_line, said", [("ACC,2", "metadata row 'ACC,2'"),  # mixed
                                            ("ACC,", "metadata row 'ACC,'"),
                                            ("Remark,none", "no metadata row 'ACC'")])
def test_real_vicolungo_without_driver_and_without_usable_flag(tmp_path, acc_line, said):
    src = require_file(VICOLUNGO_HUMAN)
    path = _modified_copy(src, tmp_path / "x.csv", drop=["Driver3"], acc_line=acc_line)
    with pytest.raises(SchemaError) as exc:
        import_openacc(path)
    msg = str(exc.value)
    assert msg.startswith(f"{path}: follower 3 has no column 'Driver3'") and said in msg
    assert "\n" not in msg
    # the other followers keep their columns: only the follower without one is a problem
    ok = _modified_copy(src, tmp_path / "y.csv", drop=["Driver1"], acc_line=acc_line)
    assert import_openacc(ok).attrs["import_stats"]["pairs"] == 4


def test_real_vicolungo_leader_without_columns(tmp_path):
    """Car 1 without any column but IVS1 kept: the pair (1, 2) stays, with no measured leader
    speed; the pipeline differentiates IVS1 (+ the follower's speed) instead."""
    src = require_file(VICOLUNGO_HUMAN)
    path = _modified_copy(src, tmp_path / "JRC-VC_280219_part2.csv", drop=_vehicle_columns(1))
    df = import_openacc(path)
    ref = import_openacc(src)
    assert df.attrs["import_stats"]["lead_speed_missing"] == 1
    f2 = df[df["recording_id"] == "JRC-VC_280219_part2_f2"]
    assert f2["lead_v"].isna().all() and f2["lead_x"].notna().all()
    pd.testing.assert_frame_equal(df.drop(columns="lead_v"), ref.drop(columns="lead_v"))
    derived, _ = leader_speed(f2.reset_index(drop=True), PipelineConfig())
    measured = ref.loc[ref["recording_id"] == "JRC-VC_280219_part2_f2", "lead_v"].to_numpy()
    err = derived["v_lead"].to_numpy() - measured
    assert np.sqrt(np.mean(err**2)) < 0.5  # [m/s]; 0.20 on this follower


def test_real_vicolungo_without_metadata_rows(tmp_path):
    src = require_file(VICOLUNGO_HUMAN)
    meta, table = _split(src)
    path = tmp_path / "no_meta.csv"
    table.to_csv(path, index=False)
    with pytest.raises(SchemaError) as exc:
        import_openacc(path)
    msg = str(exc.value)
    assert msg.startswith(f"{path}: header (with 'Time') found in row 1, but OpenACC files "
                          "start with 5 metadata rows") and "\n" not in msg
    _write(path, meta[:3], table)  # 3 of the 5 rows
    with pytest.raises(SchemaError, match=r"found in row 4, but OpenACC files start with 5"):
        import_openacc(path)


def test_other_csv_is_not_openacc(tmp_path):
    path = write_ngsim_csv(tmp_path / "trajectories.csv")
    with pytest.raises(SchemaError) as exc:
        import_openacc(path)
    msg = str(exc.value)
    assert msg.startswith(f"{path}: not an OpenACC file (row 1 starts 'Vehicle_ID,Frame_ID")
    assert "\n" not in msg
    no_header = write_openacc(tmp_path / "x.csv")
    meta, table = _split(no_header)
    no_header.write_text("".join(meta) + table.to_csv(index=False, header=False))
    with pytest.raises(SchemaError, match="OpenACC metadata rows but no header"):
        import_openacc(no_header)


# ---------------------------------------------------------------- synthetic: runs and gaps


def _run_of(df: pd.DataFrame, rid: str) -> pd.DataFrame:
    return df[df["recording_id"] == rid].reset_index(drop=True)


def test_human_acc_human_is_smoothed_per_run(tmp_path):
    """Follower 3 hands over to ACC for 5 s on a 300 m circle: its two human runs are smoothed
    apart. Smoothing across the removed stretch would see a 150 m jump along the arc."""
    path = _circle_platoon(tmp_path / "JRC-VC_280219_part9.csv")
    meta, raw = _split(path)
    t = raw["Time"] - raw["Time"].iloc[0]
    acc = (t >= 25.0 - 1e-6) & (t < 30.0 - 1e-6)
    raw["Driver3"] = np.where(acc, "ACC", "Human")
    _write(path, meta, raw)
    df = import_openacc(path)
    ids = list(pd.unique(df["recording_id"]))
    assert ids == ["JRC-VC_280219_part9_f2", "JRC-VC_280219_part9_f3_s1",
                   "JRC-VC_280219_part9_f3_s2", "JRC-VC_280219_part9_f4",
                   "JRC-VC_280219_part9_f5"]
    s1, s2 = _run_of(df, ids[1]), _run_of(df, ids[2])
    assert len(s1) == 250 and len(s2) == 300
    e, n = raw["E3"].to_numpy(), raw["N3"].to_numpy()
    after = np.flatnonzero(~acc.to_numpy() & (t.to_numpy() > 25))
    yaw_alone, kappa_alone = openacc_heading_curvature(e[after], n[after], DT)
    kept = np.flatnonzero(~acc.to_numpy())
    yaw_across, kappa_across = openacc_heading_curvature(e[kept], n[kept], DT)
    yaw_across, kappa_across = yaw_across[250:], kappa_across[250:]
    head = slice(0, 10)  # the first second after the gap
    np.testing.assert_allclose(_wrap(s2["yaw"][head] - yaw_alone[head]), 0.0, atol=1e-9)
    np.testing.assert_allclose(s2["left_c2"][head], 0.5 * kappa_alone[head], atol=1e-12)
    # [rad]: across the gap the velocity points along the chord, half the arc angle off
    assert np.abs(_wrap(yaw_across[head] - yaw_alone[head])).max() > 0.2
    assert np.abs(kappa_across[head] - kappa_alone[head]).max() > 1e-3
    # and the run alone is the circle: heading (arc length / R) within 1 mrad, curvature 1 %
    arc = 30.0 * (s2["time"] - raw["Time"].iloc[0]) - 2 * 40.0  # car 3 starts 80 m back
    np.testing.assert_allclose(_wrap(s2["yaw"] - arc / 300.0), 0.0, atol=1e-3)
    np.testing.assert_allclose(s2["left_c2"], 0.5 / 300.0, rtol=0.01)


def test_nan_stretch_breaks_the_run(tmp_path):
    """A receiver dropout (NaN E/N of follower 4 for 0.5 s) splits its recording; a dropout of
    only the spacing IVS2 does not (the follower's path is whole; its leader is NaN there)."""
    path = _circle_platoon(tmp_path / "p.csv")
    meta, raw = _split(path)
    raw.loc[200:204, ["E4", "N4"]] = np.nan
    raw.loc[300:309, "IVS2"] = np.nan
    _write(path, meta, raw)
    df = import_openacc(path)
    assert list(pd.unique(df["recording_id"])) == ["p_f2", "p_f3", "p_f4_s1", "p_f4_s2", "p_f5"]
    assert df.attrs["import_stats"]["rows_nan_skipped"] == 5
    f3 = _run_of(df, "p_f3")
    assert len(f3) == 600 and f3["lead_x"].isna().sum() == 10
    assert (f3["lead_x"].isna() == f3["lead_y"].isna()).all()
    s2 = _run_of(df, "p_f4_s2")
    rows = np.arange(205, 600)
    yaw, _ = openacc_heading_curvature(raw["E4"].to_numpy()[rows], raw["N4"].to_numpy()[rows], DT)
    np.testing.assert_allclose(_wrap(s2["yaw"] - yaw), 0.0, atol=1e-9)
    np.testing.assert_allclose(s2["time"], raw["Time"].to_numpy()[rows])


def test_time_jump_breaks_the_run(tmp_path):
    """Rows cut out of the file (no NaN): a step > 1.5 samples is a break; 1.4 samples is not."""
    path = write_openacc(tmp_path / "p.csv", n=400)
    meta, raw = _split(path)
    raw = raw.drop(index=range(150, 170)).reset_index(drop=True)  # a 2.1 s step
    raw.loc[300:, "Time"] += 0.04  # a 0.14 s step: jitter, not a break
    _write(path, meta, raw)
    df = import_openacc(path)
    assert df["recording_id"].nunique() == 8  # 4 followers x 2 runs
    assert len(_run_of(df, "p_f2_s1")) == 150 and len(_run_of(df, "p_f2_s2")) == 230


def test_openacc_runs_by_hand():
    t = np.array([0.0, 0.1, 0.2, 0.3, 0.4, 0.6, 0.7, 0.8, 0.95, 1.05])
    ok = np.array([1, 1, 0, 1, 1, 1, 1, 1, 1, 1], bool)
    runs = openacc_runs(t, ok, 0.1)
    # row 2 not ok; 0.4 -> 0.6 is 2 steps; 0.8 -> 0.95 is exactly 1.5 steps: no break
    assert [r.tolist() for r in runs] == [[0, 1], [3, 4], [5, 6, 7, 8, 9]]
    assert openacc_runs(t, np.zeros(10, bool), 0.1) == []
    # a removed row breaks the run even where the steps around it are short
    t2 = np.array([0.0, 0.1, 0.15, 0.2, 0.3])
    runs = openacc_runs(t2, np.array([1, 1, 0, 1, 1], bool), 0.1)
    assert [r.tolist() for r in runs] == [[0, 1], [3, 4]]


def test_short_run_is_skipped_and_counted(tmp_path):
    """A run shorter than the 5 s curvature window (51 samples) is not imported; the one run
    left keeps the plain id."""
    path = write_openacc(tmp_path / "p.csv", n=300)
    meta, raw = _split(path)
    raw.loc[30, "Speed5"] = np.nan  # rows 0-29: 30 samples
    raw.loc[250, "E2"] = np.nan  # rows 251-299: 49 samples
    raw.loc[[100, 151], "N3"] = np.nan  # rows 101-150: 50 samples; 152-299: 148
    _write(path, meta, raw)
    df = import_openacc(path)
    st = df.attrs["import_stats"]
    assert st["runs_short_skipped"] == 3 and st["rows_short_skipped"] == 30 + 49 + 50
    assert list(pd.unique(df["recording_id"])) == ["p_f2", "p_f3_s1", "p_f3_s2", "p_f4",
                                                   "p_f5"]
    assert len(_run_of(df, "p_f5")) == 269 and len(_run_of(df, "p_f2")) == 250
    assert len(_run_of(df, "p_f3_s1")) == 100 and len(_run_of(df, "p_f3_s2")) == 148


# ------------------------------------------------------------- synthetic: vehicle layouts


def test_pairs_with_gaps_in_numbering(tmp_path):
    """Cars 2, 4, 5, 7 with IVS1 (car 1 has no columns), IVS4, IVS6 (car 6 has no columns) and
    IVS7 (car 8 absent): pairs (1, 2), (4, 5), (6, 7); no pair (2, 3), (5, 6) or (7, 8)."""
    path = write_openacc(tmp_path / "handling_part1.csv", drivers=("Human",) * 8)
    meta, raw = _split(path)
    gone = [c for k in (1, 3, 6, 8) for c in raw.columns if _vehicle_columns(k)(c)]
    raw = raw.drop(columns=gone + ["IVS2", "IVS3", "IVS5"]
                   + [c for c in raw.columns if c.startswith("Driver")])
    _write(path, meta, raw)
    df = import_openacc(path)
    st = df.attrs["import_stats"]
    assert list(pd.unique(df["recording_id"])) == ["handling_part1_f2", "handling_part1_f5",
                                                   "handling_part1_f7"]
    assert st["pairs"] == 3 and st["driver_from_metadata"] == 3
    assert st["lead_speed_missing"] == 2  # cars 1 and 6 have no Speed column
    assert st["ivs_without_follower"] == 1  # IVS7: car 8 has no columns
    f5 = _run_of(df, "handling_part1_f5")
    np.testing.assert_allclose(f5["lead_v"], 30.0)  # Speed4
    np.testing.assert_allclose(f5["lead_x"], 35.5)  # IVS4
    np.testing.assert_allclose(f5["x"], raw["E5"])
    assert _run_of(df, "handling_part1_f7")["lead_v"].isna().all()


def test_follower_partly_without_columns_or_no_pair_at_all(tmp_path):
    path = write_openacc(tmp_path / "p.csv", drop="N3")
    with pytest.raises(SchemaError, match=r"p\.csv: missing column\(s\) 'N3'"):
        import_openacc(path)
    meta, raw = _split(write_openacc(tmp_path / "q.csv", drivers=("Human", "Human")))
    _write(tmp_path / "q.csv", meta, raw.drop(columns=["IVS1"] + [c for c in raw.columns
                                                                  if c.endswith("2")]))
    with pytest.raises(SchemaError) as exc:
        import_openacc(tmp_path / "q.csv")
    assert str(exc.value).startswith(f"{tmp_path / 'q.csv'}: no follower pair: a pair (k, k+1)")
