"""``safeil-evaluate MODEL`` (safeil_sumo.evaluate, docs/evaluate.md): the verdict rules and the
rendering by hand, a clean Ctrl-C, the one-line error of an unknown model, and one real libsumo
run of the whole report card whose report.md and report.json must agree."""

from __future__ import annotations

import json
import math
import os
import re
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest

from safeil_sumo import evaluate as ev
from safeil_sumo.data.by_path import DataSpec
from safeil_sumo.data.sources import DEFAULT_DATA_DIR, NGSIM_FILE
from safeil_sumo.planners import idm
from safeil_sumo.report import card as rc
from safeil_sumo.report import held_out_replays as rr
from safeil_sumo.report import sections as rs

# ------------------------------------------------------------------- the rules, by hand


def test_all_completed_by_hand() -> None:
    assert rc.all_completed(10, 10)
    assert not rc.all_completed(9, 10)
    assert not rc.all_completed(0, 0)  # nothing ran: nothing passed


def test_none_of_by_hand() -> None:
    assert rc.none_of(0, 0, 0)
    assert not rc.none_of(0, 1)
    assert rc.none_of()


def test_certificate_passes_by_hand() -> None:
    assert rc.certificate_passes(True, {"leader": 1.0, "lane": 1.0})
    assert not rc.certificate_passes(True, {"leader": 1.0, "lane": 0.9999})
    assert not rc.certificate_passes(False, {"leader": 1.0, "lane": 1.0})  # hashes mismatch
    assert not rc.certificate_passes(True, {})


def test_beats_by_hand() -> None:
    assert rc.beats(1.0, 2.0)
    assert not rc.beats(2.0, 2.0)
    assert not rc.beats(math.nan, 2.0)
    assert not rc.beats(1.0, math.inf)


def test_rate_text_by_hand() -> None:
    # Wilson, z = 1.96: 0/30 -> centre = half = (z^2 / 60) / (1 + z^2 / 30) = 0.05676, so the
    # upper bound is 0.1135; 7/10 -> centre 0.6445 +- 0.2477 = 0.3968 .. 0.8922
    assert rc.rate_text(0, 30) == "0/30 (0.0 %, 95 % CI 0.0-11.4 %)"
    assert rc.rate_text(7, 10) == "7/10 (70.0 %, 95 % CI 39.7-89.2 %)"
    assert rc.rate_text(0, 0) == "0/0"
    numbers = rc.rate_numbers("collisions", 0, 30)
    assert numbers["collisions"] == 0 and numbers["collisions_rate"] == 0.0
    assert numbers["collisions_ci_high"] == pytest.approx(0.11352, abs=1e-5)


def test_best_median_worst_by_hand() -> None:
    # finite values sorted: 1.0 (pos 1), 2.0 (pos 3), 3.0 (pos 0), 5.0 (pos 4); the median of
    # four is the lower middle, 2.0
    assert rc.best_median_worst([3.0, 1.0, math.nan, 2.0, 5.0]) == [
        ("best", 1), ("median", 3), ("worst", 4)]
    assert rc.best_median_worst([1.0, 2.0]) == [("best", 0), ("worst", 1)]
    assert rc.best_median_worst([2.0]) == [("best", 0)]
    assert rc.best_median_worst([math.nan]) == []


def test_format_value_by_hand() -> None:
    assert [rc.format_value(v) for v in (True, False, 3, 0.113518, 12345.6, math.nan, None,
                                         "ngsim:1003-996#0")] == [
        "yes", "no", "3", "0.1135", "1.235e+04", "-", "-", "ngsim:1003-996#0"]


def _section(key: str, *passed: bool | None, status: str = "done") -> rc.Section:
    checks = tuple(rc.Check(f"check {i}", "k", "c", p) for i, p in enumerate(passed))
    return rc.Section(key, key, "", {"x": 1}, checks, status=status)


def test_overall_verdict_by_hand() -> None:
    assert rc.overall([_section("a", True), _section("b", None)]) == rc.PASS
    assert rc.overall([_section("a", True, False), _section("b", True)]) == rc.FAIL
    assert rc.overall([_section("a", True), _section("b", status="error")]) == "INCOMPLETE"
    assert rc.overall([_section("a", False), _section("b", status="not run")]) == rc.FAIL
    assert rc.section_verdicts(_section("a", True, None)) == [rc.PASS, rc.NOT_APPLICABLE]


