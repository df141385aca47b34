"""The real recordings by name: ``openacc``, ``ngsim`` or a drive file -> one validated drive frame.

Every command that reads the shared data (replay, the IDM calibration, recorded leaders, the gap
probe's human statistics, results) finds it here: the data folder, the files of each source, and
who drove each maneuver.
"""

from __future__ import annotations

from pathlib import Path

import pandas as pd

from safeil_sumo.data.schema import SchemaError, load_drive

# the project sits beside ../shared (checkout/safeil_sumo/data/sources.py -> ../shared/data)
DEFAULT_DATA_DIR = Path(__file__).resolve().parents[3] / "shared" / "data"
NGSIM_FILE = Path("ngsim_i80") / "i80_pairs.parquet"
OPENACC_GLOB = "openacc_vicolungo/JRC-VC_280219_*.csv.gz"  # the all-human day


def load_source(source: str, data_dir: Path = DEFAULT_DATA_DIR) -> pd.DataFrame:
    """A validated drive frame of ``openacc``, ``ngsim`` or a drive file path."""
    from safeil_sumo.data.importers import import_ngsim_pairs, import_openacc

    if source == "ngsim":
        return import_ngsim_pairs(data_dir / NGSIM_FILE)
    if source == "openacc":
        files = sorted(data_dir.glob(OPENACC_GLOB))
        if not files:
            raise SchemaError(f"no OpenACC files {OPENACC_GLOB} in {data_dir}")
        frames = [import_openacc(f) for f in files]
        return pd.concat([f for f in frames if len(f)], ignore_index=True)
    return load_drive(source)


def driver_of(source: str, maneuver_id: str) -> str:
    """The driver a maneuver of ``source`` belongs to, where the data identify drivers: OpenACC
    ``openacc/f<k>``, the platoon position of one campaign day (the same car and driver in every
    part); NGSIM ``ngsim/<id>``, the follower's vehicle id; else ``<source>/<recording>``."""
    recording = maneuver_id.split("#")[0]
    if source == "openacc":
        return f"openacc/{recording.rsplit('_', 1)[-1]}"
    if source == "ngsim":
        return f"ngsim/{recording.split('-')[0]}"
    return f"{source}/{recording}"
