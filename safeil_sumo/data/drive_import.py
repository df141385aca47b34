"""One entry to import recordings by a ``"format:path"`` spec (``docs/your_own_drives.md``).

``import_drives("highd:DIR")``, ``import_drives(["csv:a.csv", "openacc:DIR"], csv_map=...)``:
the validated drive frame of every spec, concatenated. What a command line's ``--data`` calls.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from pathlib import Path

import pandas as pd

from safeil_sumo.data.car_following_csv import import_car_following_csv
from safeil_sumo.data.highd import import_highd
from safeil_sumo.data.importers import (
    ImportArgumentError,
    _fields,
    _head_lines,
    import_ngsim_csv,
    import_ngsim_pairs,
    import_openacc_files,
)
from safeil_sumo.data.schema import SchemaError, validate_drive

FORMATS = {
    "highd": "a highD directory, recording prefix (DIR/01) or NN_tracks.csv",
    "csv": "a car-following CSV, columns mapped by csv_map, speeds in speed_unit",
    "openacc": "an OpenACC file (.csv, .csv.gz) or a directory of them (human followers)",
    "ngsim": "an NGSIM trajectory CSV (feet) or the I-80 pairs Parquet (metric)",
}


def split_spec(spec: str) -> tuple[str, Path]:
    """``"highd:data/highD"`` -> ``("highd", Path("data/highD"))``; an unknown format or an empty
    path raises :class:`ImportArgumentError` listing the known formats."""
    fmt, sep, path = spec.partition(":")
    fmt = fmt.strip().lower()
    if not sep or fmt not in FORMATS or not path.strip():
        why = (f"unknown format {fmt!r}" if sep and fmt not in FORMATS
               else "no path" if sep and fmt in FORMATS else "not format:path")
        raise ImportArgumentError(f"data spec {spec!r}: {why} (known formats: "
                                  f"{', '.join(f'{k}:PATH' for k in FORMATS)})")
    return fmt, Path(path.strip())


def is_openacc_file(path: Path) -> bool:
    """Whether a csv[.gz] starts as an OpenACC file does: its first field is the metadata row's
    ``Date`` (a byte-order mark and quotes allowed); an unreadable file is not one."""
    try:
        head = _head_lines(path, 1)
    except SchemaError:
        return False
    return bool(head) and _fields(head[0].lstrip("\ufeff"))[0] == "Date"


def openacc_folder_files(path: Path) -> tuple[list[Path], list[Path]]:
    """The OpenACC files of a directory, sorted by name, and its other ``.csv``/``.csv.gz``
    files (a campaign folder also holds e.g. the vehicles' specifications)."""
    csvs = sorted(f for f in path.iterdir() if f.name.lower().endswith((".csv", ".csv.gz")))
    files = [f for f in csvs if is_openacc_file(f)]
    if not files:
        raise SchemaError(f"{path}: no OpenACC file (.csv, .csv.gz starting with the 'Date' "
                          f"metadata row) in the directory ({len(csvs)} other CSV files)")
    return files, [f for f in csvs if f not in files]


def _openacc(path: Path) -> pd.DataFrame:
    """One OpenACC file, or every one in a directory (:func:`openacc_folder_files`; the others
    are listed in ``import_stats["files_skipped"]``)."""
    if not path.is_dir():
        return import_openacc_files([path])
    files, others = openacc_folder_files(path)
    out = import_openacc_files(files)
    out.attrs["import_stats"]["files_skipped"] = [f.name for f in others]
    return out


def _ngsim(path: Path) -> pd.DataFrame:
    return import_ngsim_pairs(path) if path.suffix.lower() == ".parquet" else import_ngsim_csv(path)


def import_drive(spec: str, csv_map: Mapping[str, str] | str | None = None,
                 speed_unit: str = "m/s") -> pd.DataFrame:
    """The validated drive frame of ONE ``"format:path"`` spec (formats: :data:`FORMATS`), with
    its importer's ``import_stats``. ``csv_map`` and ``speed_unit`` are for ``csv:`` only (see
    :func:`~safeil_sumo.data.car_following_csv.import_car_following_csv`). No recording
    imported (e.g. an OpenACC day on ACC) is an error: there is nothing to train on."""
    fmt, path = split_spec(spec)
    readers: dict[str, Callable[[Path], pd.DataFrame]] = {
        "highd": import_highd,
        "csv": lambda p: import_car_following_csv(p, csv_map, speed_unit),
        "openacc": _openacc,
        "ngsim": _ngsim,
    }
    out = readers[fmt](path)
    if len(out) == 0:
        raise SchemaError(f"{spec}: no recording imported (import_stats: "
                          f"{out.attrs.get('import_stats')})")
    return out


def import_drives(specs: str | Sequence[str], csv_map: Mapping[str, str] | str | None = None,
                  speed_unit: str = "m/s") -> pd.DataFrame:
    """The drives of one spec or several (``"highd:DIR"``, ``"csv:FILE"``, ``"openacc:DIR"``,
    ``"ngsim:FILE"``) as one validated frame (N rows, the schema's columns).

    ``import_stats`` = ``{"specs": [{"spec", "stats"}, ...], "recordings", "rows"}``. Raises
    SchemaError (one line) on a bad spec, a bad file, or a recording id in two specs.
    """
    specs = [specs] if isinstance(specs, str) else list(specs)
    if not specs:
        raise ImportArgumentError(f"no data spec given (known formats: "
                                  f"{', '.join(f'{k}:PATH' for k in FORMATS)})")
    parts = [import_drive(s, csv_map, speed_unit) for s in specs]
    seen: dict[str, str] = {}
    for spec, part in zip(specs, parts, strict=True):
        for rid in part["recording_id"].unique():
            if rid in seen:
                raise SchemaError(f"{spec}: recording id {rid!r} also comes from {seen[rid]} "
                                  "(the same file given twice?)")
            seen[rid] = spec
    out = validate_drive(pd.concat(parts, ignore_index=True), " ".join(specs))
    out.attrs["import_stats"] = {
        "specs": [{"spec": s, "stats": p.attrs.get("import_stats", {})}
                  for s, p in zip(specs, parts, strict=True)],
        "recordings": len(seen), "rows": len(out),
    }
    return out