def test_events_by_hand() -> None:
    summary = pd.DataFrame({
        "status": ["ok", "ok", "ok", "ok", "failed"],
        "completed": [True, False, False, False, None],
        "flag": ["", "collision", "lane_departure", "ttc", None],
        "end_reason": ["completed", "collision", "completed", "completed", None],
        "collision_events": [0, 1, 0, 0, None],
        "lane_departure_events": [0, 0, 1, 2, None],  # a departure after a TTC flag counts
    })
    assert rs.events(summary) == {"n": 4, "completed": 1, "collisions": 1, "lane_departures": 2}


def test_quick_settings_and_overrides() -> None:
    quick = rs.settings(True, seed=3, sweep_scenarios=None, falsify_budget=10)
    assert (quick.sweep_scenarios, quick.replay_maneuvers, quick.gap_speeds_mps) == (30, 2, (25.0,))
    assert (quick.seed, quick.falsify_budget, quick.falsify_batch) == (3, 10, 10)
    full = rs.settings(False)
    assert (full.sweep_scenarios, full.replay_maneuvers, full.falsify_budget) == (1000, None, 1000)


def test_maneuvers_to_replay_by_hand() -> None:
    ids, held = {"c", "a", "b"}, {"b", "a", "z"}
    assert rr.maneuvers_to_replay(ids, held, given=False, cap=None) == (["a", "b"], True)
    assert rr.maneuvers_to_replay(ids, held, given=True, cap=1) == (["a"], True)
    # the user's recordings, none held out by the model: every maneuver, capped
    assert rr.maneuvers_to_replay(ids, {"z"}, given=True, cap=None) == (["a", "b", "c"], False)
    assert rr.maneuvers_to_replay(ids, {"z"}, given=True, cap=2) == (["a", "b"], False)
    assert rr.maneuvers_to_replay(ids, {"z"}, given=False, cap=None) == ([], False)


def test_data_names_are_short_and_unique() -> None:
    taken = {"openacc", "ngsim"}
    a = DataSpec("csv", (Path("/x/my drives.v2.csv"),))
    assert rr.data_name(a, taken) == "csv_my_drives"
    assert rr.data_name(a, taken) == "csv_my_drives_2"
    assert rr.data_name(DataSpec("highd", (Path("/d/highD/"),)), taken) == "highd_highD"


def test_the_baseline_idm_is_the_one_trained_beside_the_checkpoint(tmp_path: Path) -> None:
    model = tmp_path / "mine.safetensors"
    model.write_bytes(b"")
    assert rr.baseline_idm(str(model)) == "idm"  # none beside it: the shipped one
    assert rr.baseline_idm("safeil") == "idm"
    idm.save_model(idm.baseline_path(model), {"training": idm.IDMFit(
        idm.IDMParams(), 1.0, 0.1, ("m",), 3)}, default="training")
    assert (tmp_path / "mine.idm.json").is_file()
    assert rr.baseline_idm(str(model)) == str(tmp_path / "mine.idm.json")
    assert rr.planners(str(model)) == [str(model), str(tmp_path / "mine.idm.json"),
                                       "constant_speed"]
    assert rr.planners("idm") == ["idm", "constant_speed"]


@pytest.mark.parametrize(("argv", "message"), [
    (["--data", "csv:nowhere.csv"], "--data csv:"),
    (["--data", "tsv:x.csv"], "unknown data format 'tsv'"),
    (["--map", "time=t"], "--map and --speed-unit read csv data"),
])
def test_bad_data_options_are_one_line(argv, message, capsys) -> None:
    with pytest.raises(SystemExit) as exit_:
        ev.parse_args(["idm", *argv])
    err = capsys.readouterr().err.strip().splitlines()
    assert exit_.value.code == 2 and len(err) == 1 and message in err[0], err


def test_default_out_names_the_model() -> None:
    assert ev.default_out("idm", True) == Path("runs/evaluate_idm_quick")
    assert ev.default_out("some/dir/my model.safetensors", False) == Path(
        "runs/evaluate_my_model")


