"""Training recipes: a TOML file (``tomllib``) parsed into frozen dataclasses.

A recipe names its data by format and path (``[[data]]``), the held-out split (``[split]``: by
driver, a fraction and a seed, or explicit ids), the stages (``[openloop]``, ``[closed_loop]``,
``[lateral_refit]``: each the fields of its config class plus ``enabled`` and ``sources``) and
the certificate's budget (``[certify]``). The shipped recipe (``safeil_sumo/recipes/
shipped.toml``) states what ``training/train_shipped_models.py`` does for ``safeil``; a user's
recipe inherits every stage, pipeline and certify key it does not set from it. Every key is
checked: an unknown one, or a value of the wrong type, is one line naming the file and the key.
docs/training.md lists the keys.
"""

from __future__ import annotations

import dataclasses
import tomllib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from safeil_sumo.data.by_path import DataError, DataSpec
from safeil_sumo.data.pipeline import PipelineConfig
from safeil_sumo.data.sources import DEFAULT_DATA_DIR
from safeil_sumo.learn.closed_loop import FinetuneConfig
from safeil_sumo.learn.lateral_refit import LateralRefitConfig
from safeil_sumo.learn.trainer import TrainConfig

SHIPPED_RECIPE = Path(__file__).resolve().parents[1] / "recipes" / "shipped.toml"
STAGE_CONFIGS: dict[str, type] = {"openloop": TrainConfig, "closed_loop": FinetuneConfig,
                                  "lateral_refit": LateralRefitConfig}
STAGES = tuple(STAGE_CONFIGS)
STAGE_KEYS = ("enabled", "sources")  # besides the config's fields
TOP_KEYS = ("name", "seed", "data_dir", "init", "data", "pipeline", "split", *STAGES, "certify")
DATA_KEYS = ("format", "path", "name", "max_curvature_1pm", "drivers", "seed", "lane_changes",
             "workers", "columns", "speed_unit")
SPLIT_BY = ("driver", "maneuver")
INHERITED = ("pipeline", *STAGES, "certify")  # a user's recipe takes these from the shipped one


class RecipeError(ValueError):
    """A recipe that cannot be read or is wrong: one line naming the file and the key."""


@dataclass(frozen=True)
class Split:
    """The held-out maneuvers (early stopping, and left out of the closed-loop episodes).
    ``by``: ``driver`` (whole drivers, :func:`safeil_sumo.data.sources.driver_of`) or
    ``maneuver``; ``fraction`` [-] of each source's drivers (maneuvers) drawn with ``seed``,
    unless ``held_out`` names them (driver ids, e.g. ``ngsim/1003``, or maneuver ids)."""

    by: str = "driver"
    fraction: float = 0.2
    seed: int = 0
    held_out: tuple[str, ...] = ()


@dataclass(frozen=True)
class Stage:
    """One training stage: its ``name`` (:data:`STAGES`), whether it runs, the data names it
    trains on (``()``: all) and its config (the stage's config class)."""

    name: str
    enabled: bool
    sources: tuple[str, ...]
    config: Any


@dataclass(frozen=True)
class CertifySpec:
    """The certificate of the final checkpoint (:func:`safeil_sumo.learn.branch_and_bound.certify`):
    ``time_gap_range_s`` [s] the style settings covered (None: the checkpoint's default),
    ``max_boxes`` the box budget (None: none), ``budget_s`` the wall-time budget [s], ``batch``
    boxes bounded together, ``seed`` of the counterexample search."""

    enabled: bool = True
    time_gap_range_s: tuple[float, float] | None = None
    max_boxes: int | None = None
    budget_s: float = 600.0
    batch: int = 512
    seed: int = 0


@dataclass(frozen=True)
class Recipe:
    """A parsed recipe. ``path``: its file; ``init``: the checkpoint the closed-loop stage
    starts from when the openloop stage is off (a path or a shipped name)."""

    path: Path
    name: str
    seed: int
    data: tuple[DataSpec, ...]
    pipeline: PipelineConfig
    split: Split
    openloop: Stage
    closed_loop: Stage
    lateral_refit: Stage
    certify: CertifySpec
    init: str | None = None

    @property
    def stages(self) -> tuple[Stage, ...]:
        return (self.openloop, self.closed_loop, self.lateral_refit)

    def with_data(self, data: Sequence[DataSpec]) -> Recipe:
        """The recipe on other data (``--data``): each stage keeps the sources it names that the
        new data has, or all of them if it has none (a stage's ``sources`` named the recipe's
        data)."""
        names = {d.name for d in data}

        def kept(stage: Stage) -> Stage:
            return replace(stage, sources=tuple(s for s in stage.sources if s in names))

        return replace(self, data=tuple(data), openloop=kept(self.openloop),
                       closed_loop=kept(self.closed_loop), lateral_refit=kept(self.lateral_refit))


