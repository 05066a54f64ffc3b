"""`dct-hil a2l`'s file read by the tools engineers have, IF_DATA and all.

Two independent readers, each given the file as `dct-hil a2l` writes it (the
default matrix, and the example vehicle's with XCP on both transports):

* a2ltool (PyPI: the a2lfile crate's command line): ``--check --strict``
  reports no problem; ``--ifdata-cleanup``, which drops every IF_DATA the
  file's A2ML does not describe, drops none (and does drop a broken one:
  the check bites); ``--show-xcp`` reads the transport out of the file.
* pya2l: the A2ML is in its tree and every IF_DATA block is there, with the
  XCP transport's port and address.

Then the slave: pyxcp connects to a running server and what the slave answers
(CONNECT, GET_ID, the EPK read at ADDR_EPK, PAG, the segment and its pages,
DAQ) is what its A2L says.
"""

from __future__ import annotations

import argparse
import io
import re
import struct
import subprocess
import sys
import uuid
from pathlib import Path

import pytest
import requires

from rt_loop.measure.xcp import a2l, a2ml
from rt_loop.measure.xcp import protocol as xcp_protocol

VEHICLE = ("--mapping", "vehicle", "--xcp-transport", "both", "--xcp-port", "6001",
           "--xcp-address", "192.168.7.3")


def _a2ltool() -> str:
    """a2ltool next to this Python (the test extra installs it into the venv)."""
    exe = Path(sys.executable).with_name("a2ltool")
    if not exe.exists():
        pytest.fail(f"a2ltool is not installed ({exe} missing): scripts/setup installs the "
                    "test extra (pip install -e '.[test]')")
    return str(exe)


def _write(path: Path, *argv: str) -> str:
    p = argparse.ArgumentParser()
    a2l.add_arguments(p)
    assert a2l.run(p.parse_args([str(path), *argv]), out=io.StringIO()) == 0
    return path.read_text()


@pytest.fixture(scope="module", params=["default", "vehicle"])
def written(request, tmp_path_factory):
    """(path, text, argv) of `dct-hil a2l`'s output."""
    argv = () if request.param == "default" else VEHICLE
    path = tmp_path_factory.mktemp("a2l") / f"{request.param}.a2l"
    return path, _write(path, *argv), argv


