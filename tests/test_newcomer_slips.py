"""Slips a newcomer meets (issue 39): ``api.sweep(policies=...)`` failing, env ids in the docs
without their namespace, ``check_env`` starting sumo-gui on a headless machine, and a
recorded-leader run that uses up its recording reported as a timeout, "0/1 completed"."""

from __future__ import annotations

import re
from pathlib import Path

import gymnasium as gym
import numpy as np
import pandas as pd
import pytest

import safeil_sumo.envs  # noqa: F401 - registers the ids

REPO = Path(__file__).resolve().parents[1]
ENV_ID = re.compile(r"(?<![\w.-])(?:[\w]+/)?[A-Z]\w*-v\d+\b")


@pytest.mark.parametrize("doc", ["README.md", "docs/gymnasium.md"])
def test_every_env_id_in_the_docs_is_registered(doc: str) -> None:
    """Each id the doc names works in ``gym.make`` as written (with its namespace)."""
    named = set(ENV_ID.findall((REPO / doc).read_text()))
    assert len(named) >= 5, f"{doc} names no env ids"
    missing = sorted(named - set(gym.registry))
    assert not missing, f"{doc} names ids gym.make does not know: {missing}"


@pytest.mark.sumo
def test_check_env_on_a_headless_machine(monkeypatch) -> None:
    """Without a display, Gymnasium's full check (render modes included) passes without
    starting sumo-gui, and render_mode="human" says why it cannot be."""
    pytest.importorskip("libsumo")
    from gymnasium.utils.env_checker import check_env

    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    env = gym.make("safeil_sumo/Curved500-v0", max_time_s=1.0)
    try:
        assert env.unwrapped.metadata["render_modes"] == ["rgb_array"]
        check_env(env.unwrapped)
    finally:
        env.close()
    with pytest.raises(ValueError, match="needs a display"):
        gym.make("safeil_sumo/Curved500-v0", render_mode="human")


@pytest.mark.sumo
def test_a_run_that_uses_up_its_recording_is_completed(tmp_path, capsys) -> None:
    """A real libsumo run behind a 25 s recorded leader, no time limit asked: it ends where the
    recording ends (``recording_end``), without a flag: completed."""
    pytest.importorskip("libsumo")
    from safeil_sumo import run
    from safeil_sumo.scenarios import recorded_leaders as rl

    profile = tmp_path / "leader.csv"
    t = np.arange(0.0, 25.0, 0.1)
    pd.DataFrame({"time": t, "speed": np.full(t.size, 20.0)}).to_csv(profile, index=False)
    rl.library.cache_clear()
    out = tmp_path / "r"
    assert run.main(["--net", "straight", "--policy", "analytic", "--leader", "recorded",
                     "--leader-profile", str(profile), "--scenarios", "1", "--no-plots",
                     "--out", str(out)]) == 0
    summary = pd.read_csv(out / "summary.csv")
    assert summary["end_reason"].tolist() == ["recording_end"]
    assert summary["completed"].tolist() == [True] and summary["flag"].isna().all()
    assert summary["path_completed"].iloc[0] < 1.0  # the road went on
    assert "1/1 scenarios completed" in capsys.readouterr().out


@pytest.mark.sumo
def test_a_shorter_time_limit_is_still_a_timeout(tmp_path) -> None:
    """Asked for less than the recording: the time limit ends it, as before."""
    pytest.importorskip("libsumo")
    from safeil_sumo import api
    from safeil_sumo.scenarios import recorded_leaders as rl

    profile = tmp_path / "leader.csv"
    t = np.arange(0.0, 25.0, 0.1)
    pd.DataFrame({"time": t, "speed": np.full(t.size, 20.0)}).to_csv(profile, index=False)
    rl.library.cache_clear()
    result = api.run("straight", policy="analytic", scenarios=1, leader_kind="recorded",
                     leader_profile=str(profile), max_time_s=2.0)
    assert result.summary["end_reason"].tolist() == ["timeout"]
    assert result.summary["completed"].tolist() == [False]


@pytest.mark.sumo
def test_api_sweep_takes_policy_like_the_cli(tmp_path) -> None:
    pytest.importorskip("libsumo")
    from safeil_sumo import api

    one = api.sweep(policy="analytic", out=tmp_path / "one", scenarios=1, nets=("straight",),
                    max_time_s=1.0)
    assert list(one["policy"]) == ["analytic"] and (one["status"] == "ok").all()
    both = api.sweep(policy=["analytic", "idm"], out=tmp_path / "both", scenarios=1,
                     nets=("straight",), max_time_s=1.0)
    assert sorted(both["policy"]) == ["analytic", "idm"] and (both["status"] == "ok").all()
    with pytest.raises(TypeError, match="policy must be"):
        api.sweep(policy=[], out=tmp_path / "none")
