"""The one seam to the simulator: the only module that imports libsumo or traci (lazily).

``libsumo`` and ``traci`` modules already satisfy :class:`SumoApi`; tests pass a fake. The runner
only ever talks to SUMO through the methods listed here.
"""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any, Protocol, Sequence


class VehicleDomain(Protocol):
    def add(self, vehID: str, routeID: str, typeID: str = ..., depart: str = ...,
            departLane: str = ..., departPos: str = ..., departSpeed: str = ...) -> None: ...
    def moveToXY(self, vehID: str, edgeID: str, laneIndex: int, x: float, y: float,
                 angle: float = ..., keepRoute: int = ...) -> None: ...
    def setSpeed(self, vehID: str, speed: float) -> None: ...
    def setSpeedMode(self, vehID: str, speedMode: int) -> None: ...
    def setLaneChangeMode(self, vehID: str, laneChangeMode: int) -> None: ...
    def setLength(self, vehID: str, length: float) -> None: ...
    def setWidth(self, vehID: str, width: float) -> None: ...
    def getPosition(self, vehID: str) -> tuple[float, float]: ...
    def getAngle(self, vehID: str) -> float: ...
    def getSpeed(self, vehID: str) -> float: ...
    def getIDList(self) -> Sequence[str]: ...
    # used by the synthetic-drive recorder (data/recorder.py) to see the surrounding traffic
    def getLanePosition(self, vehID: str) -> float: ...
    def subscribeContext(self, objectID: str, domain: int, dist: float,
                         varIDs: Sequence[int] = ..., begin: float = ...,
                         end: float = ...) -> None: ...
    def getContextSubscriptionResults(self, objectID: str) -> dict: ...


class SimulationDomain(Protocol):
    def step(self, time: float = ...) -> Any: ...
    def getTime(self) -> float: ...
    def getCollidingVehiclesIDList(self) -> Sequence[str]: ...


class RouteDomain(Protocol):
    def add(self, routeID: str, edges: Sequence[str]) -> None: ...


class LaneDomain(Protocol):
    def getLastStepVehicleIDs(self, laneID: str) -> Sequence[str]: ...


class SumoApi(Protocol):
    """The subset of the TraCI API the closed loop and the recorder use (libsumo and traci both
    satisfy it)."""

    vehicle: VehicleDomain
    simulation: SimulationDomain
    route: RouteDomain
    lane: LaneDomain

    def close(self) -> None: ...


class SumoError(RuntimeError):
    """SUMO could not be started or failed during a run."""


def sumo_binary(gui: bool = False) -> str:
    """Path of the ``sumo`` (or ``sumo-gui``) executable from the eclipse-sumo wheel or PATH."""
    name = "sumo-gui" if gui else "sumo"
    found = shutil.which(name)
    if found:
        return found
    try:
        import sumo  # the eclipse-sumo wheel

        candidate = Path(sumo.SUMO_HOME) / "bin" / name
        if candidate.exists():
            return str(candidate)
    except ImportError:
        pass
    raise SumoError(f"cannot find the {name!r} executable: pip install eclipse-sumo==1.28.0")


GUI_CONNECT_RETRIES = 5  # [-] traci connection attempts (1 s apart) to a starting sumo-gui


def start(args: Sequence[str], backend: str = "libsumo", gui: bool = False) -> SumoApi:
    """Start SUMO with command-line ``args`` (without the binary) and return the API module.

    ``backend``: ``"libsumo"`` (in-process, fast; one simulation per process) or ``"traci"``
    (socket; needed for ``sumo-gui``). Raises :class:`SumoError` with SUMO's message on failure.
    """
    if gui and backend != "traci":
        raise SumoError("sumo-gui needs the traci backend (--backend traci)")
    binary = sumo_binary(gui)
    if backend == "libsumo":
        import libsumo as api
    elif backend == "traci":
        import traci as api
    else:
        raise SumoError(f"unknown backend {backend!r}: use 'libsumo' or 'traci'")
    try:
        if gui:  # sumo-gui that cannot open its window dies: fail in seconds, not traci's minute
            api.start([binary, *args], numRetries=GUI_CONNECT_RETRIES)
        else:
            api.start([binary, *args])
    except Exception as exc:  # libsumo raises TraCIException / FatalTraCIError
        raise SumoError(f"SUMO failed to start: {exc}") from exc
    return api  # type: ignore[return-value]


def version() -> str:
    """The SUMO version of the installed wheel, e.g. ``"1.28.0"``."""
    try:
        from importlib.metadata import version as pkg_version

        return pkg_version("eclipse-sumo")
    except Exception:  # pragma: no cover - metadata missing
        return "unknown"
