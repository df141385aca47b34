"""Hypothesis fuzzing of the loaders and the processing pipeline (issue 7).

Each either returns a valid result or raises its documented ValueError subclass with a message:
never another exception, never a hang (small inputs, per-example deadlines).
"""

from __future__ import annotations

import shutil
import tempfile
from contextlib import suppress
from pathlib import Path

import numpy as np
import pandas as pd
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from safeil_sumo.data.pipeline import PipelineConfig, run_pipeline
from safeil_sumo.data.schema import SchemaError, load_drive, validate_drive
from safeil_sumo.data.tuples import Tuples
from safeil_sumo.learn.checkpoint import CheckpointError, load_checkpoint
from safeil_sumo.planners.registry import MODELS_DIR
from safeil_sumo.sim.leaders import ProfileError, SpeedProfile, from_file

FAST = settings(max_examples=60, deadline=2000, derandomize=True,
                suppress_health_check=[HealthCheck.too_slow])


def _scratch() -> Path:
    return Path(tempfile.mkdtemp(prefix="fuzz-"))


# -- drive files: random bytes -------------------------------------------------------------------

@FAST
@given(data=st.binary(max_size=2048), suffix=st.sampled_from([".csv", ".parquet", ".csv.gz"]),
       magic=st.sampled_from([b"", b"PAR1", b"recording_id,time\n", b"\x1f\x8b"]))
def test_fuzz_load_drive_random_bytes(data, suffix, magic):
    folder = _scratch()
    try:
        path = folder / f"d{suffix}"
        path.write_bytes(magic + data + (magic if suffix == ".parquet" else b""))
        try:
            df = load_drive(path)
        except SchemaError as exc:
            assert str(exc).startswith(str(path)) and "\n" not in str(exc)
            return
        assert len(df) > 0
    finally:
        shutil.rmtree(folder)


# -- leader profiles -----------------------------------------------------------------------------

_num = st.floats(allow_nan=True, allow_infinity=True, width=32) | st.integers(-100, 100)


@FAST
@given(times=st.lists(_num, max_size=8), speeds=st.lists(_num, max_size=8),
       fmt=st.sampled_from(["csv", "parquet"]))
def test_fuzz_leader_profile_file(times, speeds, fmt):
    n = min(len(times), len(speeds))
    df = pd.DataFrame({"time": times[:n], "speed": speeds[:n]}, dtype=float)
    folder = _scratch()
    try:
        path = folder / f"lead.{fmt}"
        df.to_csv(path, index=False) if fmt == "csv" else df.to_parquet(path)
        try:
            prof = from_file(path)
        except ProfileError as exc:
            assert str(exc)
            return
        # accepted: a drivable profile
        assert np.all(np.diff(prof.times) > 0) and np.all(prof.speeds >= 0)
        assert np.all(np.isfinite(prof.times)) and np.all(np.isfinite(prof.speeds))
        assert prof.times[0] == 0.0 and np.all(np.diff(prof.times) <= 1.0)
    finally:
        shutil.rmtree(folder)


@FAST
@given(data=st.binary(max_size=512))
def test_fuzz_leader_profile_random_bytes(data):
    folder = _scratch()
    try:
        path = folder / "lead.csv"
        path.write_bytes(b"time,speed\n" + data)
        with suppress(ProfileError):
            from_file(path)
    finally:
        shutil.rmtree(folder)


@FAST
@given(times=st.lists(_num, min_size=0, max_size=6), speeds=st.lists(_num, max_size=6))
def test_fuzz_speed_profile_arrays(times, speeds):
    try:
        prof = SpeedProfile(np.array(times, float), np.array(speeds, float))
    except ProfileError:
        return
    v = prof.speed_at(np.linspace(-1, 10, 7))
    assert np.all(np.isfinite(v)) and np.all(v >= 0)


# -- the processing pipeline on random small schema-valid drives ----------------------------------

