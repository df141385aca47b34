"""The highD and car-following CSV importers and the ``format:path`` entry, on small files the
tests write in each documented layout (no real highD data: none is shipped), values by hand."""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from fixtures_data import write_ngsim_csv, write_openacc
from hypothesis import given, settings
from hypothesis import strategies as st

from safeil_sumo.data.car_following_csv import (
    import_car_following_csv,
    parse_column_map,
)
from safeil_sumo.data.drive_import import import_drive, import_drives, split_spec
from safeil_sumo.data.highd import highd_recording_files, import_highd
from safeil_sumo.data.importers import MIN_GAP, ImportArgumentError
from safeil_sumo.data.pipeline import PipelineConfig, run_pipeline
from safeil_sumo.data.schema import SchemaError, load_drive, save_drive

RATE = 25  # [Hz] highD's frame rate
UPPER = "5.0;9.0;13.0"  # image y [m] of the upper carriageway's lines (drivingDirection 1)
LOWER = "19.0;23.0;27.0"  # the lower carriageway's (drivingDirection 2)

TRACK_COLUMNS = (
    "frame", "id", "x", "y", "width", "height", "xVelocity", "yVelocity", "xAcceleration",
    "yAcceleration", "frontSightDistance", "backSightDistance", "dhw", "thw", "ttc",
    "precedingXVelocity", "precedingId", "followingId", "leftPrecedingId", "leftAlongsideId",
    "leftFollowingId", "rightPrecedingId", "rightAlongsideId", "rightFollowingId", "laneId")
META_COLUMNS = (
    "id", "width", "height", "initialFrame", "finalFrame", "numFrames", "class",
    "drivingDirection", "traveledDistance", "minXVelocity", "maxXVelocity", "meanXVelocity",
    "minDHW", "minTHW", "minTTC", "numLaneChanges")


def vehicle(vid: int, cls: str, direction: int, x0: float, y: float, length: float,
            width: float, vx: float, lane: int, preceding: int = 0, vy: float = 0.0,
            lead_until: int | None = None) -> dict:
    """One highD vehicle: box upper-left corner ``(x0, y)`` at frame 1 (image frame, y down),
    ``length`` along x (highD's ``width``), ``width`` across (highD's ``height``), signed
    ``xVelocity`` ``vx``; ``preceding`` its leader's id up to frame ``lead_until``, then 0."""
    return {"id": vid, "class": cls, "dir": direction, "x0": x0, "y": y, "w": length,
            "h": width, "vx": vx, "vy": vy, "lane": lane, "pre": preceding,
            "lead_until": lead_until}


# the hand-computed scene: both carriageways, a truck and cars, leaders without leader
# (precedingId 0) and a follower whose leader goes at frame 451
SCENE = [
    # lower carriageway, driving +x (drivingDirection 2), lane 5 between y = 19 and 23
    vehicle(1, "Car", 2, x0=130.0, y=20.0, length=4.0, width=2.0, vx=20.0, lane=5),
    vehicle(2, "Truck", 2, x0=100.0, y=19.5, length=12.0, width=2.5, vx=20.0, lane=5,
            preceding=1, lead_until=450),
    vehicle(3, "Car", 2, x0=80.0, y=20.1, length=4.5, width=1.8, vx=20.0, lane=5, preceding=2),
    # upper carriageway, driving -x (drivingDirection 1), lane 2 between y = 5 and 9
    vehicle(4, "Car", 1, x0=200.0, y=5.5, length=4.0, width=2.0, vx=-25.0, lane=2),
    vehicle(5, "Car", 1, x0=230.0, y=6.5, length=5.0, width=2.0, vx=-25.0, lane=2, preceding=4),
]


def track_rows(vehicles: list[dict], frames: int) -> pd.DataFrame:
    """The ``NN_tracks.csv`` table of ``vehicles`` at constant velocity, frames 1..frames."""
    rows = []
    for v in vehicles:
        f = np.arange(1, frames + 1)
        t = (f - 1) / RATE
        pre = np.where(f <= (v["lead_until"] or frames), v["pre"], 0)
        row = {c: np.zeros(frames) for c in TRACK_COLUMNS}
        row.update({"frame": f, "id": v["id"], "x": v["x0"] + v["vx"] * t,
                    "y": v["y"] + v["vy"] * t, "width": v["w"], "height": v["h"],
                    "xVelocity": v["vx"], "yVelocity": v["vy"], "frontSightDistance": 100.0,
                    "backSightDistance": 100.0, "precedingId": pre, "laneId": v["lane"]})
        rows.append(pd.DataFrame(row))
    return pd.concat(rows, ignore_index=True).sort_values(["frame", "id"], kind="stable")


