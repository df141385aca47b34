"""Animations (safeil_sumo.experiments.animation, safeil-animate): frames of a fixture log, the plan in world coordinates, the
ego-following view, writers, and the CLIs' one-line errors."""

from __future__ import annotations

import json
import math

import numpy as np
import pandas as pd
import pytest
from PIL import Image

from safeil_sumo import animate as animate_cli
from safeil_sumo.experiments import animation as an
from safeil_sumo.roads.catalogue import resolve_net
from safeil_sumo.roads.road import load_road
from safeil_sumo.sim.rollout_log import _Log

DURATION_S = 3.0
GAP_M = 40.0
LENGTH_M, WIDTH_M = 4.54, 1.76


def write_fixture_run(folder, scenarios=("s0000", "s0001")):
    """A results folder like ``run``'s: the ego on the curved500 ego-lane centre at 30 m/s for
    DURATION_S at 100 Hz, the leader GAP_M ahead, a straight plan re-made every 0.1 s; s0001
    raises its TTC flag from 2 s on."""
    net = resolve_net("curved500")
    road = load_road(net)
    centre = road.lanes[road.ego_lane].centre
    t = np.arange(round(DURATION_S * 100) + 1) / 100.0
    s = 30.0 + 30.0 * t
    front, yaw = centre.point_at(s)
    rear_leader, _ = centre.point_at(s + GAP_M)
    plan_i = np.floor(t * 10 + 1e-9).astype(int) * 10  # the row where the tracked plan was made
    frames = []
    for name in scenarios:
        df = pd.DataFrame({c: np.zeros(len(t)) for c in _Log.COLUMNS})
        df = df.assign(t=t, x=front[:, 0], y=front[:, 1], yaw=yaw, v=30.0, front_x=front[:, 0],
                       front_y=front[:, 1], s=s, leader_x=rear_leader[:, 0],
                       leader_y=rear_leader[:, 1], leader_v=30.0, gap=GAP_M, ttc=math.inf,
                       plan_t=t[plan_i], plan_x=front[plan_i, 0], plan_y=front[plan_i, 1],
                       plan_yaw=yaw[plan_i], cp1_x=40.0, cp1_y=0.0, cp2_x=80.0, cp2_y=0.0,
                       cp3_x=120.0, cp3_y=0.0, scenario=name)
        for col in ("lane_departure", "ttc_flag", "collision"):
            df[col] = False
        if name == "s0001":
            df["ttc_flag"] = t >= 2.0
        frames.append(df)
    folder.mkdir(parents=True, exist_ok=True)
    pd.concat(frames, ignore_index=True).to_parquet(folder / "steps.parquet", index=False)
    (folder / "manifest.json").write_text(json.dumps({"config": {
        "net": str(net), "vehicle": {"length_m": LENGTH_M, "width_m": WIDTH_M}}}))
    return folder


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    return write_fixture_run(tmp_path_factory.mktemp("anim") / "run")


# ------------------------------------------------------------------------------ pure parts


def test_plan_world_of_a_hand_made_plan():
    # pose (10, 5) heading north: the plan's x axis is world +y, its y axis (left) world -x
    row = {"plan_x": 10.0, "plan_y": 5.0, "plan_yaw": math.pi / 2, "cp1_x": 10.0, "cp1_y": 0.0,
           "cp2_x": 20.0, "cp2_y": 0.0, "cp3_x": 30.0, "cp3_y": 0.0}
    spline, cps = an.plan_world(row, samples=3)
    np.testing.assert_allclose(cps, [[10, 5], [10, 15], [10, 25], [10, 35]], atol=1e-12)
    # tau = 0, 0.5, 1: Bernstein weights 1/8, 3/8, 3/8, 1/8 at the middle -> 15 m along
    np.testing.assert_allclose(spline, [[10, 5], [10, 20], [10, 35]], atol=1e-12)
    row["cp1_y"] = 2.0  # 2 m to the LEFT of a north heading is west
    assert an.plan_world(row, samples=2)[1][1] == pytest.approx([8.0, 15.0])
    assert an.plan_world({**row, "cp3_x": math.nan}) is None  # no plan (e.g. recorded)
    assert an.plan_world({"t": 0.0}) is None  # a log without plan columns