def _tool(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([_a2ltool(), *args], capture_output=True, text=True, timeout=120)


def _if_data_count(text: str) -> int:
    return len(re.findall(r"^\s*/begin IF_DATA XCP\b", text, re.M))


# ---------------------------------------------------------------------------
# a2ltool
# ---------------------------------------------------------------------------

def test_a2ltool_check_strict_finds_no_problem(written):
    path, _text, _argv = written
    run = _tool("--check", "--strict", str(path))
    out = run.stdout + run.stderr
    assert run.returncode == 0, out
    assert "Consistency check complete. No problems found." in out, out
    assert not re.search(r"warning|error", out, re.I), out


def test_a2ltool_parses_every_if_data_by_the_a2ml(written, tmp_path):
    path, text, _argv = written
    assert _if_data_count(text) == 2                # the module's and the memory segment's
    cleaned = tmp_path / "cleaned.a2l"
    run = _tool("--ifdata-cleanup", str(path), "-o", str(cleaned))
    assert run.returncode == 0, run.stdout + run.stderr
    assert _if_data_count(cleaned.read_text()) == 2
    # the control: an IF_DATA the A2ML does not allow (a bad enum, a number too
    # large for its uchar) is dropped by the same command
    for good, bad in (("OVERLOAD_INDICATION_EVENT PRESCALER", "OVERLOAD_INDICATION_NONE PRESCALER"),
                      ("INIT_SEGMENT 0 /end PAGE", "INIT_SEGMENT 300 /end PAGE")):
        broken = tmp_path / "broken.a2l"
        broken.write_text(text.replace(good, bad))
        run = _tool("--ifdata-cleanup", str(broken), "-o", str(cleaned))
        assert run.returncode == 0, run.stdout + run.stderr
        assert _if_data_count(cleaned.read_text()) == 1, bad


def test_a2ltool_reads_the_xcp_transport(written):
    path, _text, argv = written
    run = _tool("--show-xcp", str(path))
    assert run.returncode == 0, run.stdout + run.stderr
    shown = run.stdout
    if argv:
        assert "XCP on UDP/IP" in shown and "XCP on TCP/IP" in shown
        assert shown.count("address: 192.168.7.3") == 2 and shown.count("port: 6001") == 2
    else:
        assert "XCP on UDP/IP" in shown and "TCP/IP" not in shown
        assert "address: 127.0.0.1" in shown and "port: 5555" in shown


# ---------------------------------------------------------------------------
# pya2l
# ---------------------------------------------------------------------------

def _blocks(blob) -> list[tuple[str, list]]:
    """pya2l's generic IF_DATA element as (name, values) of it and every block
    in it, depth first (a value: a number, a string, or a block's name)."""
    out = []
    which = blob.WhichOneof("oneof")
    node = getattr(blob, which)
    if which != "Generic":
        return out
    values = []
    for e in node.Element:
        w = e.WhichOneof("oneof")
        values.append(f"/{getattr(e, w).Name.Value}" if w == "Generic" else getattr(e, w).Value)
    out.append((node.Name.Value, values))
    for e in node.Element:
        out += _blocks(e)
    return out


def test_pya2l_reads_the_a2ml_and_every_if_data_block(written, parser):
    _path, text, argv = written
    tree = parser.tree_from_a2l(text.encode(), enforce_version_check=False)
    module = tree.PROJECT.MODULE[0]
    assert len(module.A2ML.Declaration) >= 5      # the structs and the IF_DATA block
    blocks = [b for ifd in module.IF_DATA for blob in ifd.Blob for b in _blocks(blob)]
    seg = [b for ms in module.MOD_PAR.MEMORY_SEGMENT for ifd in ms.IF_DATA
           for blob in ifd.Blob for b in _blocks(blob)]
    # every /begin in the text's IF_DATA blocks is in the tree: nothing dropped
    inside = re.findall(r"/begin IF_DATA XCP(.*?)/end IF_DATA", text, re.S)
    in_text = sorted(re.findall(r"/begin (\w+)", "".join(inside)))
    assert sorted(name for name, _ in blocks + seg) == in_text
    # pya2l 0.4 parses IF_DATA generically, A2ML or not, and warns of each block
    # inside one as if it were repeated ("may be used at most once here"): the
    # tree above holds them all, so those warnings and no other are allowed
    for warning in parser.warnings:
        m = re.match(r"\d+:\d+ (\w+) may be used at most once here", warning)
        assert m and m.group(1) in in_text, warning
    named = {}
    for name, values in blocks + seg:
        named.setdefault(name, []).append(values)
    port, host = ("6001", "192.168.7.3") if argv else ("5555", "127.0.0.1")
    transports = ("XCP_ON_UDP_IP", "XCP_ON_TCP_IP") if argv else ("XCP_ON_UDP_IP",)
    for tl in transports:
        assert named[tl] == [[0x0104, int(port), "ADDRESS", host]]
    assert "XCP_ON_TCP_IP" in named or not argv
    assert [v[:3] for v in named["EVENT"]] == [["tick", "tick", 0], ["10ms", "10ms", 1],
                                               ["100ms", "100ms", 2]]
    assert named["PAG"] == [[1]] and named["SEGMENT"][0][:5] == [0, 2, 0, 0, 0]
    mod_par = module.MOD_PAR
    assert mod_par.ADDR_EPK[0].Address.Value == xcp_protocol.EPK_ADDRESS
    assert mod_par.EPK.Identifier.Value == re.search(r'EPK "([^"]+)"', text).group(1)


# ---------------------------------------------------------------------------
# the A2ML against the slave's codes
# ---------------------------------------------------------------------------

def test_a2ml_command_codes_are_the_slaves():
    codes = {name: value for name, value in vars(xcp_protocol).items()
             if name.isupper() and isinstance(value, int)}
    for name, code in a2ml.OPTIONAL_CMD_CODES.items():
        if name in codes:
            assert codes[name] == code, name
    assert a2ml.OPTIONAL_LEVEL1_CMD_CODES["GET_VERSION"] == xcp_protocol.GET_VERSION_SUB
    # every command the A2L declares optional is one the slave has a code for
    for name in a2l.XCP_DEFAULTS["optional_cmds"]:
        assert name in a2ml.OPTIONAL_CMD_CODES and name in codes, name


# ---------------------------------------------------------------------------
# the slave answers what its A2L says
# ---------------------------------------------------------------------------

_ACCESS = {"NOT_ALLOWED": 0, "WITHOUT_XCP_ONLY": 1, "WITH_XCP_ONLY": 2, "WITHOUT_ECU_ONLY": 1,
           "WITH_ECU_ONLY": 2, "DONT_CARE": 3}


@pytest.mark.slow
def test_the_slave_answers_what_its_a2l_says():
    requires.module("pyxcp")
    from pyxcp import types
    from test_xcp_protocol import pyxcp_master

    from rt_loop.server import Server

    srv = Server(f"a2l-{uuid.uuid4().hex[:8]}", interface="virtual", priority=0,
                 xcp="127.0.0.1:0")
    srv.start()
    try:
        with pyxcp_master(srv.xcp) as x:
            conn = x.connect()
            text = x.identifier(4)              # the A2L the slave serves (GET_ID 4)
            host, port = srv.xcp.address
            assert f'/begin XCP_ON_UDP_IP 0x0104 {port} ADDRESS "{host}"' in text
            layer = re.search(r"/begin PROTOCOL_LAYER\s+0x0104 (\d+) (\d+)(?: \d+){5} (\d+) (\d+) "
                              r"BYTE_ORDER_MSB_LAST ADDRESS_GRANULARITY_BYTE", text)
            assert layer, text[:2000]
            assert (conn.maxCto, conn.maxDto) == (int(layer.group(3)), int(layer.group(4)))
            assert conn.commModeBasic.byteOrder == "INTEL"

            # the EPK: GET_ID 5 and the memory at ADDR_EPK say the A2L's EPK
            epk = re.search(r'EPK "([^"]+)"', text).group(1)
            addr = int(re.search(r"ADDR_EPK (0x[0-9A-F]+)", text).group(1), 16)
            assert addr == xcp_protocol.EPK_ADDRESS
            assert x.identifier(5) == epk
            assert bytes(x.shortUpload(len(epk), addr)).decode("ascii") == epk
            x.setMta(addr)
            assert bytes(x.upload(len(epk))).decode("ascii") == epk

            # PAG, the calibration segment and its pages
            pag = int(re.search(r"/begin PAG (\d+) /end PAG", text).group(1))
            assert x.getPagProcessorInfo().maxSegments == pag
            seg = re.search(r"/begin MEMORY_SEGMENT calibration \"[^\"]*\" DATA RAM INTERN "
                            r"(0x[0-9A-F]+) (0x[0-9A-F]+)", text)
            start, size = int(seg.group(1), 16), int(seg.group(2), 16)
            assert x.getSegmentInfo(0, 0, 0, 0).basicInfo == start
            assert x.getSegmentInfo(0, 0, 1, 0).basicInfo == size
            number, pages, ext = map(int, re.search(r"/begin SEGMENT (\d+) (\d+) (\d+) ",
                                                    text).groups())
            assert number == 0
            info = x.getSegmentInfo(1, 0, 0, 0)
            assert (info.maxPages, info.addressExtension) == (pages, ext)
            declared = re.findall(r"/begin PAGE (\d+) ECU_ACCESS_(\w+) XCP_READ_ACCESS_(\w+) "
                                  r"XCP_WRITE_ACCESS_(\w+) INIT_SEGMENT (\d+) /end PAGE", text)
            assert len(declared) == pages
            for page, ecu, read, write, init in declared:
                raw = x.transport.request(types.Command.GET_PAGE_INFO, 0, 0, int(page))
                expected = _ACCESS[ecu] | _ACCESS[read] << 2 | _ACCESS[write] << 4
                assert (raw[0], raw[1]) == (expected, int(init)), page

            # DAQ: the processor and the events
            daq = re.search(r"/begin DAQ\s+DYNAMIC (\d+) (\d+) (\d+) ", text)
            proc = x.getDaqProcessorInfo()
            assert (proc.maxDaq, proc.maxEventChannel, proc.minDaq) == tuple(map(int, daq.groups()))
            assert proc.daqProperties.daqConfigType == "DYNAMIC"
            assert proc.daqProperties.prescalerSupported
            for channel, cycle, unit in re.findall(
                    r'/begin EVENT "\w+" "\w+" (\d+) DAQ 0xFF (\d+) (\d+) ', text):
                ev = x.getDaqEventInfo(int(channel))
                assert (ev.eventChannelTimeCycle, int(ev.eventChannelTimeUnit)) == (int(cycle), int(unit))
            # the EPK is read only
            with pytest.raises(Exception, match="WRITE_PROTECTED"):
                x.shortDownload(addr, 0, struct.pack("<B", 0))
            x.disconnect()
    finally:
        srv.stop()
