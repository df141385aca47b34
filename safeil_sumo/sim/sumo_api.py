"""The one seam to the simulator: the only module that imports libsumo or traci (lazily).

The ``libsumo`` module and a ``traci`` connection already satisfy :class:`SumoApi`; tests pass
a fake. The runner only ever talks to SUMO through the methods listed here.
"""

from __future__ import annotations

import itertools
import os
import shutil
import signal
import subprocess
import threading
from collections.abc import Sequence
from contextlib import suppress
from pathlib import Path
from typing import Any, Protocol


class VehicleDomain(Protocol):
    def add(self, vehID: str, routeID: str, typeID: str = ..., depart: str = ...,
            departLane: str = ..., departPos: str = ..., departSpeed: str = ...) -> None: ...
    def moveToXY(self, vehID: str, edgeID: str, laneIndex: int, x: float, y: float,
                 angle: float = ..., keepRoute: int = ...) -> None: ...
    def moveTo(self, vehID: str, laneID: str, pos: float) -> None: ...
    def remove(self, vehID: str) -> None: ...
    def setSpeed(self, vehID: str, speed: float) -> None: ...
    def setSpeedMode(self, vehID: str, speedMode: int) -> None: ...
    def setLaneChangeMode(self, vehID: str, laneChangeMode: int) -> None: ...
    def setLength(self, vehID: str, length: float) -> None: ...
    def setWidth(self, vehID: str, width: float) -> None: ...
    def getPosition(self, vehID: str) -> tuple[float, float]: ...
    def getAngle(self, vehID: str) -> float: ...
    def getSpeed(self, vehID: str) -> float: ...
    def getLength(self, vehID: str) -> float: ...
    def getWidth(self, vehID: str) -> float: ...
    # libsumo answers ("", -1) when there is no leader, traci None
    def getLeader(self, vehID: str, dist: float = ...) -> tuple[str, float] | None: ...
    def getIDList(self) -> Sequence[str]: ...
    # used by the synthetic-drive recorder (data/recorder.py) to see the surrounding traffic
    def getLanePosition(self, vehID: str) -> float: ...
    def subscribeContext(self, objectID: str, domain: int, dist: float,
                         varIDs: Sequence[int] = ..., begin: float = ...,
                         end: float = ...) -> None: ...
    def getContextSubscriptionResults(self, objectID: str) -> dict[str, dict[int, Any]]: ...


class SimulationDomain(Protocol):
    def step(self, time: float = ...) -> Any: ...
    def getTime(self) -> float: ...
    def getCollidingVehiclesIDList(self) -> Sequence[str]: ...


class RouteDomain(Protocol):
    def add(self, routeID: str, edges: Sequence[str]) -> None: ...


class LaneDomain(Protocol):
    def getLastStepVehicleIDs(self, laneID: str) -> Sequence[str]: ...
    def getLength(self, laneID: str) -> float: ...


class GuiDomain(Protocol):
    """sumo-gui's view (traci with ``gui=True`` only)."""

    def trackVehicle(self, viewID: str, vehID: str) -> None: ...
    def setZoom(self, viewID: str, zoom: float) -> None: ...
    def getZoom(self, viewID: str = ...) -> float: ...
    def getBoundary(self, viewID: str = ...) -> tuple[tuple[float, float], tuple[float, float]]: ...
    def screenshot(self, viewID: str, filename: str, width: int = ...,
                   height: int = ...) -> None: ...


class SumoApi(Protocol):
    """The subset of the TraCI API the closed loop and the recorder use (libsumo and traci both
    satisfy it)."""

    vehicle: VehicleDomain
    simulation: SimulationDomain
    route: RouteDomain
    lane: LaneDomain
    gui: GuiDomain  # only usable when started with gui=True

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


def has_display() -> bool:
    """Whether a window can open (X11 or Wayland): sumo-gui needs one."""
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


GUI_CONNECT_RETRIES = 5  # [-] traci connection attempts (1 s apart) to a starting sumo-gui
# --start: without it sumo-gui waits for its play button and the first traci step blocks forever;
# --quit-on-end: without it the window stays open and traci's close() waits for the user
GUI_OPTIONS = ("--start", "--quit-on-end")
GUI_VIEW = "View #0"  # sumo-gui's first (and only) view
# a sumo-gui whose OpenGL context fails (e.g. no Mesa DRI driver: "X Error ... BadValue") accepts
# the traci connection and never answers: it is killed after this long [s]
GUI_START_TIMEOUT_S = GUI_CONNECT_RETRIES + 5.0


