"""Leader speed profiles: constant, piecewise, recorded files and their errors."""

import numpy as np
import pandas as pd
import pytest

from safeil_sumo.sim.leaders import (
    ProfileError,
    constant,
    from_file,
    implausible_change,
    piecewise,
)


def test_constant_and_piecewise():
    assert constant(27.0).speed_at(12.3) == 27.0
    p = piecewise([0.0, 10.0, 12.0], [30.0, 30.0, 20.0])
    assert p.speed_at(11.0) == pytest.approx(25.0)
    assert p.speed_at(100.0) == 20.0


def test_bad_profiles():
    with pytest.raises(ProfileError, match="negative speed"):
        piecewise([0, 1], [10, -1])
    with pytest.raises(ProfileError, match="increase strictly"):
        piecewise([0, 1, 1], [10, 10, 10])
    with pytest.raises(ProfileError, match="finite"):
        piecewise([0, 1], [10, np.nan])


def test_recorded_profile_csv_and_parquet(tmp_path):
    df = pd.DataFrame({"time": [5.0, 5.25, 5.5], "speed": [20.0, 21.0, 22.0]})
    df.to_csv(tmp_path / "p.csv", index=False)
    df.to_parquet(tmp_path / "p.parquet")
    for name in ("p.csv", "p.parquet"):
        p = from_file(tmp_path / name)
        assert p.speed_at(0.125) == pytest.approx(20.5)  # time re-based to the first row
    with pytest.raises(ProfileError, match="missing column"):
        from_file(tmp_path / "p.csv", speed_column="v")
    gap = pd.DataFrame({"time": [0.0, 0.1, 3.0], "speed": [1.0, 1.0, 1.0]})
    gap.to_csv(tmp_path / "gap.csv", index=False)
    with pytest.raises(ProfileError, match="gap of"):
        from_file(tmp_path / "gap.csv")
    with pytest.raises(ProfileError, match="not found"):
        from_file(tmp_path / "nope.csv")
    (tmp_path / "bad.parquet").write_bytes(b"PAR1 not really")
    with pytest.raises(ProfileError, match="cannot read"):
        from_file(tmp_path / "bad.parquet")


def test_implausible_change_hand_computed():
    t = np.round(np.arange(10.0, 20.0, 0.1), 1)
    # a dropout: 25.8 m/s to 0 for one sample at 12.3 s; the mean over the 0.5 s window that
    # ends at the dropout is -25.8 / 0.5 = -51.6 m/s^2
    why = implausible_change(t, np.where(np.isclose(t, 12.3), 0.0, 25.8))
    assert why.startswith("speed falls 25.8 m/s in 0.1 s at t = 12.3 s (-258 m/s²; "
                          "-51.6 m/s² over 0.5 s, beyond the plausible -15 m/s²)"), why
    # one step of 4.9 m/s (NGSIM's reconstruction has such): -9.8 m/s^2 over 0.5 s, accepted
    assert implausible_change(t, np.where(t < 15.0, 12.5, 7.6)) is None
    # ramps: braking at 14.9 m/s^2 is accepted, at 15.1 refused; +12 m/s^2 refused, +9.9 not
    ramp = np.clip(t - 11.0, 0.0, 1.0)
    assert implausible_change(t, 30.0 - 14.9 * ramp) is None
    assert "falls" in implausible_change(t, 30.0 - 15.1 * ramp)
    assert implausible_change(t, 10.0 + 9.9 * ramp) is None
    why = implausible_change(t, 10.0 + 12.0 * ramp)
    assert why.startswith("speed rises 1.2 m/s in 0.1 s at t = 11.1 s (+12 m/s²; +12.0 m/s² "
                          "over 0.5 s, beyond the plausible +10 m/s²)"), why
    # shorter than the window: the whole profile is the window; one sample: nothing to judge
    assert "over 0.2 s" in implausible_change(np.array([0.0, 0.2]), np.array([20.0, 15.0]))
    assert implausible_change(np.array([0.0]), np.array([20.0])) is None


def test_from_file_refuses_a_dropout_with_file_and_time(tmp_path):
    t = np.round(np.arange(0.0, 30.0, 0.1), 1)
    pd.DataFrame({"time": t, "speed": np.where(np.isclose(t, 12.3), 0.0, 25.8)}).to_csv(
        tmp_path / "profile.csv", index=False)
    with pytest.raises(ProfileError, match=r"profile\.csv: speed falls 25\.8 m/s in 0\.1 s at "
                                           r"t = 12\.3 s .*a sensor dropout\? fix or trim"):
        from_file(tmp_path / "profile.csv")