def test_boxes_from_bumpers():
    ego = an.ego_box(10.0, 0.0, 0.0, 4.0, 2.0)  # front bumper at x = 10, heading +x
    np.testing.assert_allclose(ego, [[10, 1], [10, -1], [6, -1], [6, 1]])
    lead = an.leader_box(0.0, 0.0, math.pi / 2, 4.0, 2.0)  # rear bumper at 0, heading +y
    np.testing.assert_allclose(lead.mean(axis=0), [0.0, 2.0], atol=1e-12)


def test_frame_times_and_rows():
    t = np.arange(1, 301) / 100.0  # a run's log: 0.01 .. 3.00 s
    times = an.frame_times(t, 0.1)
    assert len(times) == 30 and times[0] == 0.01 and times[-1] == pytest.approx(2.91)
    assert len(an.frame_times(np.arange(301) / 100.0, 0.1)) == 31  # both ends: D * fps + 1
    assert len(an.frame_times(t, 0.5, start_s=1.0, end_s=2.0)) == 3
    rows = an.frame_rows(t, np.array([0.0, 0.01, 0.015, 0.1, 99.0]))
    assert list(rows) == [0, 0, 0, 9, 299]  # the last row at or before each time
    with pytest.raises(an.AnimateError, match="no logged time"):
        an.frame_times(t, 0.1, start_s=5.0)


def test_frame_follows_the_ego(run_dir):
    ep = an.load_episode(run_dir, scenario="s0001")
    assert (ep.length_m, ep.width_m) == (LENGTH_M, WIDTH_M) and len(ep.log) == 301
    drawer = an.FrameDrawer(ep)
    try:
        i = 255  # 2.55 s, in the curve: the view turns with the lane
        drawer.draw(i)
        view = drawer.view.transform
        row = ep.log.iloc[i]
        # the front bumper at the view's origin, the body behind it, the leader GAP_M ahead
        np.testing.assert_allclose(view([[row["front_x"], row["front_y"]]]), [[0, 0]], atol=1e-6)
        ego = view(drawer.ego.get_xy()[:4])
        assert ego[:, 0].min() == pytest.approx(-LENGTH_M, abs=1e-3)
        lead = view(drawer.leader.get_xy()[:4]).mean(axis=0)  # ahead, along the curving lane
        assert np.hypot(*lead) == pytest.approx(GAP_M + LENGTH_M / 2, abs=0.05)
        assert 0.5 < lead[1] < 3.0  # the view is tangent at the ego; the road bends left
        # the straight plan made at 2.5 s (1.5 m back), ending 120 m ahead of its pose
        cps = view(np.column_stack(drawer.cps.get_data()))
        assert cps[0] == pytest.approx([-1.5, 0.0], abs=0.01)
        assert cps[-1, 0] == pytest.approx(118.5, abs=0.1)
        assert "TTC FLAG" in drawer.flag_text.get_text()
        assert drawer.stamp.get_text().startswith("s0001  t=  2.5")
        drawer.draw(0)
        assert drawer.flag_text.get_text() == "no flag"
    finally:
        drawer.close()


# ------------------------------------------------------------------------------ the writers


def test_gif_has_one_frame_per_tenth_of_a_second(run_dir, tmp_path, monkeypatch):
    monkeypatch.setattr(an, "find_ffmpeg", lambda: None)
    path = an.animate(run_dir, scenario="s0001", fps=10.0)
    assert path == run_dir / "animation_s0001.gif"  # default: GIF without an ffmpeg
    with Image.open(path) as im:
        assert im.n_frames == round(DURATION_S * 10) + 1
        assert im.size == (720, 368) and im.info["duration"] == 100  # [ms]
    assert not [p for p in run_dir.iterdir() if p.name.startswith(".tmp")]


def test_cli_speed_fps_and_out(run_dir, tmp_path, capsys):
    out = tmp_path / "fast.gif"
    assert animate_cli.main([str(run_dir), "--fps", "5", "--speedup", "2", "--out", str(out)]) == 0
    assert f"animation: {out}" in capsys.readouterr().out
    with Image.open(out) as im:  # a frame every 0.4 s of the 3 s of s0000: 0.0 .. 2.8 s
        assert im.n_frames == 8 and im.info["duration"] == 200


