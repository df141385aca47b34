"""Recordings by path and format -> drive frames -> the paper's processing -> tuples.

A data spec names a format and path(s) (``openacc:DIR|FILE``, ``ngsim:FILE``, ``drive:FILE``) or
the synthetic drivers recorded in SUMO (``synthetic:DRIVERS``). :func:`import_drive` is the ONE
place a format is mapped to an importer (:mod:`safeil_sumo.data.importers`); :func:`load_data`
runs it for every spec and :func:`process` runs the processing pipeline
(:mod:`safeil_sumo.data.pipeline`) on each drive, as ``training/build_real_datasets.py`` does.
No torch here: ``safeil-train`` checks the data before it imports its training modules.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Sequence
from dataclasses import asdict, dataclass, fields, replace
from pathlib import Path

import pandas as pd

from safeil_sumo.data.importers import MAX_PATH_CURVATURE
from safeil_sumo.data.pipeline import PipelineConfig, PipelineReport, run_pipeline
from safeil_sumo.data.schema import SchemaError
from safeil_sumo.data.tuples import Tuples

FORMATS = ("openacc", "ngsim", "highd", "csv", "drive", "synthetic")
FORMAT_HELP = ("openacc:DIR|FILE (JRC OpenACC csv[.gz]; a folder: every *.csv / *.csv.gz in it), "
               "ngsim:FILE (the I-80 pairs .parquet or an original NGSIM .csv), highd:DIR|PREFIX "
               "(levelXdata NN_tracks/NN_tracksMeta/NN_recordingMeta.csv), csv:FILE (car "
               "following: columns time, v, gap[, lead_v, id, driver] in s, m/s, m; "
               "docs/your_own_drives.md), drive:FILE (a "
               "drive in the project's schema, .csv/.parquet), synthetic:DRIVERS (that many "
               "synthetic drivers recorded in SUMO on n74)")


class DataError(ValueError):
    """A data spec that names an unknown format, a missing path or no recording (one line)."""


@dataclass(frozen=True)
class DataSpec:
    """One data source. ``format``: one of :data:`FORMATS`; ``paths``: its file(s) or folder
    (absolute once resolved); ``name``: the tuples' source label (default: the format; the
    training recipe's ``longitudinal_only_sources`` and each stage's ``sources`` refer to it);
    ``max_curvature_1pm``: openacc's lane-curvature clip [1/m] (a test track needs more than the
    motorway default); ``drivers``, ``seed``, ``lane_changes``: synthetic's drivers, their
    seed, whether they change lane; ``workers``: synthetic's SUMO processes; ``columns``,
    ``speed_unit``: csv's column map (``"time=t,v=speed,gap=gap"``, empty: the default names)
    and the unit of its speeds (``m/s`` or ``km/h``; docs/your_own_drives.md)."""

    format: str
    paths: tuple[Path, ...] = ()
    name: str = ""
    max_curvature_1pm: float = MAX_PATH_CURVATURE
    drivers: int = 16
    seed: int = 0
    lane_changes: bool = True
    workers: int = 2
    columns: str = ""
    speed_unit: str = "m/s"

    def __post_init__(self) -> None:
        if self.format not in FORMATS:
            raise DataError(f"unknown data format {self.format!r}: use one of "
                            f"{', '.join(FORMATS)}")
        object.__setattr__(self, "paths", tuple(Path(p) for p in self.paths))
        object.__setattr__(self, "name", self.name or self.format)
        if self.format == "synthetic":
            if self.drivers < 1 or self.workers < 1 or self.seed < 0:
                raise DataError(f"synthetic data needs drivers >= 1, workers >= 1 and seed >= "
                                f"0, got {self.drivers}, {self.workers}, {self.seed}")
        elif not self.paths:
            raise DataError(f"{self.format} data needs a path")
        if (self.columns or self.speed_unit != "m/s") and self.format != "csv":
            raise DataError(f"columns and speed_unit are for csv data, not {self.format}")
        if not self.max_curvature_1pm > 0:
            raise DataError(f"max_curvature_1pm must be > 0, got {self.max_curvature_1pm}")

    def resolved(self, base: Path) -> DataSpec:
        """The spec with its relative paths taken from ``base``."""
        return replace(self, paths=tuple(p if p.is_absolute() else base / p
                                         for p in self.paths))

    def to_json(self) -> dict:
        """The spec as JSON (paths as strings): what a checkpoint records of its data."""
        return {**asdict(self), "paths": [str(p) for p in self.paths]}

    @staticmethod
    def from_json(doc: dict) -> DataSpec:
        """:meth:`to_json` read back; :class:`DataError` for an unknown format or field."""
        known = {f.name for f in fields(DataSpec)}
        unknown = sorted(set(doc) - known)
        if unknown or "format" not in doc:
            raise DataError(f"not a data spec: unknown fields {unknown}" if unknown
                            else "not a data spec: no format")
        return DataSpec(**{**doc, "paths": tuple(Path(p) for p in doc.get("paths", ()))})

    def label(self) -> str:
        """``format:path[,path]`` (or ``synthetic:N``), for messages."""
        if self.format == "synthetic":
            return f"synthetic:{self.drivers}"
        return f"{self.format}:{','.join(map(str, self.paths))}"


def parse_data_option(text: str, columns: str = "", speed_unit: str = "m/s") -> DataSpec:
    """``FORMAT:PATH`` (``--data``) -> a spec (path relative to the working folder);
    :class:`DataError` in one line for a missing or unknown format. ``columns`` and
    ``speed_unit`` (``--map``, ``--speed-unit``) apply to a ``csv`` spec only."""
    fmt, sep, rest = text.partition(":")
    if not sep or not rest:
        raise DataError(f"--data {text!r}: expected FORMAT:PATH, FORMAT one of "
                        f"{', '.join(FORMATS)}")
    if fmt not in FORMATS:
        raise DataError(f"unknown data format {fmt!r} in {text!r}: use one of "
                        f"{', '.join(FORMATS)}")
    if fmt == "synthetic":
        try:
            return DataSpec("synthetic", drivers=int(rest))
        except ValueError:
            raise DataError(f"--data {text!r}: synthetic takes a number of drivers") from None
    if fmt == "csv":
        return DataSpec(fmt, (Path(rest).resolve(),), columns=columns, speed_unit=speed_unit)
    return DataSpec(fmt, (Path(rest).resolve(),))


def _openacc_files(paths: Sequence[Path]) -> list[Path]:
    """The OpenACC files of files and folders (a folder: its files that start with OpenACC's
    metadata rows, sorted by name)."""
    from safeil_sumo.data.drive_import import openacc_folder_files

    files: list[Path] = []
    for p in paths:
        if p.is_dir():
            try:
                files.extend(openacc_folder_files(p)[0])
            except SchemaError as exc:
                raise DataError(str(exc)) from None
        else:
            files.append(p)
    return files


def missing_paths(spec: DataSpec) -> list[Path]:
    """The paths of ``spec`` that do not exist."""
    return [p for p in spec.paths if not p.exists()]


def _check_paths(spec: DataSpec) -> None:
    missing = missing_paths(spec)
    if missing:
        raise DataError(f"{spec.format} data {missing[0]} does not exist")


def import_drive(spec: DataSpec, progress: bool = False) -> pd.DataFrame:
    """The validated drive frame of one spec: the ONE format -> importer dispatch."""
    from safeil_sumo.data import importers
    from safeil_sumo.data.schema import load_drive

    _check_paths(spec)
    if spec.format == "openacc":
        files: list[str | Path] = list(_openacc_files(spec.paths))
        return importers.import_openacc_files(files, max_curvature=spec.max_curvature_1pm)
    if spec.format in ("ngsim", "highd", "csv"):
        from safeil_sumo.data.drive_import import import_drive as import_by_spec

        frames = [import_by_spec(f"{spec.format}:{p}", spec.columns or None, spec.speed_unit)
                  for p in spec.paths]
    elif spec.format == "drive":
        frames = [load_drive(p) for p in spec.paths]
    elif spec.format == "synthetic":
        from safeil_sumo.data.synthetic_drives import record_drivers

        return record_drivers(spec.drivers, spec.seed, spec.lane_changes, spec.workers,
                              progress)[0]
    else:  # DataSpec refuses it already; kept for a dispatcher swapped in
        raise DataError(f"unknown data format {spec.format!r}: use one of {', '.join(FORMATS)}")
    return frames[0] if len(frames) == 1 else pd.concat(frames, ignore_index=True)


def load_data(specs: Sequence[DataSpec], progress: bool = False) -> list[pd.DataFrame]:
    """The drive frame of each spec, in order; :class:`DataError` naming the spec for a missing
    path, a file the importer rejects, or no recording at all."""
    drives = []
    for spec in specs:
        try:
            drive = import_drive(spec, progress)
        except (SchemaError, OSError) as exc:
            raise DataError(f"{spec.label()}: {exc}") from exc
        if len(drive) == 0:
            raise DataError(f"{spec.label()}: no human follower recording in this data")
        drives.append(drive)
    return drives


def process(drive: pd.DataFrame, spec: DataSpec, config: PipelineConfig
            ) -> tuple[Tuples, PipelineReport]:
    """The paper's processing of one drive frame -> tuples labelled ``spec.name``."""
    return run_pipeline(drive, config, source=spec.name)


def spec_digest(spec: DataSpec, config: PipelineConfig) -> str:
    """sha256 of what a spec's tuples depend on: the spec, the pipeline settings and the bytes
    of its files (a folder: of each OpenACC file in it, by name). Synthetic: the spec alone (the
    recorder is deterministic for its seeds)."""
    h = hashlib.sha256()
    fields = {k: v for k, v in asdict(spec).items() if k not in ("paths", "workers")}
    h.update(json.dumps({**fields, "pipeline": asdict(config)}, sort_keys=True,
                        default=str).encode())
    _check_paths(spec)
    files = _openacc_files(spec.paths) if spec.format == "openacc" else list(spec.paths)
    for f in files:
        h.update(f.name.encode())
        with f.open("rb") as fh:
            for chunk in iter(lambda: fh.read(1 << 20), b""):
                h.update(chunk)
    return h.hexdigest()