def meta_rows(vehicles: list[dict], frames: int) -> pd.DataFrame:
    return pd.DataFrame([{
        "id": v["id"], "width": v["w"], "height": v["h"], "initialFrame": 1,
        "finalFrame": frames, "numFrames": frames, "class": v["class"],
        "drivingDirection": v["dir"], "traveledDistance": abs(v["vx"]) * frames / RATE,
        "minXVelocity": abs(v["vx"]), "maxXVelocity": abs(v["vx"]), "meanXVelocity": abs(v["vx"]),
        "minDHW": -1, "minTHW": -1, "minTTC": -1, "numLaneChanges": 0} for v in vehicles],
        columns=list(META_COLUMNS))


def write_highd(folder: Path, vehicles: list[dict] = SCENE, frames: int = 500, nn: int = 1,
                upper: str = UPPER, lower: str = LOWER) -> Path:
    """The three files of recording ``nn`` in the documented highD layout; returns ``folder``."""
    folder.mkdir(parents=True, exist_ok=True)
    track_rows(vehicles, frames).to_csv(folder / f"{nn:02d}_tracks.csv", index=False)
    meta_rows(vehicles, frames).to_csv(folder / f"{nn:02d}_tracksMeta.csv", index=False)
    cars = sum(v["class"] == "Car" for v in vehicles)
    pd.DataFrame([{
        "id": nn, "frameRate": RATE, "locationId": 1, "speedLimit": -1, "month": "09.2017",
        "weekDay": "Tue", "startTime": "08:38", "duration": frames / RATE,
        "totalDrivenDistance": 1.0, "totalDrivenTime": 1.0, "numVehicles": len(vehicles),
        "numCars": cars, "numTrucks": len(vehicles) - cars, "upperLaneMarkings": upper,
        "lowerLaneMarkings": lower}]).to_csv(folder / f"{nn:02d}_recordingMeta.csv", index=False)
    return folder


@pytest.fixture
def scene(tmp_path: Path) -> pd.DataFrame:
    return import_highd(write_highd(tmp_path / "highD"))


def rec(df: pd.DataFrame, vid: int) -> pd.DataFrame:
    return df[df["recording_id"] == f"highd_01_{vid}"].reset_index(drop=True)


# ------------------------------------------------------------------------------------ highD


def test_highd_front_centre_from_the_upper_left_corner(scene):
    """Car 3 (lower lanes, +x): box x = 80 + 20 t, y = 20.1 (upper-left, y down), 4.5 x 1.8 m:
    front centre (84.5 + 20 t, 21.0) in the image, (84.5 + 20 t, -21.0) in the y-up road frame;
    lines at image y 19 (left, its driver's left is up) and 23: c0 = +2.0 and -2.0."""
    c = rec(scene, 3)
    t = np.arange(500) / RATE
    np.testing.assert_allclose(c["x"], 84.5 + 20.0 * t, atol=1e-9)
    np.testing.assert_allclose(c["y"], -21.0, atol=1e-9)
    np.testing.assert_allclose(c["time"], (np.arange(500) + 1) / RATE)
    np.testing.assert_allclose(c["left_c0"], 2.0, atol=1e-9)
    np.testing.assert_allclose(c["right_c0"], -2.0, atol=1e-9)
    np.testing.assert_allclose(c[["yaw", "left_c1", "right_c1", "left_c2", "right_c3"]], 0.0,
                               atol=1e-12)
    np.testing.assert_allclose(c["v_x"], 20.0)
    assert (c["lane_index"] == 5).all()