def test_mp4_frames(run_dir, tmp_path):
    ffmpeg = pytest.importorskip("imageio_ffmpeg")
    out = tmp_path / "a.mp4"
    an.animate(run_dir, out=out, fps=5.0, every_s=0.2)
    assert ffmpeg.count_frames_and_secs(str(out))[0] == round(DURATION_S * 5) + 1


@pytest.mark.parametrize("args, message", [
    (["--scenario", "s0099"], "unknown scenario 's0099'; available: s0000, s0001"),
    (["--policy", "safeil"], "a run folder (one policy): choose with --scenario"),
    (["--out", "x.avi"], ".mp4 or .gif"),
    (["--out", "x.mp4"], "an .mp4 needs ffmpeg"),
    (["--start-s", "10"], "no logged time"),
])
def test_cli_bad_input_one_line(run_dir, tmp_path, capsys, monkeypatch, args, message):
    monkeypatch.setattr(an, "find_ffmpeg", lambda: None)
    args = [str(tmp_path / a) if a.startswith("x.") else a for a in args]
    assert animate_cli.main([str(run_dir), *args]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and err.count("\n") == 1 and message in err
    assert not list(tmp_path.iterdir())


def test_cli_missing_folder_and_bad_fps(tmp_path, capsys):
    assert animate_cli.main([str(tmp_path / "nope")]) == 2
    assert capsys.readouterr().err == f"error: results folder not found: {tmp_path / 'nope'}\n"
    assert animate_cli.main([str(tmp_path)]) == 2
    assert "no steps.parquet" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exc:
        animate_cli.main([str(tmp_path), "--fps", "0"])
    assert exc.value.code == 2


# ------------------------------------------------------------------- run / replay --animate


@pytest.mark.sumo
def test_run_animate_names_and_errors(tmp_path, capsys, monkeypatch):
    from safeil_sumo import run

    out = tmp_path / "res"
    assert run.main(["--net", "straight", "--policy", "analytic", "--scenarios", "2",
                     "--out", str(out), "--animate", "s0002"]) == 2
    err = capsys.readouterr().err
    assert err == "error: --animate: unknown scenario 's0002'; available: s0000, s0001\n"
    assert not out.exists()

    calls = []

    def fake(run_dir, scenario=None, **kwargs):  # the drawing is tested above: check the wiring
        assert (run_dir / "steps.parquet").is_file()  # the results are in place first
        calls.append(scenario)
        return run_dir / f"animation_{scenario}.gif"

    monkeypatch.setattr(run.animation, "animate", fake)
    assert run.main(["--net", "straight", "--policy", "analytic", "--scenarios", "1",
                     "--no-plots", "--out", str(out), "--animate"]) == 0
    assert calls == ["s0000"]
    assert f"animation: {out / 'animation_s0000.gif'}" in capsys.readouterr().out


@pytest.mark.sumo
def test_replay_animate_each_policy(tmp_path, capsys, monkeypatch):
    from fixtures_data import arc_drive

    from safeil_sumo import replay
    from safeil_sumo.data.schema import save_drive

    monkeypatch.setattr(an, "find_ffmpeg", lambda: None)
    drive = tmp_path / "arc.parquet"
    save_drive(arc_drive(), drive)
    out = tmp_path / "out"
    assert replay.main(["--source", str(drive), "--maneuver", "longest", "--duration-s", "2",
                        "--policy", "recorded", "--out", str(out), "--animate"]) == 0
    with Image.open(out / "animation_recorded.gif") as im:
        assert im.n_frames == 20  # the replay logs 0.01 .. 2.00 s: frames 0.01 .. 1.91 s
    ep = an.load_episode(out)
    assert ep.name == "recorded" and ep.human is not None
    # the recorded pseudo-planner drives the human's own path
    assert np.hypot(ep.log["front_x"].iloc[-1] - ep.human["x"].iloc[-1],
                    ep.log["front_y"].iloc[-1] - ep.human["y"].iloc[-1]) < 0.5
    assert animate_cli.main([str(out), "--scenario", "s0000"]) == 2
    assert "replay folder: choose with --policy" in capsys.readouterr().err
