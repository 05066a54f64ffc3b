"""The pytest plugin of the HiL bench (registered as the ``pytest11`` entry
point ``dct_hil``): a ``bench`` fixture, its command-line options and markers.

    def test_launch(bench):                        # a fresh bench per test
        bench.set("accel_pedal_pct", 30)
        bench.wait_until("gear == 2", timeout_s=8)

    @pytest.mark.bench(maneuver="0-100", record="out/0-100.mf4")
    def test_full_throttle(bench): ...

    @pytest.mark.tcu_under_test                    # no reference TCU: yours is on the bus
    def test_my_tcu(bench): ...

Options: ``--bench-transport embedded|socketcan`` (default embedded:
python-can's in-process bus, the reference TCU in a thread),
``--bench-channel NAME`` (SocketCAN: default vcan0), ``--bench-tcu
reference|external`` (external: no reference TCU for any test),
``--bench-tcu-clock wall|bus`` (the reference TCU's task clock: a tick per
2 ms of wall time, or per 2 ms plant frame, so its timers and reactions
follow plant time even on a busy machine), ``--bench-time-scale X`` (slow
motion, 0 < X <= 1), ``--bench-recordings
DIR`` (one recording per test, ``DIR/<test name>.mf4``: kept when the test
fails, deleted when it passes unless ``--bench-keep-recordings``).
``--bench-url tcp://HOST:PORT`` (``tls://``, or a socket path) with
``--bench-token-file`` and ``--bench-ca-file``: no bench is started; every
test drives the one running there (``dct-hil serve --control-tcp ... --tcu
reference``, or with the TCU under test on its bus), from ``Bench.reset()``.

The marker ``bench(...)`` takes ``dct_hil.bench.Bench.start``'s keywords
for one test (``transport``, ``channel``, ``maneuver``, ``record``,
``params``, ``mapping``, ``time_scale``, ``tcu_clock``, ``faults``, ...);
markers on the module, the class and the test add up, the closest one
winning a keyword they share. With
``--junitxml`` each test using the fixture carries the properties
``bench_recording`` (the recording's path, when kept) and
``bench_fault_events`` (the faults' starts and ends, JSON).

Importing this module costs nothing beyond pytest: the bench is imported
when the fixture is first used.
"""

from __future__ import annotations

import json
import os
import re

import pytest

_REPORTS = pytest.StashKey[dict]()
_SAFE = re.compile(r"[^\w.\-\[\]=+,]")


def pytest_addoption(parser: pytest.Parser) -> None:
    group = parser.getgroup("dct-hil", "dct-hil HiL bench (the bench fixture)")
    group.addoption("--bench-transport", choices=("embedded", "socketcan"), default="embedded",
                    help="embedded: python-can's in-process bus, the reference TCU in a thread "
                         "(default); socketcan: --bench-channel, the reference TCU as a process")
    group.addoption("--bench-channel", default=None, metavar="NAME",
                    help="the SocketCAN interface (default vcan0)")
    group.addoption("--bench-tcu", choices=("reference", "external"), default="reference",
                    help="reference: the bench starts the reference TCU (default); external: the "
                         "TCU under test is on the bus")
    group.addoption("--bench-tcu-clock", choices=("wall", "bus"), default=None,
                    help="the reference TCU's task clock: wall (a tick per 2 ms of wall time, "
                         "Bench.start's default in real time) or bus (a tick per 2 ms plant "
                         "frame: its timers follow plant time on a busy machine)")
    group.addoption("--bench-time-scale", type=float, default=None, metavar="X",
                    help="run plant and reference TCU in slow motion (0 < X <= 1)")
    group.addoption("--bench-recordings", default=None, metavar="DIR",
                    help="record each test as DIR/<test name>.mf4: kept when it fails, deleted "
                         "when it passes unless --bench-keep-recordings")
    group.addoption("--bench-keep-recordings", action="store_true",
                    help="keep the recordings of passing tests too")
    group.addoption("--bench-url", default=None, metavar="URL",
                    help="drive a bench that runs already (dct-hil serve --control-tcp, or "
                         "--control PATH) instead of starting one per test: tcp://HOST:PORT, "
                         "tls://HOST:PORT or a socket path; each test starts from reset() (faults "
                         "cleared, the car braked to a stop, the TCU calm)")
    group.addoption("--bench-token-file", default=None, metavar="FILE",
                    help="with --bench-url: the token (the server's --control-token-file)")
    group.addoption("--bench-ca-file", default=None, metavar="PEM",
                    help="with --bench-url tls://: the certificate the server's is checked "
                         "against (its own, when self-signed)")


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line(
        "markers", "bench(transport=None, maneuver=None, record=None, **kwargs): settings of "
                   "the bench fixture for this test (dct_hil.bench.Bench.start's keywords)")
    config.addinivalue_line(
        "markers", "tcu_under_test: the bench starts no reference TCU (the TCU under test is on "
                   "the bus)")