def test_highd_both_directions_leader_ahead_and_lines_on_their_sides(scene):
    """Truck 2 (+x): front 112 + 20 t, leader 1's rear 130 + 20 t: gap 18 m; centre y 20.75 ->
    lines +1.75 (y 19) / -2.25 (y 23); leader centre 21.0 is 0.25 m lower in the image, i.e.
    on the truck's right: lead_y = -0.25.
    Car 5 (-x): front = box LEFT edge 230 - 25 t, leader 4's rear = its RIGHT edge 204 - 25 t:
    gap 26 m; centre y 7.5, its driver's left is DOWN the image: left line y 9 -> +1.5, right
    line y 5 -> -2.5; leader centre 6.5 is up the image, on car 5's right: lead_y = -1.0."""
    truck, car = rec(scene, 2), rec(scene, 5)
    following = truck[truck["time"] <= 450 / RATE + 1e-9]
    np.testing.assert_allclose(following["lead_x"], 18.0, atol=1e-9)
    np.testing.assert_allclose(following["lead_y"], -0.25, atol=1e-9)
    np.testing.assert_allclose(following["lead_v"], 20.0)
    np.testing.assert_allclose(truck[["left_c0", "right_c0"]], [[1.75, -2.25]] * 500, atol=1e-9)
    np.testing.assert_allclose(car["lead_x"], 26.0, atol=1e-9)
    np.testing.assert_allclose(car["lead_y"], -1.0, atol=1e-9)
    np.testing.assert_allclose(car["lead_v"], 25.0)
    np.testing.assert_allclose(car["v_x"], 25.0)
    np.testing.assert_allclose(car[["left_c0", "right_c0"]], [[1.5, -2.5]] * 500, atol=1e-9)
    # car 5 drives towards -x in the image: the road frame is turned 180 degrees, so it drives
    # +x there with heading 0, front centre (-(230 - 25 t), +7.5)
    t = np.arange(500) / RATE
    np.testing.assert_allclose(car["x"], -(230.0 - 25.0 * t), atol=1e-9)
    np.testing.assert_allclose(car["y"], 7.5, atol=1e-9)
    np.testing.assert_allclose(car["yaw"], 0.0, atol=1e-12)
    np.testing.assert_allclose(rec(scene, 3)["lead_y"], 0.25, atol=1e-9)  # truck on its left
    np.testing.assert_allclose(rec(scene, 3)["lead_x"], 15.5, atol=1e-9)  # 100 - 84.5


def test_highd_preceding_zero_rows_keep_the_ego_without_leader(scene):
    truck = rec(scene, 2)
    gone = truck["time"] > 450 / RATE
    assert gone.sum() == 50
    assert truck.loc[gone, ["lead_x", "lead_y", "lead_v"]].isna().all().all()
    assert truck.loc[~gone, "lead_x"].notna().all()
    for leader in (1, 4):  # precedingId 0 throughout: a recording without any leader
        assert rec(scene, leader)["lead_x"].isna().all()
    stats = scene.attrs["import_stats"]["files"][0]
    assert stats["rows_without_leader"] == 50 + 2 * 500
    assert stats["recordings"] == 5 and stats["rows"] == 2500


def test_highd_trucks_and_cars_both_imported_class_in_stats(scene):
    stats = scene.attrs["import_stats"]["files"][0]
    assert stats["cars"] == 4 and stats["trucks"] == 1
    assert stats["vehicle_class"] == {"highd_01_1": "Car", "highd_01_2": "Truck",
                                      "highd_01_3": "Car", "highd_01_4": "Car",
                                      "highd_01_5": "Car"}
    assert sorted(scene["recording_id"].unique()) == [f"highd_01_{i}" for i in range(1, 6)]


def test_highd_heading_tilts_the_lines(tmp_path):
    """Drifting left at 0.5 m/s while driving 20 m/s, in either direction (yVelocity -0.5 on the
    lower lanes, +0.5 on the upper): psi = atan(0.5 / 20), c1 = -0.025, c0 = offset / cos; the
    leaders drive 22 m/s."""
    cars = [vehicle(1, "Car", 2, 100.0, 20.0, 4.0, 2.0, 20.0, 5, preceding=2, vy=-0.5),
            vehicle(2, "Car", 2, 130.0, 20.0, 4.0, 2.0, 22.0, 5),
            vehicle(3, "Car", 1, 300.0, 6.0, 4.0, 2.0, -20.0, 2, preceding=4, vy=0.5),
            vehicle(4, "Car", 1, 270.0, 6.0, 4.0, 2.0, -22.0, 2)]
    df = import_highd(write_highd(tmp_path, cars, frames=3))
    psi = np.arctan2(0.5, 20.0)
    for vid in (1, 3):
        first = rec(df, vid).iloc[0]
        assert first["yaw"] == pytest.approx(psi)
        assert first["left_c1"] == pytest.approx(-0.025)
        assert first["left_c0"] == pytest.approx(2.0 / np.cos(psi))
        assert first["right_c0"] == pytest.approx(-2.0 / np.cos(psi))
        # the leader 26 m ahead (30 m front to front, minus its 4 m) straight along the road
        assert first["lead_x"] == pytest.approx(26.0 * np.cos(psi))
        assert first["lead_y"] == pytest.approx(-26.0 * np.sin(psi))
        assert first["lead_v"] == 22.0 and first["v_x"] == 20.0  # the leader's own speed


