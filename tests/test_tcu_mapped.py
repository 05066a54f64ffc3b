"""The reference TCU through a mapping file: the same logic on another CAN matrix.

Offline (plant and TCU in one process, every message through cantools'
encode and decode at its mapping cycle time), the first 25 s of the paper
cycle (launch at full load, 1-2-3-4, braking 4-3-2-1) must shift:

- through the project's own contract expressed as a mapping
  (``can_dbc/mappings/dct_hil.toml``): exactly as through the hard-wired
  contract (``ContractLink``): the same quantisation, the same cycle phases;
- through the example vehicle matrix (``can_dbc/mappings/vehicle.toml``:
  a 500 kbit/s powertrain bus and an I/O bus, other scalings, a vehicle speed
  sent as magnitude and direction): in the same sequence, each shift within
  30 ms (the other quantisation and 10 ms refresh of the vehicle signals move
  a shift by a TCU period or a few).
"""

import os
import re

import pytest

from can_dbc import mapping
from plant.maneuvers import gear_shifts, get_maneuver
from plant.model import Plant
from tcu_stub.mapped_link import MappedLink, MissingSignalError
from tcu_stub.offline import run_offline

DURATION_S = 25.0
SHIFT_TOLERANCE_S = 0.030


def shifts(link):
    m = get_maneuver("paper-cycle")
    plant = Plant(overrides={"hydraulics": {"pressure_commanded": 0}})
    plant.reset(**m.reset_kwargs)
    rec = run_offline(plant, m.driver, DURATION_S, record_every_s=0.002, link=link)
    return gear_shifts(rec["time_s"], rec["gear"])


@pytest.fixture(scope="module")
def reference():
    return shifts(None)


def test_the_reference_run_has_the_shifts_of_the_first_launch(reference):
    assert [(a, b) for _, a, b in reference] == [(1, 2), (2, 3), (3, 4), (4, 3), (3, 2), (2, 1)]


@pytest.mark.slow
def test_the_default_mapping_is_the_hard_wired_contract(reference):
    link = MappedLink(mapping.load(mapping.DEFAULT_MAPPING))
    assert shifts(link) == reference


@pytest.mark.slow
def test_the_vehicle_matrix_gives_the_same_shifts(reference):
    link = MappedLink(mapping.load(mapping.find_mapping("vehicle")))
    got = shifts(link)
    assert [(a, b) for _, a, b in got] == [(a, b) for _, a, b in reference]
    for (t, a, b), (t0, _, _) in zip(got, reference):
        assert abs(t - t0) <= SHIFT_TOLERANCE_S, f"{a}-{b} at {t:.3f} s, reference {t0:.3f} s"


def test_the_vehicle_speed_keeps_its_sign_through_magnitude_and_direction():
    link = MappedLink(mapping.load(mapping.find_mapping("vehicle")))
    plant = Plant(overrides={"hydraulics": {"pressure_commanded": 0}})
    plant.reset(vehicle_speed_kmh=-8.0)
    view = link.sensors(plant.outputs, 0)
    assert view["VehicleSpeed"] == pytest.approx(float(plant.outputs["vehicle_speed_kmh"]), abs=0.1)
    assert view["VehicleSpeed"] < 0


def copy_without(tmp_path, message):
    """vehicle.toml in tmp_path with its DBC paths absolute and no signal of
    ``message`` mapped (the plant still sends it, every signal at its start value)."""
    src = mapping.find_mapping("vehicle")
    text = open(src, encoding="utf-8").read()
    here = os.path.dirname(src)
    text = re.sub(r'dbc = "([^"]+)"',
                  lambda m: f'dbc = "{os.path.normpath(os.path.join(here, m.group(1)))}"', text)
    head = f"[message.{message}.signals]\n"
    start = text.index(head)
    end = text.find("\n\n", start)
    text = text[:start] + (text[end + 2:] if end >= 0 else "")
    path = tmp_path / "vehicle-without.toml"
    path.write_text(text, encoding="utf-8")
    return str(path)


def test_a_matrix_without_a_quantity_the_tcu_needs_is_refused_in_one_line(tmp_path):
    m = mapping.load(copy_without(tmp_path, "IO_Pressures"))
    with pytest.raises(MissingSignalError) as e:
        MappedLink(m)
    text = str(e.value)
    assert "\n" not in text
    assert "vehicle-without.toml" in text and "clutch1_pressure_bar" in text


def test_simulate_runs_the_stub_through_a_mapping(capsys):
    from dct_hil import cli

    assert cli.main(["simulate", "--scenario", "0-100", "--duration", "3", "--mapping",
                     "vehicle"]) == 0
    out = capsys.readouterr().out
    assert "through the matrix of" in out and "vehicle.toml" in out


@pytest.mark.parametrize("args, says", [
    (["--mapping", "no-such-mapping.toml"], "no-such-mapping.toml"),
    (["--mapping", "vehicle", "--tcu", "none"], "--tcu none"),
])
def test_simulate_with_a_bad_mapping_is_one_line(capsys, args, says):
    from dct_hil import cli

    assert cli.main(["simulate", "--scenario", "0-100", "--duration", "1", *args]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("dct-hil: error:") and says in err[0]
