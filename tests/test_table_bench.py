"""The codec cost benchmark (python -m can_dbc.table --bench): what it times and
what it reports, for the shipped mappings and any other mapping file. Few
iterations, and never a timing asserted: the figures are the machine's."""

import json
import os

import pytest

from can_dbc import mapping, table

#: (name, sent, received, {bus: (sent, received)}) of the shipped mappings
SHIPPED = [("dct_hil", 7, 4, {"dct": (7, 4)}),
           ("vehicle", 14, 5, {"pt": (9, 3), "io": (5, 2)})]


@pytest.fixture(scope="module")
def c():
    from rt_loop._rt_loop import (  # built by scripts/setup: a missing build fails here
        ffi,
        lib,
    )
    assert hasattr(lib, "ct_bench_tick"), "rt_loop._rt_loop does not include the table codec"
    return ffi, lib


def _bench(argv, capsys):
    code = table.main(["--bench", "--iterations", "300", "--repeat", "2", *argv])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def _check_result(r, name, n_tx, n_rx, buses):
    assert r["name"] == name and r["mapping"].endswith(f"{name}.toml")
    assert len(r["tx_messages"]) == n_tx and len(r["rx_messages"]) == n_rx
    assert r["frames_per_tick"] == {"encoded": n_tx, "decoded": n_rx, "total": n_tx + n_rx}
    assert {b["bus"]: (len(b["tx_messages"]), len(b["rx_messages"])) for b in r["buses"]} == buses
    assert r["iterations"] == 300 and r["repeat"] == 2 and len(r["runs_ns"]) == 2
    assert r["all_messages_ns"] == min(r["runs_ns"]) and r["all_messages_ns"] > 0
    # the bound's figure is the loop's own costliest tick, timed as one tick
    assert r["figure"] == "schedule_worst_tick"
    assert r["ns_per_tick"] == r["schedule"]["ns_per_tick"] > 0
    assert 1 <= len(r["schedule"]["tx_messages"]) <= n_tx
    for b in r["buses"]:
        assert b["calls"] == 1 and len(b["runs_ns"]) == 2
    # a run's figure is the sum of its buses'
    for k, total in enumerate(r["runs_ns"]):
        assert total == pytest.approx(sum(b["runs_ns"][k] for b in r["buses"]))
    assert r["bound_ns"] == 1000.0 and r["pass"] is (r["ns_per_tick"] <= 1000.0)
    sched = r["schedule"]
    assert 1 <= r["schedule_worst_tick_tx"] == len(sched["tx_messages"]) <= n_tx
    # the burst is part of the tick, but the two are timed apart (best of a few runs each):
    # allow the timer's noise between them
    assert sched["ns_per_tick"] > 0 and 0 < sched["rx_burst_ns"] <= 1.25 * sched["ns_per_tick"]


def test_both_mappings_are_timed_and_written_as_json(c, tmp_path, capsys):
    path = tmp_path / "deep" / "codec_bench.json"
    code, out, _ = _bench(["--json", str(path)], capsys)
    assert code == 0
    report = json.loads(path.read_text())
    assert set(report) == {"what", "definition", "bound_ns", "iterations", "repeat", "machine",
                           "mappings", "pass"}
    assert report["bound_ns"] == 1000.0 and report["iterations"] == 300 and report["repeat"] == 2
    assert "the frames due in the loop's costliest tick" in report["definition"]
    assert "one frame of every received message checked + decoded" in report["definition"]
    assert {"cpu", "nproc", "kernel", "python", "date"} <= set(report["machine"])
    assert [r["name"] for r in report["mappings"]] == [name for name, *_ in SHIPPED]
    for r, (name, n_tx, n_rx, buses) in zip(report["mappings"], SHIPPED):
        _check_result(r, name, n_tx, n_rx, buses)
    assert report["pass"] is all(r["pass"] for r in report["mappings"])
    # printed: the definition, per mapping its messages, frames, figure, bound and verdict
    assert "one tick's work: the frames due in the loop's costliest tick" in out
    assert "dct_hil (can_dbc/mappings/dct_hil.toml): 7 plant messages encoded + protected, " \
           "4 TCU messages checked + decoded (1 bus: dct 7 + 4)" in out
    assert "vehicle (can_dbc/mappings/vehicle.toml): 14 plant messages encoded + protected, " \
           "5 TCU messages checked + decoded (2 buses: pt 9 + 3, io 5 + 2)" in out
    assert "every message at once (7 encoded, 4 decoded" in out
    assert "every message at once (14 encoded, 5 decoded" in out
    assert out.count("bound 1000 ns: ") == 2
    assert f"figures in {path}" in out


def test_the_schedules_worst_tick(c):
    """The loop staggers its sent messages: the contract's 7 never meet (at 2 kHz
    their rates add up to less than one frame per tick), the vehicle's 14 two at most."""
    for name, worst in (("dct_hil", 1), ("vehicle", 2)):
        m = mapping.load(mapping.find_mapping(name))
        assert table.schedule_worst_tick(m) == worst
        plan = table.send_schedule(m)
        assert len(plan) == len([x for x in m.messages if x.direction == "send"])
        cycles = {(x.bus, x.name): x.cycle_ms for x in m.messages}
        for bus, msg, div, off in plan:
            assert div == round(cycles[bus, msg] * m.rate_hz / 1000) and 0 <= off < div