def _turned(v: dict, road_length: float, road_height: float) -> dict:
    """The same vehicle on the other carriageway: the image turned 180 degrees."""
    return v | {"dir": 3 - v["dir"], "x0": road_length - v["x0"] - v["w"],
                "y": road_height - v["y"] - v["h"], "vx": -v["vx"], "vy": -v["vy"]}


@settings(max_examples=25, deadline=None)
@given(lateral=st.floats(0.0, 1.2), length=st.floats(3.5, 18.0), width=st.floats(1.6, 2.6),
       lead_len=st.floats(3.5, 18.0), gap=st.floats(0.5, 80.0), speed=st.floats(5.0, 40.0),
       drift=st.floats(-1.0, 1.0), lead_shift=st.floats(-0.8, 0.8))
def test_highd_direction_one_is_direction_two_turned(lateral, length, width, lead_len, gap,
                                                     speed, drift, lead_shift):
    """Any follower/leader pair on the lower lanes and the same pair turned 180 degrees in the
    image onto the upper lanes give the same ego-frame values; the gap is the hand gap."""
    y0 = 19.0 + 0.2 + lateral  # the box's upper edge inside lane 19..23
    pair = [vehicle(1, "Car", 2, 50.0, y0, length, width, speed, 5, preceding=2, vy=drift),
            vehicle(2, "Truck", 2, 50.0 + length + gap, y0 + lead_shift, lead_len, 2.0, speed,
                    5)]
    # road 420 m x 32 m: markings turned too (y -> 32 - y)
    turned = [_turned(v, 420.0, 32.0) | {"lane": 2} for v in pair]
    with tempfile.TemporaryDirectory() as tmp:
        down = import_highd(write_highd(Path(tmp) / "a", pair, frames=2))
        up = import_highd(write_highd(Path(tmp) / "b", turned, frames=2, upper="5.0;9.0;13.0",
                                      lower="19.0;23.0;27.0"))
    cols = ["v_x", "yaw", "left_c0", "right_c0", "left_c1", "lead_x", "lead_y", "lead_v"]
    np.testing.assert_allclose(up[cols].to_numpy(float), down[cols].to_numpy(float),
                               atol=1e-9, equal_nan=True)
    first = rec(down, 1).iloc[0]
    psi = np.arctan2(-drift, speed)
    dy = -lead_shift + 0.5 * (width - 2.0)  # leader centre minus ego centre, y up
    assert first["lead_x"] == pytest.approx(np.cos(psi) * gap + np.sin(psi) * dy, abs=1e-9)
    assert first["left_c0"] > 0 > first["right_c0"]
    assert first["left_c0"] - first["right_c0"] == pytest.approx(4.0 / np.cos(psi))


def test_highd_recording_files_by_directory_prefix_and_file(tmp_path):
    write_highd(tmp_path, SCENE[:2], frames=3, nn=1)
    write_highd(tmp_path, SCENE[:2], frames=3, nn=12)
    assert [t.name for t, _, _ in highd_recording_files(tmp_path)] == ["01_tracks.csv",
                                                                       "12_tracks.csv"]
    for given_path in (tmp_path / "12", tmp_path / "12_", tmp_path / "12_tracksMeta.csv"):
        (t, m, r), = highd_recording_files(given_path)
        assert (t.name, m.name, r.name) == ("12_tracks.csv", "12_tracksMeta.csv",
                                            "12_recordingMeta.csv")
    both = import_highd(tmp_path)
    assert sorted(both["recording_id"].unique()) == ["highd_01_1", "highd_01_2", "highd_12_1",
                                                     "highd_12_2"]
    assert len(import_highd(tmp_path / "12")) == 6


def test_highd_output_survives_save_and_load(scene, tmp_path):
    save_drive(scene, tmp_path / "d.parquet")
    back = load_drive(tmp_path / "d.parquet")
    pd.testing.assert_frame_equal(back, scene, check_dtype=False)