# ------------------------------------------------------------------- report.md vs report.json


def md_numbers(md: str, title: str) -> dict[str, str]:
    """The ``| `name` | value |`` rows of one section of report.md."""
    part = md.split(f". {title}\n", 1)[1].split("\n## ", 1)[0]
    return dict(re.findall(r"^\| `([^`]+)` \| (.*) \|$", part, flags=re.MULTILINE))


def check_report(out: Path) -> dict:
    """report.md and report.json agree: every section done, with its numbers (the same values
    as shown), its reproduce command(s), its checks in the verdict table and its figures."""
    md = (out / "report.md").read_text()
    report = json.loads((out / "report.json").read_text())
    assert [s["key"] for s in report["sections"]] == list(ev.KEYS)
    assert f"Overall: **{report['overall']}**" in md
    for s in report["sections"]:
        assert s["status"] == "done", (s["key"], s["error"])
        assert s["numbers"], s["key"]
        shown = md_numbers(md, s["title"])
        assert shown == {k: rc.format_value(v) for k, v in s["numbers"].items()}, s["key"]
        assert s["commands"] and all(f"\n{c}\n" in md for c in s["commands"]), s["key"]
        for c in s["checks"]:
            assert f"| {c['key']} | {c['criterion']} | **{c['verdict']}** |" in md
        for fig in s["figures"]:
            assert (out / fig).is_file() and f"]({fig})" in md
    return report


def test_markdown_and_json_agree_by_hand(tmp_path: Path) -> None:
    sections = [rc.Section(k, t, "measures", {"n": 3, "rate": 0.25, "ok": True, "none": None},
                           (rc.Check("c", "3/4", "all", False),), (f"safeil-{k} --x 1",),
                           ()) for k, t, _ in ev.SECTIONS]
    ev.write_report(tmp_path, {"model": "m", "seed": 0, "command": "x", "commit": "c"}, sections)
    report = check_report(tmp_path)
    assert report["overall"] == rc.FAIL
    assert md_numbers((tmp_path / "report.md").read_text(), ev.SECTIONS[0][1]) == {
        "n": "3", "rate": "0.25", "ok": "yes", "none": "-"}


# ------------------------------------------------------------------- the command line


