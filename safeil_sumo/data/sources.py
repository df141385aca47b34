"""The real recordings by name: ``openacc``, ``zalazone``, ``ngsim`` or a drive file -> a drive frame.

Every command that reads the shared data (replay, the IDM calibration, recorded leaders, the gap
probe's human statistics, results) finds it here: the data folder, the files of each source, and
who drove each maneuver.
"""

from __future__ import annotations

import functools
import os
import re
from pathlib import Path

import pandas as pd

from safeil_sumo.data.schema import SchemaError, load_drive

DATA_DIR_VARIABLE = "SAFEIL_SUMO_DATA"  # where the real data is, for an installed package
# else: the project sits beside ../shared (checkout/safeil_sumo/data/sources.py -> ../shared/data)
DEFAULT_DATA_DIR = Path(os.environ.get(DATA_DIR_VARIABLE)
                        or Path(__file__).resolve().parents[3] / "shared" / "data")
NGSIM_FILE = Path("ngsim_i80") / "i80_pairs.parquet"
OPENACC_GLOB = "openacc_vicolungo/JRC-VC_280219_*.csv.gz"  # the all-human day
ZALAZONE_GLOB = "openacc_zalazone/handling_part*.csv.gz"  # the handling course, all human
# [1/m] lane-curvature clip of the handling course (median radius ~150 m, 1 % of rows below
# 50 m): the importer's motorway default (1/250 m) would bend its lanes far too little
ZALAZONE_MAX_CURVATURE = 1.0 / 40.0
# an OpenACC recording id "<file>_f<k>" or, one of several runs of follower k, "<file>_f<k>_s<i>"
_OPENACC_RECORDING = re.compile(r"^(?P<file>.+)_f(?P<k>\d+)(?:_s\d+)?$")


def load_source(source: str, data_dir: Path = DEFAULT_DATA_DIR, columns: str = "",
                speed_unit: str = "m/s") -> pd.DataFrame:
    """A validated drive frame of ``openacc`` (Vicolungo, the all-human day), ``zalazone`` (the
    ZalaZone handling course, lane curvature clipped at :data:`ZALAZONE_MAX_CURVATURE`),
    ``ngsim``, recordings by ``FORMAT:PATH`` (:mod:`safeil_sumo.data.by_path`; ``columns`` and
    ``speed_unit`` read a ``csv:``) or a drive file path."""
    from safeil_sumo.data.importers import import_ngsim_pairs, import_openacc

    if source == "ngsim":
        return import_ngsim_pairs(data_dir / NGSIM_FILE)
    if source in ("openacc", "zalazone"):
        pattern = OPENACC_GLOB if source == "openacc" else ZALAZONE_GLOB
        files = sorted(data_dir.glob(pattern))
        if not files:
            raise SchemaError(f"no {source} files {pattern} in {data_dir}")
        frames = [import_openacc(f) if source == "openacc"
                  else import_openacc(f, max_curvature=ZALAZONE_MAX_CURVATURE) for f in files]
        return pd.concat([f for f in frames if len(f)], ignore_index=True)
    from safeil_sumo.data.by_path import FORMATS, load_data, parse_data_option

    fmt, sep, _ = source.partition(":")
    if sep and fmt in FORMATS and not Path(source).exists():
        return load_data([parse_data_option(source, columns, speed_unit)])[0]
    return load_drive(source)


@functools.lru_cache(maxsize=32)
def _zalazone_cars(path: Path) -> dict[int, str]:
    """Platoon position -> car name of one ZalaZone file (its metadata row, read once)."""
    from safeil_sumo.data.importers import openacc_vehicle_names, read_openacc_metadata

    return openacc_vehicle_names(read_openacc_metadata(path))


def driver_of(source: str, maneuver_id: str, data_dir: Path = DEFAULT_DATA_DIR) -> str:
    """The driver a maneuver of ``source`` belongs to, where the data identify drivers: OpenACC
    ``openacc/f<k>``, the platoon position of one campaign day (the same car and driver in every
    part); ZalaZone ``zalazone/<car>``, the follower's car named by its file's metadata row
    ``Vehicle_order`` (read from ``data_dir``): the platoon order differs between the files, so
    the position ``k`` alone would mix cars; the car is the finest identity the files give (no
    driver names), and a recording whose file or position has no name keeps
    ``zalazone/<file>_f<k>``; NGSIM ``ngsim/<id>``, the follower's vehicle id; else
    ``<source>/<recording>``."""
    recording = maneuver_id.split("#")[0]
    if source == "openacc":
        return f"openacc/{recording.rsplit('_', 1)[-1]}"
    if source == "zalazone":
        m = _OPENACC_RECORDING.match(recording)
        if m is None:
            return f"zalazone/{recording}"
        path = data_dir / ZALAZONE_GLOB.split("/")[0] / f"{m['file']}.csv.gz"
        try:
            car = _zalazone_cars(path).get(int(m["k"]))
        except SchemaError:  # the file is not there: identify by file and position
            car = None
        return f"zalazone/{car or m['file'] + '_f' + m['k']}"
    if source == "ngsim":
        return f"ngsim/{recording.split('-')[0]}"
    return f"{source}/{recording}"