# --------------------------------------------------------------------------- highD bad input


def _one_line(exc: pytest.ExceptionInfo) -> str:
    msg = str(exc.value)
    assert "\n" not in msg
    return msg


def test_highd_missing_column_names_file_column_and_found(tmp_path):
    write_highd(tmp_path, SCENE[:2], frames=3)
    t = pd.read_csv(tmp_path / "01_tracks.csv").rename(columns={"precedingId": "preceding"})
    t.to_csv(tmp_path / "01_tracks.csv", index=False)
    with pytest.raises(SchemaError) as exc:
        import_highd(tmp_path)
    msg = _one_line(exc)
    assert "01_tracks.csv" in msg and "missing column(s) 'precedingId'" in msg
    assert "have: frame, id, x, y" in msg and "preceding," in msg


def test_highd_empty_files(tmp_path):
    write_highd(tmp_path, SCENE[:2], frames=3)
    (tmp_path / "01_tracks.csv").write_text("")
    with pytest.raises(SchemaError, match=r"01_tracks\.csv: empty file"):
        import_highd(tmp_path)
    (tmp_path / "01_tracks.csv").write_text(",".join(TRACK_COLUMNS) + "\n")
    with pytest.raises(SchemaError, match=r"01_tracks\.csv: empty file \(a header, no rows\)"):
        import_highd(tmp_path)


def test_highd_without_any_leader(tmp_path):
    write_highd(tmp_path, [SCENE[0], SCENE[3]], frames=3)
    with pytest.raises(SchemaError) as exc:
        import_highd(tmp_path)
    assert "01_tracks.csv, column 'precedingId': no row with a leader" in _one_line(exc)


def test_highd_km_h_speed_names_the_row(tmp_path):
    write_highd(tmp_path, SCENE[:2], frames=3)
    t = pd.read_csv(tmp_path / "01_tracks.csv")
    t.loc[3, "xVelocity"] = 72.0 * 1.0  # 72 "m/s": km/h written where m/s is documented
    t.to_csv(tmp_path / "01_tracks.csv", index=False)
    with pytest.raises(SchemaError) as exc:
        import_highd(tmp_path)
    msg = _one_line(exc)
    assert "01_tracks.csv, column 'xVelocity', row 3: speed 72 m/s" in msg
    assert "km/h given where m/s is declared" in msg


def test_highd_other_levelx_layouts_and_bad_meta_are_named(tmp_path):
    write_highd(tmp_path, SCENE[:2], frames=3)
    t = pd.read_csv(tmp_path / "01_tracks.csv").rename(columns={"x": "xCenter", "y": "yCenter"})
    t.to_csv(tmp_path / "01_tracks.csv", index=False)
    with pytest.raises(SchemaError, match="an inD/rounD/exiD tracks file"):
        import_highd(tmp_path)
    write_highd(tmp_path, SCENE[:2], frames=3, lower="19.0")
    with pytest.raises(SchemaError, match=r"01_recordingMeta\.csv, column 'lowerLaneMarkings', "
                                          r"row 0: needs two or more"):
        import_highd(tmp_path)
    write_highd(tmp_path, SCENE[:2], frames=3)
    m = pd.read_csv(tmp_path / "01_tracksMeta.csv")
    m.loc[1, "drivingDirection"] = 3
    m.to_csv(tmp_path / "01_tracksMeta.csv", index=False)
    with pytest.raises(SchemaError, match=r"01_tracksMeta\.csv, column 'drivingDirection', "
                                          r"row 1: must be 1"):
        import_highd(tmp_path)
    m.loc[1, "drivingDirection"] = 1  # the truck drives +x: the wrong carriageway
    m.to_csv(tmp_path / "01_tracksMeta.csv", index=False)
    with pytest.raises(SchemaError, match="drives against it"):
        import_highd(tmp_path)
    (tmp_path / "01_tracksMeta.csv").unlink()
    with pytest.raises(SchemaError, match=r"01_tracksMeta\.csv: no such file"):
        import_highd(tmp_path)
    with pytest.raises(SchemaError, match="no highD recording"):
        import_highd(tmp_path / "..")


# -------------------------------------------------------------------------- car-following CSV

CSV_MAP = "time=t,v=follower_speed,lead_v=leader_speed,gap=gap_m,driver=who"


