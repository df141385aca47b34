"""The replay's rebuilt road on recordings it had failed on (issue 20, part 3).

- ZalaZone as a replay source: ``load_source("zalazone")`` and its drivers, the cars named by
  each file's ``Vehicle_order`` row (the platoon order differs between files).
"""

from __future__ import annotations

import pytest
from fixtures_data import SHARED, require_file

from safeil_sumo.data.importers import openacc_vehicle_names, read_openacc_metadata
from safeil_sumo.replay import driver_of, load_source

ZALAZONE_DIR = SHARED / "openacc_zalazone"


# ------------------------------------------------------------------------- ZalaZone source


def test_zalazone_drivers_are_cars_named_by_each_files_metadata():
    """Position 3 is a Tesla Model 3 in part 22 and a BMW i3 in part 35 (the files' own
    ``Vehicle_order`` rows): the driver follows the car, not the position."""
    meta = read_openacc_metadata(require_file(ZALAZONE_DIR / "handling_part35.csv.gz"))
    names = openacc_vehicle_names(meta)
    assert names[1] == "SKODA_TARGET" and names[3] == "BMW_I3" and len(names) == 11
    assert driver_of("zalazone", "handling_part22_f3#0", SHARED) == "zalazone/TESLA_MODEL3"
    assert driver_of("zalazone", "handling_part35_f3_s1#2", SHARED) == "zalazone/BMW_I3"
    assert driver_of("zalazone", "handling_part35_f4_s2#0", SHARED) == "zalazone/MERCEDES_GLE450"
    # no such file or no such id: the file and the position stand in
    assert driver_of("zalazone", "handling_part99_f3_s2#0", SHARED) == \
        "zalazone/handling_part99_f3"
    assert driver_of("zalazone", "other#0", SHARED) == "zalazone/other"
    assert openacc_vehicle_names({}) == {}


def test_zalazone_source_loads_the_four_files():
    require_file(ZALAZONE_DIR / "handling_part22.csv.gz")
    drive = load_source("zalazone", SHARED)
    assert len(drive) == 71_007 and drive["recording_id"].nunique() == 50
    assert drive["recording_id"].str.startswith("handling_part").all()
    # the handling course's curvature clip (1/40 m), not the motorway's (1/250 m)
    assert drive["left_c2"].abs().max() == pytest.approx(0.5 / 40.0)