def _fail(path: Path, where: str, what: str) -> RecipeError:
    return RecipeError(f"{path}: {where}: {what}")


def _check_keys(path: Path, where: str, table: Mapping[str, Any], known: Sequence[str]) -> None:
    if not isinstance(table, Mapping):
        raise _fail(path, where, f"expected a table, got {type(table).__name__}")
    for key in table:
        if key not in known:
            raise _fail(path, f"{where}{key}", f"unknown key (known: {', '.join(known)})")


def _typed(value: Any, default: Any, path: Path, key: str) -> Any:
    """``value`` as the type of ``default`` (TOML ints for floats, lists for tuples)."""
    def bad(kind: str) -> RecipeError:
        return _fail(path, key, f"expected {kind}, got {value!r}")

    if isinstance(default, bool):
        if not isinstance(value, bool):
            raise bad("true or false")
        return value
    if isinstance(default, float):
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise bad("a number")
        return float(value)
    if isinstance(default, int):
        if isinstance(value, bool) or not isinstance(value, int):
            raise bad("an integer")
        return value
    if isinstance(default, str):
        if not isinstance(value, str):
            raise bad("a string")
        return value
    if isinstance(default, tuple):
        if not isinstance(value, list):
            raise bad("a list")
        return tuple(_typed(v, default[0], path, key) if default else v for v in value)
    return value


def _config(cls: type, table: Mapping[str, Any], path: Path, where: str, **extra: Any) -> Any:
    """``cls`` from a table of its fields (type-checked against the defaults), its own check
    failing as one line."""
    defaults = cls()
    names = [f.name for f in dataclasses.fields(cls)]
    _check_keys(path, where, table, names)
    kwargs = {k: _typed(v, getattr(defaults, k), path, f"{where}{k}") for k, v in table.items()}
    try:
        return cls(**{**extra, **kwargs})
    except (ValueError, TypeError) as exc:
        raise _fail(path, where.rstrip("."), str(exc)) from None


def _stage(name: str, table: Mapping[str, Any], seed: int, path: Path) -> Stage:
    where = f"[{name}] "
    _check_keys(path, where, table,
                (*STAGE_KEYS, *(f.name for f in dataclasses.fields(STAGE_CONFIGS[name]))))
    rest = {k: v for k, v in table.items() if k not in STAGE_KEYS}
    enabled = _typed(table.get("enabled", True), True, path, f"{where}enabled")
    sources = _typed(table.get("sources", []), ("",), path, f"{where}sources")
    config = _config(STAGE_CONFIGS[name], rest, path, where, seed=seed)
    return Stage(name, enabled, sources, config)


def _data(items: Any, base: Path, path: Path, seed: int) -> tuple[DataSpec, ...]:
    if not isinstance(items, list):
        raise _fail(path, "data", "expected [[data]] tables")
    specs = []
    for i, item in enumerate(items):
        where = f"[[data]] #{i + 1} "
        _check_keys(path, where, item, DATA_KEYS)
        if "format" not in item:
            raise _fail(path, f"{where}format",
                        "missing (one of openacc, ngsim, highd, csv, drive, synthetic)")
        if isinstance(item.get("columns"), dict):  # columns = {time = "t", v = "speed"}
            item = {**item, "columns": ",".join(f"{k}={v}" for k, v in item["columns"].items())}
        raw = item.get("path", [])
        paths = [raw] if isinstance(raw, str) else _typed(raw, ("",), path, f"{where}path")
        fields = {k: v for k, v in item.items() if k not in ("path", "format")}
        defaults = DataSpec("synthetic")
        kwargs = {k: _typed(v, getattr(defaults, k), path, f"{where}{k}")
                  for k, v in fields.items()}
        kwargs.setdefault("seed", seed)
        try:
            specs.append(DataSpec(_typed(item["format"], "", path, f"{where}format"),
                                  tuple(Path(p) for p in paths), **kwargs).resolved(base))
        except DataError as exc:
            raise _fail(path, where.strip(), str(exc)) from None
    return tuple(specs)