def write_cf_csv(path: Path, speed: float = 20.0, lead_speed: float = 21.0, n: int = 150,
                 drivers: tuple[str, ...] = ("anna", "bo")) -> Path:
    """``n`` samples at 10 Hz per driver: speeds constant, gap 30 m, rows 5..9 without leader,
    row 2 a -0.4 m gap (a tracking artefact)."""
    parts = []
    for who in drivers:
        gap = np.full(n, 30.0)
        gap[2] = -0.4
        gap[5:10] = np.nan
        parts.append(pd.DataFrame({"t": np.round(np.arange(n) * 0.1, 6), "follower_speed": speed,
                                   "leader_speed": lead_speed, "gap_m": gap, "who": who,
                                   "note": "x"}))
    pd.concat(parts).to_csv(path, index=False)
    return path


def test_csv_mapping_recordings_and_hand_values(tmp_path):
    df = import_car_following_csv(write_cf_csv(tmp_path / "my drive.csv"), CSV_MAP)
    assert list(df["recording_id"].unique()) == ["my_drive_anna", "my_drive_bo"]
    a = df[df["recording_id"] == "my_drive_anna"].reset_index(drop=True)
    np.testing.assert_allclose(a["x"], 2.0 * np.arange(150), atol=1e-9)  # 20 m/s x 0.1 s
    np.testing.assert_allclose(a[["y", "yaw", "left_c1", "left_c2", "right_c2"]], 0.0)
    np.testing.assert_allclose(a[["left_c0", "right_c0"]], [[1.75, -1.75]] * 150)
    assert a.loc[2, "lead_x"] == MIN_GAP
    assert a.loc[5:9, ["lead_x", "lead_y", "lead_v"]].isna().all().all()
    np.testing.assert_allclose(a.drop(index=[2, 5, 6, 7, 8, 9])["lead_x"], 30.0)
    np.testing.assert_allclose(a.loc[a["lead_x"].notna(), "lead_v"], 21.0)
    stats = df.attrs["import_stats"]
    assert stats["gap_clipped"] == 2 and stats["rows_without_leader"] == 10
    assert stats["mapping"]["v"] == "follower_speed" and stats["speed_unit"] == "m/s"
    # the dict form is the same mapping
    as_dict = import_car_following_csv(tmp_path / "my drive.csv", parse_column_map(CSV_MAP))
    pd.testing.assert_frame_equal(as_dict, df)


def test_csv_km_h_declared(tmp_path):
    path = write_cf_csv(tmp_path / "kmh.csv", speed=72.0, lead_speed=90.0)
    df = import_car_following_csv(path, CSV_MAP, speed_unit="km/h")
    np.testing.assert_allclose(df["v_x"], 20.0)
    np.testing.assert_allclose(df["lead_v"].dropna(), 25.0)
    np.testing.assert_allclose(df["x"].iloc[:3], [0.0, 2.0, 4.0])


def test_csv_default_names_and_id_column_split_interleaved_rows(tmp_path):
    """Without a map the roles are the column names; rows of two ids interleaved in the file are
    grouped (first appearance first), each in its own time order."""
    pd.DataFrame({"id": ["b", "a", "b", "a"], "time": [0.0, 0.0, 0.1, 0.1],
                  "v": [10.0, 12.0, 10.0, 12.0], "gap": [20.0, 25.0, 20.0, np.nan]}
                 ).to_csv(tmp_path / "f.csv", index=False)
    df = import_car_following_csv(tmp_path / "f.csv")
    assert list(df["recording_id"]) == ["f_b", "f_b", "f_a", "f_a"]
    np.testing.assert_allclose(df["x"], [0.0, 1.0, 0.0, 1.2])
    assert df["lead_v"].isna().all() and df.attrs["import_stats"]["lead_speed_missing"] == 3