def test_one_mapping_file(c, tmp_path, capsys):
    path = tmp_path / "one.json"
    vehicle = os.path.join(mapping.MAPPINGS_DIR, "vehicle.toml")
    code, out, _ = _bench(["--mapping", vehicle, "--json", str(path)], capsys)
    assert code == 0
    report = json.loads(path.read_text())
    assert [r["name"] for r in report["mappings"]] == ["vehicle"]
    _check_result(report["mappings"][0], *SHIPPED[1])
    assert "dct_hil" not in out


def test_check_exits_1_above_the_bound(c, tmp_path, capsys, monkeypatch):
    path = tmp_path / "b.json"
    monkeypatch.setattr(table, "BOUND_NS", 0.0)          # every figure above it
    code, out, err = _bench(["--mapping", "dct_hil", "--json", str(path), "--check"], capsys)
    assert code == 1 and "FAIL" in out and "above 0 ns per tick: dct_hil" in err
    assert json.loads(path.read_text())["pass"] is False
    monkeypatch.setattr(table, "BOUND_NS", 1e12)         # every figure below it
    code, out, err = _bench(["--mapping", "dct_hil", "--json", str(path), "--check"], capsys)
    assert code == 0 and "pass" in out and not err
    assert json.loads(path.read_text())["pass"] is True


def test_a_bad_mapping_is_one_line(c, tmp_path, capsys):
    code, _, err = _bench(["--mapping", str(tmp_path / "missing.toml"), "--json", ""], capsys)
    assert code == 2 and err.startswith("python -m can_dbc.table: ") and err.count("\n") == 1


# -------------------------------------------- a mapping with more received messages than one call takes

N_RX = 11


def _many_messages_mapping(tmp_path):
    """A matrix of its own: 2 PLANT messages, N_RX TCU messages (more than
    CT_BENCH_MAX_RX), each with an 8-bit value; protected by the project's own
    scheme (CRC and counter)."""
    lines = ['VERSION ""', "", "NS_ :", "", "BS_:", "", "BU_: PLANT TCU", ""]
    frames = [(0x100 + k, f"PLANT_{k}", "PLANT") for k in range(2)]
    frames += [(0x200 + k, f"TCU_{k}", "TCU") for k in range(N_RX)]
    for fid, name, sender in frames:
        receiver = "TCU" if sender == "PLANT" else "PLANT"
        lines += [f"BO_ {fid} {name}: 8 {sender}",
                  f' SG_ {name}_CRC : 0|8@1+ (1,0) [0|255] "" {receiver}',
                  f' SG_ {name}_Ctr : 8|4@1+ (1,0) [0|15] "" {receiver}',
                  f' SG_ {name}_Value : 16|8@1+ (0.5,0) [0|127.5] "" {receiver}', ""]
    lines += ['BA_DEF_ BO_ "GenMsgCycleTime" INT 0 65535;', 'BA_DEF_DEF_ "GenMsgCycleTime" 0;']
    lines += [f'BA_ "GenMsgCycleTime" BO_ {fid} 10;' for fid, _, _ in frames]
    (tmp_path / "many.dbc").write_text("\n".join(lines) + "\n")
    toml = ['[[bus]]', 'name = "many"', 'dbc = "many.dbc"', "bitrate = 500000",
            'plant_nodes = ["PLANT"]', 'tcu_nodes = ["TCU"]', ""]
    for _, name, _ in frames:
        toml += [f"[message.{name}]",
                 f'protection = {{ kind = "dct", crc = "{name}_CRC", counter = "{name}_Ctr" }}', ""]
    (tmp_path / "many.toml").write_text("\n".join(toml))
    return tmp_path / "many.toml"


def test_more_received_messages_than_one_call_takes(c, tmp_path):
    path = _many_messages_mapping(tmp_path)
    r = table.bench(iterations=300, repeat=2, mapping=str(path))
    _, lib = c
    per_call = lib.CT_BENCH_MAX_RX
    assert N_RX > per_call
    assert r["name"] == "many" and len(r["tx_messages"]) == 2 and len(r["rx_messages"]) == N_RX
    assert r["frames_per_tick"]["total"] == 2 + N_RX
    (bus,) = r["buses"]
    assert bus["calls"] == -(-N_RX // per_call)         # every frame of every call accepted (bench checks)
    assert r["ns_per_tick"] > 0


def test_the_calls_split_the_messages(c, monkeypatch):
    """Each call within ct_bench_tick's limits, every message in exactly one call."""
    t = table.CodecTable([(x.message, x.protection)
                          for x in mapping.load(mapping.find_mapping("vehicle")).codec_order("pt")])
    monkeypatch.setattr(table, "_TX_PER_CALL", 4)
    monkeypatch.setattr(table, "_rx_per_call", lambda: 2)
    tx, rx = list(range(9)), [9, 10, 11]
    calls = table._bench_calls(t, tx, rx)
    assert [(k["n_tx"], k["n_rx"]) for k in calls] == [(4, 2), (4, 1), (1, 0)]
    assert [k["tx"][i] for k in calls for i in range(k["n_tx"])] == tx
    assert [k["rx"][i] for k in calls for i in range(k["n_rx"])] == rx
    assert sum(table._bench_call(t, k, 50) for k in calls) > 0