def test_an_unknown_model_is_one_line(tmp_path, monkeypatch, capsys) -> None:
    monkeypatch.chdir(tmp_path)
    assert ev.main(["no_such_planner"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: unknown policy 'no_such_planner'") and err.count("\n") == 1
    assert not (tmp_path / "runs").exists()  # nothing written


def test_ctrl_c_keeps_the_finished_sections(tmp_path, monkeypatch, capsys) -> None:
    def done(ctx: rs.EvalContext) -> rc.Section:
        return rc.Section("safety", "first", "m", {"n": 1}, (rc.Check("c", "1", "c", True),),
                          ("safeil-run",))

    def interrupted(ctx: rs.EvalContext) -> rc.Section:
        raise KeyboardInterrupt

    monkeypatch.setattr(ev, "SECTIONS", (("safety", "first", done),
                                         ("suite", "second", interrupted),
                                         ("falsify", "third", done)))
    assert ev.main(["idm", "--out", str(tmp_path)]) == 130
    err = capsys.readouterr().err.splitlines()
    assert err[-1] == "interrupted" and "[1/3] safety: PASS" in err[1]
    report = json.loads((tmp_path / "report.json").read_text())
    assert [s["status"] for s in report["sections"]] == ["done", "not run", "not run"]
    assert "| 1 | first | c | 1 | c | **PASS** |" in (tmp_path / "report.md").read_text()


def test_a_failing_section_is_an_error_line_not_the_end(tmp_path, monkeypatch, capsys) -> None:
    def broken(ctx: rs.EvalContext) -> rc.Section:
        raise ValueError("no data\nsecond line")

    monkeypatch.setattr(ev, "SECTIONS", (("safety", "first", broken),))
    assert ev.main(["idm", "--out", str(tmp_path)]) == 1
    report = json.loads((tmp_path / "report.json").read_text())
    assert report["sections"][0]["error"] == "ValueError: no data"
    assert report["overall"] == "INCOMPLETE"


def test_a_data_file_the_importer_refuses_is_the_replay_sections_one_line_error(
        tmp_path: Path, capsys) -> None:
    """Your own recordings are never skipped quietly: a CSV without its gap column ends the
    replay section with the importer's line (file, column), before any SUMO run."""
    pd.DataFrame({"time": [0.0, 0.1], "v": [20.0, 20.1]}).to_csv(tmp_path / "log.csv",
                                                                 index=False)
    (tmp_path / "no_data").mkdir()
    code = ev.main(["idm", "--only", "replay", "--data", f"csv:{tmp_path / 'log.csv'}",
                    "--data-dir", str(tmp_path / "no_data"), "--out", str(tmp_path / "card")])
    assert code == 1
    (section,) = [s for s in json.loads((tmp_path / "card" / "report.json").read_text())
                  ["sections"] if s["key"] == "replay"]
    assert section["status"] == "error", section
    # the user's spec leads the line (not the "nothing to replay" of skipped sources)
    assert section["error"].startswith(f"ValueError: csv:{tmp_path / 'log.csv'}: "), section
    assert "'gap'" in section["error"] and "\n" not in section["error"]


@pytest.mark.sumo
@pytest.mark.skipif(not (DEFAULT_DATA_DIR / NGSIM_FILE).is_file(), reason="no NGSIM data")
def test_evaluate_idm_end_to_end_in_libsumo(tmp_path: Path) -> None:
    """A real run of every section on a test-sized budget: the quick budgets with a 3-scenario
    sweep, one held-out maneuver, 5 falsification simulations, and a data folder holding NGSIM
    only (OpenACC's 150 s maneuvers are skipped, with a note: the test stays near a minute)."""
    pytest.importorskip("libsumo")
    data = tmp_path / "data"
    (data / NGSIM_FILE).parent.mkdir(parents=True)
    (data / NGSIM_FILE).symlink_to(DEFAULT_DATA_DIR / NGSIM_FILE)
    out = tmp_path / "card"
    cmd = [sys.executable, "-m", "safeil_sumo.evaluate", "idm", "--quick", "--scenarios", "3",
           "--maneuvers", "1", "--budget-sims", "5", "--data-dir", str(data), "--out", str(out)]
    proc = subprocess.run(cmd, check=False, capture_output=True, text=True, timeout=600,
                          cwd=tmp_path, env={**os.environ, "PYTHONUNBUFFERED": "1"})
    assert proc.returncode in (0, 1), proc.stderr  # 1: a check failed (reported, not a crash)
    assert len([line for line in proc.stderr.splitlines() if re.match(r"\[\d/6\] ", line)]) == 12
    report = check_report(out)
    by_key = {s["key"]: s for s in report["sections"]}
    assert by_key["safety"]["numbers"]["paper_scenarios"] == 10
    assert by_key["safety"]["numbers"]["sweep_scenarios"] == 3
    assert by_key["certificate"]["checks"][0]["verdict"] == rc.NOT_APPLICABLE
    assert by_key["replay"]["numbers"]["ngsim_maneuvers"] == 1
    assert by_key["replay"]["numbers"]["openacc_maneuvers"] == 0
    assert "figures/replay_best_median_worst.png" in by_key["replay"]["figures"]
    assert by_key["falsify"]["numbers"]["simulations"] == 5
    assert all(s["figures"] for k, s in by_key.items() if k != "certificate")
    assert proc.stdout.splitlines()[-1] == f"report: {out / 'report.md'}"


def test_the_data_folder_comes_from_the_environment_when_set(tmp_path: Path) -> None:
    """An installed package has no checkout beside ../shared: SAFEIL_SUMO_DATA names the data."""
    code = "from safeil_sumo.data.sources import DEFAULT_DATA_DIR as d; print(d)"
    env = {**os.environ, "SAFEIL_SUMO_DATA": str(tmp_path)}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                         check=True).stdout.strip()
    assert out == str(tmp_path)
    env.pop("SAFEIL_SUMO_DATA")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                         check=True).stdout.strip()
    assert out.endswith("shared/data")