def _split(table: Mapping[str, Any], seed: int, path: Path) -> Split:
    split = _config(Split, table, path, "[split] ", seed=seed)
    if split.by not in SPLIT_BY or not 0.0 <= split.fraction < 1.0:
        raise _fail(path, "[split]", f"by must be one of {', '.join(SPLIT_BY)} and fraction in "
                                     f"[0, 1), got {split.by!r}, {split.fraction}")
    return split


def _certify(table: Mapping[str, Any], seed: int, path: Path) -> CertifySpec:
    fixed = dict(table)
    tg = fixed.pop("time_gap_range_s", None)
    boxes = fixed.pop("max_boxes", None)
    spec = _config(CertifySpec, fixed, path, "[certify] ", seed=seed)
    if tg is not None:
        tg = _typed(tg, (0.0,), path, "[certify] time_gap_range_s")
        if len(tg) != 2 or not 0 < tg[0] <= tg[1]:
            raise _fail(path, "[certify] time_gap_range_s", f"expected [LO, HI] [s], got {tg}")
    if boxes is not None:  # 0: no box budget
        boxes = _typed(boxes, 0, path, "[certify] max_boxes") or None
    if spec.budget_s <= 0 or spec.batch < 1:
        raise _fail(path, "[certify]", "budget_s must be > 0 and batch >= 1")
    return replace(spec, time_gap_range_s=tg, max_boxes=boxes)


def _merged(doc: Mapping[str, Any], base: Mapping[str, Any]) -> dict[str, Any]:
    """``doc`` over the shipped recipe's stage, pipeline and certify tables (a stage's
    ``sources`` are data names: not inherited)."""
    out = dict(doc)
    for key in INHERITED:
        inherited = {k: v for k, v in base.get(key, {}).items() if k != "sources"}
        mine = doc.get(key, {})
        if isinstance(mine, Mapping):
            out[key] = {**inherited, **mine}
    return out


def _read(path: Path) -> dict[str, Any]:
    try:
        with path.open("rb") as fh:
            return tomllib.load(fh)
    except OSError as exc:
        raise RecipeError(f"{path}: cannot read the recipe ({exc.strerror or exc})") from None
    except tomllib.TOMLDecodeError as exc:
        raise RecipeError(f"{path}: not TOML: {exc}") from None


def parse_recipe(doc: Mapping[str, Any], path: Path, data_dir: Path | None = None,
                 shipped: bool = False) -> Recipe:
    """A recipe from its TOML document ``doc`` (read from ``path``). Relative data paths are
    taken from ``data_dir`` (else the recipe's ``data_dir``, itself relative to the recipe's
    folder; else the shared data folder for the shipped recipe, the recipe's folder for
    another)."""
    _check_keys(path, "", doc, TOP_KEYS)
    if not shipped:
        doc = _merged(doc, _read(SHIPPED_RECIPE))
    seed = _typed(doc.get("seed", 0), 0, path, "seed")
    name = _typed(doc.get("name", "safeil" if shipped else path.stem), "", path, "name")
    if data_dir is None:
        own = doc.get("data_dir")
        data_dir = (path.parent / _typed(own, "", path, "data_dir") if own is not None
                    else DEFAULT_DATA_DIR if shipped else path.parent)
    init = doc.get("init")
    return Recipe(
        path=path, name=name, seed=seed,
        data=_data(doc.get("data", []), Path(data_dir), path, seed),
        pipeline=_config(PipelineConfig, doc.get("pipeline", {}), path, "[pipeline] "),
        split=_split(doc.get("split", {}), seed, path),
        **{s: _stage(s, doc.get(s, {}), seed, path) for s in STAGES},
        certify=_certify(doc.get("certify", {}), seed, path),
        init=None if init is None else _typed(init, "", path, "init"))


def load_recipe(path: str | Path | None = None, data_dir: str | Path | None = None) -> Recipe:
    """The recipe in the TOML file ``path`` (None: the shipped one)."""
    shipped = path is None
    path = SHIPPED_RECIPE if path is None else Path(path)
    return parse_recipe(_read(path), path, None if data_dir is None else Path(data_dir), shipped)