def test_csv_km_h_given_where_m_s_declared_names_the_row(tmp_path):
    path = tmp_path / "d.csv"
    pd.DataFrame({"t": [0.0, 0.1, 0.2, 0.3], "follower_speed": [65.0, 68.0, 71.5, 72.0],
                  "gap_m": 30.0}).to_csv(path, index=False)
    with pytest.raises(SchemaError) as exc:
        import_car_following_csv(path, "time=t,v=follower_speed,gap=gap_m")
    msg = _one_line(exc)
    assert msg.startswith(f"{path}, column 'follower_speed', row 2: speed 71.5 m/s (read as m/s)")
    assert "km/h given where m/s is declared?" in msg
    # the leader's speed is checked too
    pd.DataFrame({"time": [0.0, 0.1], "v": [20.0, 20.0], "lead_v": [20.0, 90.0],
                  "gap": 30.0}).to_csv(path, index=False)
    with pytest.raises(SchemaError, match=r"d\.csv, column 'lead_v', row 1: speed 90 m/s"):
        import_car_following_csv(path)


def test_csv_missing_or_misnamed_column(tmp_path):
    path = write_cf_csv(tmp_path / "d.csv", n=20)
    with pytest.raises(SchemaError) as exc:
        import_car_following_csv(path, "time=t,v=speed,gap=gap_m")
    assert _one_line(exc) == (f"{path}: missing column 'speed' (mapped to 'v'; have: t, "
                              "follower_speed, leader_speed, gap_m, who, note)")
    with pytest.raises(SchemaError) as exc:
        import_car_following_csv(path, "time=t,v=follower_speed")
    msg = _one_line(exc)
    assert msg.startswith(f"{path}: no column for 'gap'") and "have: t, follower_speed" in msg


def test_csv_empty_file_no_leader_bad_values(tmp_path):
    path = tmp_path / "d.csv"
    path.write_text("")
    with pytest.raises(SchemaError, match=r"d\.csv: empty file"):
        import_car_following_csv(path)
    path.write_text("time,v,gap\n")
    with pytest.raises(SchemaError, match=r"d\.csv: empty file \(a header, no rows\)"):
        import_car_following_csv(path)
    path.write_text("time,v,gap\n0.0,20,\n0.1,20,\n")
    with pytest.raises(SchemaError) as exc:
        import_car_following_csv(path)
    assert _one_line(exc) == (f"{path}, column 'gap': no row with a leader (the gap is empty "
                              "everywhere)")
    path.write_text("time,v,gap\n0.0,20,30\n0.1,fast,30\n")
    with pytest.raises(SchemaError, match=r"d\.csv, column 'v', row 1: not a number: 'fast'"):
        import_car_following_csv(path)
    path.write_text("time,v,gap\n0.0,20,30\n0.1,,30\n")
    with pytest.raises(SchemaError, match=r"d\.csv, column 'v', row 1: empty"):
        import_car_following_csv(path)
    path.write_text("time,v,gap\n0.0,20,30\n0.2,20,30\n0.1,20,30\n")
    with pytest.raises(SchemaError, match=r"d\.csv, column 'time', row 2: time does not "
                                          r"increase"):
        import_car_following_csv(path)


def test_column_map_and_unit_arguments():
    assert parse_column_map(" time = t , v=speed,gap=g ") == {"time": "t", "v": "speed",
                                                              "gap": "g"}
    with pytest.raises(ImportArgumentError, match=r"unknown role 'speed' \(known: time, v, gap"):
        parse_column_map("time=t,speed=v")
    with pytest.raises(ImportArgumentError, match="item 'v' is not role=column"):
        parse_column_map("time=t,v")
    with pytest.raises(ImportArgumentError, match="role 'v' mapped twice"):
        parse_column_map("v=a,v=b")
    with pytest.raises(ImportArgumentError, match=r"speed unit 'mph' unknown \(known: m/s, km/h\)"):
        import_car_following_csv("whatever.csv", speed_unit="mph")


# --------------------------------------------------------------------------- format:path entry