@st.composite
def _drives(draw) -> pd.DataFrame:
    n = draw(st.integers(1, 80))
    recordings = draw(st.integers(1, 3))
    dt = draw(st.floats(0.05, 1.0))
    v0 = draw(st.floats(0.0, 40.0))
    rng = np.random.default_rng(draw(st.integers(0, 2**16)))
    t = np.cumsum(rng.uniform(0.5, 1.5, n) * dt)
    v = np.clip(v0 + np.cumsum(rng.normal(0, draw(st.floats(0, 2)), n)), 0, 60)
    yaw = rng.normal(0, draw(st.floats(0, 0.2)), n)
    lead_x = rng.uniform(-5, 150, n)
    lead_x[rng.random(n) < draw(st.floats(0, 1))] = np.nan  # no leader there
    c0l = 1.75 + rng.normal(0, draw(st.floats(0, 2)), n)  # > 1.75 jumps look like lane changes
    rec = np.sort(rng.integers(0, recordings, n)).astype(str)
    df = pd.DataFrame({
        "recording_id": rec, "time": t, "x": np.cumsum(v * dt), "y": rng.normal(0, 0.1, n),
        "yaw": yaw, "v_x": v,
        "left_c0": c0l, "left_c1": rng.normal(0, 0.01, n), "left_c2": rng.normal(0, 1e-3, n),
        "left_c3": 0.0, "right_c0": c0l - 3.5, "right_c1": 0.0, "right_c2": 0.0, "right_c3": 0.0,
        "lead_x": lead_x, "lead_y": np.where(np.isnan(lead_x), np.nan, rng.normal(0, 0.3, n)),
    })
    if draw(st.booleans()):
        df["lead_v"] = np.where(rng.random(n) < 0.2, np.nan, v + rng.normal(0, 2, n))
    if draw(st.booleans()):
        df["lane_index"] = rng.integers(0, 2, n).astype(float)
    return df


@settings(max_examples=40, deadline=5000, derandomize=True,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much])
@given(drive=_drives(), samples=st.sampled_from([2, 5, 20]),
       rate=st.sampled_from([2.0, 4.0, 10.0]))
def test_fuzz_pipeline_returns_tuples_or_value_error(drive, samples, rate):
    try:
        drive = validate_drive(drive, "fuzz")
    except SchemaError:
        assume(False)
    try:
        tuples, report = run_pipeline(drive, PipelineConfig(rate_hz=rate, horizon_samples=samples))
    except ValueError as exc:
        assert str(exc)
        return
    assert isinstance(tuples, Tuples) and report.tuples == len(tuples)
    if len(tuples):
        assert np.all(np.isfinite(tuples.features)) and np.all(np.isfinite(tuples.future))
        assert tuples.future.shape[1] == samples


# -- checkpoints: random bytes -------------------------------------------------------------------

@FAST
@given(data=st.binary(max_size=4096), prefix=st.sampled_from(
    [b"", b"\x80\x04", b"PK\x03\x04", b"\x93NUMPY", b"{", b"\x10\x00\x00\x00\x00\x00\x00\x00{"]))
def test_fuzz_checkpoint_random_weights(data, prefix):
    folder = _scratch()
    try:
        shutil.copy(MODELS_DIR / "bc.json", folder / "m.json")
        (folder / "m.safetensors").write_bytes(prefix + data)
        try:
            load_checkpoint(folder / "m")
        except CheckpointError as exc:
            assert str(exc)
            return
        raise AssertionError("random bytes loaded as a checkpoint")
    finally:
        shutil.rmtree(folder)


@FAST
@given(data=st.binary(max_size=1024) | st.text(max_size=200).map(str.encode))
def test_fuzz_checkpoint_random_sidecar(data):
    folder = _scratch()
    try:
        shutil.copy(MODELS_DIR / "bc.safetensors", folder / "m.safetensors")
        (folder / "m.json").write_bytes(data)
        try:
            load_checkpoint(folder / "m")
        except CheckpointError:
            return
        raise AssertionError("a random sidecar was accepted")
    finally:
        shutil.rmtree(folder)
