"""Leader speed profiles: constant, piecewise, recorded files and their errors."""

import numpy as np
import pandas as pd
import pytest

from safeil_sumo.sim.leaders import ProfileError, constant, from_file, piecewise


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