def test_spec_dispatch_to_each_importer(tmp_path):
    highd = write_highd(tmp_path / "highD", SCENE, frames=20)
    pd.testing.assert_frame_equal(import_drives(f"highd:{highd}"), import_highd(highd))
    csv = write_cf_csv(tmp_path / "kmh.csv", speed=72.0, lead_speed=72.0, n=30)
    got = import_drive(f"csv:{csv}", csv_map=CSV_MAP, speed_unit="km/h")
    np.testing.assert_allclose(got["v_x"], 20.0)
    acc = tmp_path / "acc"
    acc.mkdir()
    write_openacc(acc / "JRC-VC_280219_part2.csv.gz", gz=True)
    write_openacc(acc / "JRC-VC_280219_part3.csv")
    (acc / "Vicolungo_veh_specifications.csv").write_text("Vehicles,Max power (kW)\nA,100\n")
    from_dir = import_drive(f"openacc:{acc}")
    assert from_dir["recording_id"].nunique() == 8
    assert from_dir.attrs["import_stats"]["files_skipped"] == ["Vicolungo_veh_specifications.csv"]
    assert import_drive(f"OpenACC:{acc / 'JRC-VC_280219_part3.csv'}")["recording_id"].nunique() == 4
    ngsim = import_drive(f"ngsim:{write_ngsim_csv(tmp_path / 'trajectories.csv')}")
    assert list(ngsim["recording_id"].unique()) == ["2-1", "3-2", "3-1"]
    both = import_drives([f"highd:{highd}", f"csv:{csv}"], csv_map=CSV_MAP, speed_unit="km/h")
    assert both["recording_id"].nunique() == 5 + 2 and len(both) == 5 * 20 + 2 * 30
    assert [s["spec"] for s in both.attrs["import_stats"]["specs"]] == [f"highd:{highd}",
                                                                        f"csv:{csv}"]


def test_spec_errors_are_one_line(tmp_path):
    known = "known formats: highd:PATH, csv:PATH, openacc:PATH, ngsim:PATH"
    with pytest.raises(ImportArgumentError) as exc:
        import_drives("inD:data/inD")
    assert _one_line(exc) == f"data spec 'inD:data/inD': unknown format 'ind' ({known})"
    with pytest.raises(ImportArgumentError, match=r"'highd': not format:path"):
        split_spec("highd")
    with pytest.raises(ImportArgumentError, match="no path"):
        split_spec("csv: ")
    with pytest.raises(ImportArgumentError, match="no data spec given"):
        import_drives([])
    highd = write_highd(tmp_path / "h", SCENE[:2], frames=3)
    with pytest.raises(SchemaError, match="recording id 'highd_01_1' also comes from"):
        import_drives([f"highd:{highd}", f"highd:{highd / '01'}"])
    acc = tmp_path / "acc.csv"
    write_openacc(acc, drivers=("Human",) + ("ACC",) * 4)
    with pytest.raises(SchemaError, match="no recording imported"):
        import_drive(f"openacc:{acc}")
    with pytest.raises(SchemaError, match="no such file"):
        import_drive(f"csv:{tmp_path / 'nope.csv'}")


# ------------------------------------------------------------------------------ end to end


def test_imported_drives_pass_the_pipeline(tmp_path):
    """Steps 1-7 accept both imports. highD: followers 3 and 5 follow for 19.96 s -> 80 samples
    at 4 Hz -> 60 tuples each (20 ahead); truck 2 for 17.96 s -> 72 samples -> 52 tuples;
    leaders 1 and 4 have no leader: none. CSV: each driver follows rows 10..149 (rows 5..9 have
    no leader, rows 0..4 are a 0.4 s segment, too short): 13.9 s -> 56 samples -> 36 tuples."""
    drive = import_drives([f"highd:{write_highd(tmp_path / 'h')}",
                           f"csv:{write_cf_csv(tmp_path / 'cf.csv')}"], csv_map=CSV_MAP)
    tup, rep = run_pipeline(drive, PipelineConfig(), source="imported")
    per = pd.Series(tup.maneuver_id).str.split("#").str[0].value_counts().to_dict()
    assert per == {"highd_01_3": 60, "highd_01_5": 60, "highd_01_2": 52,
                   "cf_anna": 36, "cf_bo": 36}
    assert rep.events.get("lane_change", 0) == 0 and rep.events.get("line_crossing", 0) == 0
    # the 9 features (left c0..c2, right c0..c2, v, v_lead, gap) of each ego, by hand
    expected = {"highd_01_3": [2.0, 0, 0, -2.0, 0, 0, 20.0, 20.0, 15.5],
                "highd_01_5": [1.5, 0, 0, -2.5, 0, 0, 25.0, 25.0, 26.0],
                "highd_01_2": [1.75, 0, 0, -2.25, 0, 0, 20.0, 20.0, 18.0],
                "cf_anna": [1.75, 0, 0, -1.75, 0, 0, 20.0, 21.0, 30.0]}
    owner = pd.Series(tup.maneuver_id).str.split("#").str[0].to_numpy()
    for rid, feats in expected.items():
        np.testing.assert_allclose(tup.features[owner == rid], [feats] * per[rid], atol=1e-9)