_TRACI_LABELS = itertools.count()  # each headless traci start gets its own connection label


def start(args: Sequence[str], backend: str = "libsumo", gui: bool = False) -> SumoApi:
    """Start SUMO with command-line ``args`` (without the binary) and return its API.

    ``backend``: ``"libsumo"`` (in-process, fast; ONE simulation per process: the module is
    returned) or ``"traci"`` (a SUMO process behind a socket; needed for ``sumo-gui``). A
    headless traci start returns its own labelled connection, so several traci simulations can
    run side by side in one process (what Gymnasium's SyncVectorEnv needs); sumo-gui uses
    traci's default connection (one per process). Raises :class:`SumoError` with SUMO's message
    on failure.
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
    if gui:
        _start_gui(api, binary, args)
        return api
    label = f"safeil_sumo_{next(_TRACI_LABELS)}" if backend == "traci" else None
    try:
        if label is None:
            api.start([binary, *args])
        else:  # doSwitch=False: traci's module-level default connection stays untouched
            api.start([binary, *args], label=label, doSwitch=False)
    except Exception as exc:  # libsumo raises TraCIException / FatalTraCIError
        raise SumoError(f"SUMO failed to start: {exc}") from exc
    return api if label is None else api.getConnection(label)


def _start_gui(traci: Any, binary: str, args: Sequence[str]) -> None:
    """Start sumo-gui and connect traci to it, failing in seconds whether it dies or hangs.

    Not ``traci.start``: that relaunches a dying sumo-gui ``numRetries`` times and waits forever
    for one that hangs. sumo-gui runs in its own process group so the watchdog also kills the
    binary the eclipse-sumo ``sumo-gui`` wrapper script starts.
    """
    port = traci.getFreeSocketPort()
    proc = subprocess.Popen([binary, *GUI_OPTIONS, *args, "--remote-port", str(port)],
                            process_group=0)
    answered = threading.Event()

    def kill() -> None:
        if not answered.is_set():
            _kill_group(proc)

    watchdog = threading.Timer(GUI_START_TIMEOUT_S, kill)
    watchdog.start()
    try:
        traci.init(port, numRetries=GUI_CONNECT_RETRIES, proc=proc)
        answered.set()
    except Exception as exc:  # TraCIException / FatalTraCIError
        died = proc.poll() is not None and not watchdog.finished.is_set()
        _kill_group(proc)
        proc.wait()
        # forget the half-open connection so a later start can use the default label (best
        # effort: the start has failed already)
        with suppress(Exception):
            traci.close(wait=False)
        why = f"it exited with code {proc.returncode}" if died else "it did not answer"
        raise SumoError(f"sumo-gui failed to start ({why}: {exc}); see its messages above and "
                        "the README's sumo-gui paragraph (OpenGL via Mesa, a 24-bit display, "
                        "a font)") from exc
    finally:
        watchdog.cancel()


def _kill_group(proc: subprocess.Popen[Any]) -> None:
    with suppress(ProcessLookupError):  # already gone
        os.killpg(proc.pid, signal.SIGKILL)


def track_in_gui(api: SumoApi, veh_id: str, view_width_m: float) -> None:
    """Make sumo-gui's view follow ``veh_id`` (already in the simulation), zoomed so the view is
    about ``view_width_m`` wide whatever the network's size and the window's."""
    api.gui.trackVehicle(GUI_VIEW, veh_id)
    (x0, _), (x1, _) = api.gui.getBoundary(GUI_VIEW)
    if x1 > x0:  # sumo-gui's zoom is relative to the whole network: scale the current one
        api.gui.setZoom(GUI_VIEW, api.gui.getZoom(GUI_VIEW) * (x1 - x0) / view_width_m)


def gui_screenshot(api: SumoApi, path: Path) -> None:
    """Save sumo-gui's view as an image (format from the suffix) at the next simulation step."""
    # sumo-gui writes the file itself, relative to its own working directory: pass it absolute
    api.gui.screenshot(GUI_VIEW, str(Path(path).resolve()))


def version() -> str:
    """The SUMO version of the installed wheel, e.g. ``"1.28.0"``."""
    try:
        from importlib.metadata import version as pkg_version

        return pkg_version("eclipse-sumo")
    except Exception:  # noqa: BLE001  # pragma: no cover - metadata missing: a label only
        return "unknown"