@pytest.hookimpl(wrapper=True, tryfirst=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo):
    report = yield
    item.stash.setdefault(_REPORTS, {})[report.when] = report
    return report


def _failed(item: pytest.Item) -> bool:
    reports = item.stash.get(_REPORTS, {})
    return any(r.failed for r in reports.values())


def recording_path(folder: str, name: str) -> str:
    """``folder/<name>.mf4`` with the characters a file name should not hold replaced."""
    return os.path.join(folder, _SAFE.sub("_", name) + ".mf4")


def marker_settings(item: pytest.Item) -> dict:
    """The keywords of every ``bench(...)`` marker of ``item``: module, class, test, the
    closest winning."""
    kwargs: dict = {}
    for marker in reversed(list(item.iter_markers("bench"))):     # farthest first
        if marker.args:
            raise pytest.UsageError(f"{item.nodeid}: bench(...) takes keywords only")
        kwargs.update(marker.kwargs)
    return kwargs


def bench_settings(item: pytest.Item, config: pytest.Config) -> dict:
    """The keywords of ``Bench.start`` for one test: options, then its marker."""
    opt = config.option
    kwargs: dict = {"transport": opt.bench_transport}
    if opt.bench_channel:
        kwargs["channel"] = opt.bench_channel
    if opt.bench_time_scale is not None:
        kwargs["time_scale"] = opt.bench_time_scale
    if opt.bench_tcu_clock is not None:
        kwargs["tcu_clock"] = opt.bench_tcu_clock
    kwargs.update(marker_settings(item))
    kwargs["tcu"] = not (item.get_closest_marker("tcu_under_test") is not None
                         or opt.bench_tcu == "external")
    if kwargs.get("record") is None and opt.bench_recordings:
        kwargs["record"] = recording_path(opt.bench_recordings, item.name)
    return kwargs


#: bench(...) keywords a bench that runs already cannot take (it was started with its own)
REMOTE_REFUSED = ("maneuver", "record", "params", "mapping", "faults", "log", "control")


def _attached(item: pytest.Item, config: pytest.Config):
    """The bench at --bench-url, reset for this test (the keywords of a bench(...) marker
    that only a bench of its own could take fail the test; the rest are the server's)."""
    from dct_hil.bench import Bench, BenchError

    opt = config.option
    refused = sorted(k for k in marker_settings(item) if k in REMOTE_REFUSED)
    if refused:
        pytest.fail(f"bench({', '.join(refused)}=...) needs a bench started for the test, "
                    f"not --bench-url", pytrace=False)
    try:
        b = Bench.attach(opt.bench_url, token_file=opt.bench_token_file,
                         ca_file=opt.bench_ca_file)
    except BenchError as e:
        pytest.fail(f"--bench-url {opt.bench_url}: {e}", pytrace=False)
    try:
        b.reset()
    except BenchError as e:
        b.detach()
        pytest.fail(f"the bench at {opt.bench_url} did not reset: {e}", pytrace=False)
    return b


@pytest.fixture
def bench(request: pytest.FixtureRequest):
    """A fresh ``dct_hil.bench.Bench`` for this test, stopped after it (with
    --bench-url: the running one, reset, and left running after it)."""
    from dct_hil.bench import Bench, BenchError

    item = request.node
    if request.config.option.bench_url is not None:
        b = _attached(item, request.config)
        try:
            yield b
        finally:
            try:
                item.user_properties.append(("bench_fault_events", json.dumps(b.events())))
                b.clear_all()
            except BenchError:
                pass
            b.detach()
        return
    kwargs = bench_settings(item, request.config)
    record = kwargs.get("record")
    explicit = marker_settings(item).get("record") is not None
    try:
        b = Bench.start(**kwargs)
    except BenchError as e:
        pytest.fail(f"the bench did not start: {e}", pytrace=False)
    events: list = []
    try:
        yield b
    finally:
        try:
            b.stop()
        finally:
            try:
                events = b.events()
            except BenchError:
                pass
        item.user_properties.append(("bench_fault_events", json.dumps(events)))
        if record is not None:
            keep = explicit or request.config.option.bench_keep_recordings or _failed(item)
            if keep:
                item.user_properties.append(("bench_recording", os.fspath(record)))
            else:                     # the recording and a CSV recording's fault events beside it
                for path in (record, os.path.splitext(os.fspath(record))[0] + ".faults.csv"):
                    try:
                        os.unlink(path)
                    except OSError:
                        pass
