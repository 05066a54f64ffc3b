"""The live bench view in a real browser: Debian's headless Chromium driven by
Selenium against a bench (the plant server and the reference TCU on the
embedded transport) with the page served beside it.

One bench, one page and one browser for the module; before each test the
bench is put back as the module started it (no maneuver, no fault, 30 %
accelerator, level road), so no test depends on what another left. The
tests read the page's models through BokehJS (``Bokeh.documents[0]``), move
its widgets as a user does (a slider's value set on its model, a button's
real DOM click) and read the effect back from the plant.
test_a_maneuver_started_on_the_page_drives_and_the_screenshot writes
docs/ui.png (the README's picture).

The bench runs at half speed with the reference TCU on the bus clock
(``TIME_SCALE``): the page, its server and the TCU share one Python process
and the browser the machine's CPUs, and these tests are about the page, not
real time; every bound on the plant is plant time. How fast the page updates
and what the browsers cost the loop is the benchmark's
(``python -m dct_hil.ui.bench``).

Without /usr/bin/chromium or /usr/bin/chromedriver these tests fail with the
line that says how to install them (scripts/test installs them)."""

import json
import os
import tempfile
import time
import urllib.error
import urllib.parse
import urllib.request

import pytest

from dct_hil.bench import Bench
from dct_hil.ui.server import UiServer

pytestmark = [pytest.mark.browser, pytest.mark.slow]

CHROMIUM = "/usr/bin/chromium"
CHROMEDRIVER = "/usr/bin/chromedriver"
INSTALL = ("install Debian's browser and its driver: apt-get install chromium chromium-driver "
           "(as root; scripts/test does it)")
SCREENSHOT = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "docs",
                          "ui.png")
TOKEN = "bench-token-42"
WAIT_S = 30.0
TIME_SCALE = 0.5


def require_browser(paths=(CHROMIUM, CHROMEDRIVER)):
    """Fails (never skips) naming what is missing and how to install it."""
    missing = [p for p in paths if not os.path.exists(p)]
    if missing:
        pytest.fail(f"{', '.join(missing)} missing: {INSTALL}", pytrace=False)


def wait_for(predicate, what, timeout=WAIT_S, step=0.05):
    """``predicate()`` until true; an element the page replaced meanwhile
    (it reloads after a form is sent) or has not shown yet counts as not yet."""
    from selenium.common.exceptions import WebDriverException

    deadline = time.monotonic() + timeout
    last = None
    while True:
        try:
            value = predicate()
        except WebDriverException as e:  # stale, not there yet, or the node of a page going away
            value, last = None, e
        if value:
            return value
        if time.monotonic() > deadline:
            why = "" if last is None else f" (last: {type(last).__name__}: {last.msg})"
            raise AssertionError(f"timed out after {timeout:g} s waiting for {what}{why}")
        time.sleep(step)


@pytest.fixture(scope="module")
def browser():
    require_browser()
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    profile = tempfile.mkdtemp(prefix="dct-hil-chromium-")
    options = webdriver.ChromeOptions()
    options.binary_location = CHROMIUM
    for arg in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
                "--no-first-run", "--disable-background-networking",
                "--disable-component-update", "--disable-sync", f"--user-data-dir={profile}",
                "--window-size=1400,1760"):
        options.add_argument(arg)
    driver = webdriver.Chrome(service=Service(CHROMEDRIVER), options=options)
    driver.set_script_timeout(20)
    yield driver
    driver.quit()


@pytest.fixture(scope="module")
def module_bench():
    # embedded transport, the reference TCU on the plant's frames (see the module's text)
    b = Bench.start(time_scale=TIME_SCALE, tcu_clock="bus")
    b.set("accel_pedal_pct", 30)
    yield b
    b.stop()


@pytest.fixture
def bench(module_bench):
    """The module's bench as each test finds it: no maneuver, no fault, 30 % pedal, 0 %."""
    b = module_bench
    if b.server.maneuver_playing:
        b.server.stop_maneuver()
    b.clear_all()
    b.set("brake_pedal_pct", 0)
    b.set("road_grade_pct", 0)
    b.set("accel_pedal_pct", 30)
    return b


@pytest.fixture(scope="module")
def page(module_bench, browser, tmp_path_factory):
    ui = UiServer(module_bench.server, ("127.0.0.1", 0),
                  recordings_dir=tmp_path_factory.mktemp("recordings"), log=lambda _l: None)
    ui.start()
    open_page(browser, ui.url)
    yield ui
    ui.stop()


def open_page(driver, url):
    driver.get(url)
    wait_for(lambda: driver.execute_script(
        "return window.Bokeh !== undefined && Bokeh.documents.length > 0 && "
        "Bokeh.documents[0].get_model_by_name('traces') !== null && "
        "Bokeh.documents[0].get_model_by_name('traces').data.t.length > 0"),
        "the page's traces")


def js(driver, code, *args):
    return driver.execute_script(code, *args)


def model(name):
    return f"Bokeh.documents[0].get_model_by_name({json.dumps(name)})"


def last_time(driver):
    return js(driver, f"const t = {model('traces')}.data.t; return t[t.length - 1];")


def click(driver, name):
    """A real click on the button of the Bokeh widget ``name``."""
    js(driver, f"Bokeh.index.find_one({model(name)}).shadow_el.querySelector('button').click();")


def message(driver):
    return js(driver, f"return {model('message')}.text;")


def set_value(driver, name, value):
    js(driver, f"{model(name)}.value = arguments[0];", value)


def speed_gain(bench, plant_s):
    """km/h gained over ``plant_s`` of plant time."""
    v0 = bench.read("vehicle_speed_kmh")
    bench.sleep(plant_s)
    return bench.read("vehicle_speed_kmh") - v0


# ---------------------------------------------------------------------------


def test_page_loads_from_the_bench_itself_and_traces_move(page, browser):
    scripts = js(browser, "return Array.from(document.scripts).map(s => s.src).filter(s => s);")
    assert scripts and all(s.startswith(page.url + "static/") for s in scripts), scripts
    assert js(browser, "return document.title") == "dct-hil bench"
    items = js(browser, f"return Array.from({model('instruments')}.data.label);")
    assert items[:5] == ["vehicle speed", "gear", "engine speed", "clutch K1", "clutch K2"]
    assert "TCU phase" in items
    t0 = last_time(browser)
    wait_for(lambda: last_time(browser) > t0 + 0.5, "the traces' last time to grow")
    # the page receives its traces as a stream of new buckets; how many a second is the
    # benchmark's figure (python -m dct_hil.ui.bench), printed here for whoever looks
    js(browser, f"window.__streams = 0; {model('traces')}.streaming.connect(() => "
                "{ window.__streams += 1; });")
    t_wall = time.monotonic()
    wait_for(lambda: js(browser, "return window.__streams;") >= 5, "five streamed updates")
    print(f"page updates: {js(browser, 'return window.__streams;') / (time.monotonic() - t_wall):.1f}"
          " per second")
    speed = js(browser, f"const d = {model('traces')}.data; "
                        "return d['vehicle_speed_kmh|hi'][d.t.length - 1];")
    assert speed == pytest.approx(page.server.snapshot()["plant"]["vehicle_speed_kmh"], abs=15)


def test_two_browser_sessions_at_once(page, browser):
    first = browser.current_window_handle
    browser.switch_to.new_window("tab")
    try:
        open_page(browser, page.url)
        assert page.counts["sessions_open"] >= 2
        t0 = last_time(browser)
        wait_for(lambda: last_time(browser) > t0, "the second session's traces to move")
    finally:
        browser.close()
        browser.switch_to.window(first)
    t0 = last_time(browser)
    wait_for(lambda: last_time(browser) > t0, "the first session's traces to move on")


def test_a_maneuver_started_on_the_page_drives_and_the_screenshot(page, browser, bench):
    """Start paper-cycle from the page: the loop plays it (the pedals are the
    table's), the car launches and shifts; with a fault injected on the page
    the screenshot docs/ui.png shows the bench at work; Stop ends it."""
    set_value(browser, "maneuver", "paper-cycle")
    click(browser, "maneuver_start")
    wait_for(lambda: bench.server.maneuver_playing, "the maneuver to start")
    assert bench.server.maneuver_name == "paper-cycle"
    bench.wait_until("maneuver_time_s > 1.5", timeout_s=5.0)
    assert bench.read("accel_pedal_pct") == 100.0, "the table's wide-open launch"
    bench.wait_until("gear >= 2 and vehicle_speed_kmh > 30", timeout_s=10.0)
    set_value(browser, "fault_kind", "can.late")
    set_value(browser, "fault_params", "message=SIM_Status delay_ms=5")
    click(browser, "inject")
    wait_for(lambda: len(js(browser, f"return Array.from({model('fault_rows')}.data.id);")) == 1,
             "the fault in the table")
    wait_for(lambda: "injected" in message(browser), "the page to say the fault was injected")
    wait_for(lambda: js(browser, f"return {model('fault_rows')}.data.state[0]") == "active",
             "the fault active")
    bench.sleep(1.0)                                    # the traces show the run's shifts
    os.makedirs(os.path.dirname(SCREENSHOT), exist_ok=True)
    assert browser.save_screenshot(SCREENSHOT)
    click(browser, "clear_all")
    wait_for(lambda: len(js(browser, f"return Array.from({model('fault_rows')}.data.id);")) == 0,
             "the fault cleared")
    assert bench.faults() == []
    click(browser, "maneuver_stop")
    wait_for(lambda: not bench.server.maneuver_playing, "the maneuver to stop")
    assert bench.read("accel_pedal_pct") == 0.0, "Stop releases the accelerator"


def test_grade_slider_slows_the_car(page, browser, bench):
    # whatever the TCU does meanwhile (driving at 30 % pedal, or both clutches open after a
    # diagnosis a loaded host can provoke: the car rolls), 12 % grade costs about 1.2 m/s^2
    flat = speed_gain(bench, 1.5)
    set_value(browser, "grade", 12)                 # the slider's model, as a drag sets it
    wait_for(lambda: bench.read("road_grade_pct") == 12, "the plant to take the grade")
    wait_for(lambda: "road_grade_pct = 12" in message(browser), "the page to say the grade was set")
    uphill = speed_gain(bench, 1.5)
    set_value(browser, "grade", 0)
    wait_for(lambda: bench.read("road_grade_pct") == 0, "the grade back to 0")
    # 12 % is about 1.2 m/s^2 against the car: 6 km/h less in 1.5 s
    assert uphill < flat - 3.0, f"gained {flat:.2f} km/h on the flat, {uphill:.2f} uphill"


def test_bad_input_on_the_page_is_refused_and_changes_nothing(page, browser, bench):
    before = bench.read("road_grade_pct")
    set_value(browser, "grade", 55)                  # beyond the plant's +-40 %
    wait_for(lambda: "outside" in message(browser), "the refusal on the page")
    assert "road_grade_pct" in message(browser)
    wait_for(lambda: js(browser, f"return {model('grade')}.value") == before,
             "the slider back at the plant's value")
    set_value(browser, "set_name", "no_such_input")
    set_value(browser, "set_value", "3")
    click(browser, "set_button")
    wait_for(lambda: "not a plant input" in message(browser), "the unknown input refused")
    bench.sleep(0.05)
    assert bench.read("road_grade_pct") == before


def test_recording_started_on_the_page_is_a_valid_file(page, browser, bench, tmp_path):
    from rt_loop.measure.recorder import read_recording

    set_value(browser, "rec_format", "csv")
    click(browser, "rec_start")
    started = wait_for(lambda: bench.server.recording, "the recording to start")["started_s"]
    bench.sleep(0.5)
    click(browser, "rec_stop")
    wait_for(lambda: "rec-link" in js(browser, f"return {model('rec_status')}.text;"),
             "the download link")
    status = js(browser, f"return {model('rec_status')}.text;")
    href = status.split('href="', 1)[1].split('"', 1)[0]
    assert href.startswith("/recordings/") and href.endswith(".csv")
    with urllib.request.urlopen(page.url.rstrip("/") + href, timeout=10) as r:
        body = r.read()
    path = tmp_path / "downloaded.csv"
    path.write_bytes(body)
    rec = read_recording(path)
    t = rec["time_s"]
    assert len(t) >= 20, f"{len(t)} samples"
    assert started - 0.001 <= t[0] <= started + 0.1, (started, t[:3].tolist())
    assert (t[1:] > t[:-1]).all(), t[:-1][t[1:] <= t[:-1]].tolist()
    assert page.counts["downloads"] == 1
    # only what the page recorded is served
    with pytest.raises(urllib.error.HTTPError) as e:
        urllib.request.urlopen(page.url + "recordings/..%2Fserve-stats.json", timeout=10)
    assert e.value.code == 404


class _NoRedirect(urllib.request.HTTPRedirectHandler):
    def redirect_request(self, *args, **kwargs):
        return None


def test_a_wrong_token_is_refused(module_bench, browser, tmp_path):
    bench = module_bench
    from selenium.webdriver.common.by import By

    ui = UiServer(bench.server, ("127.0.0.1", 0), token=TOKEN, recordings_dir=tmp_path,
                  log=lambda _l: None)
    ui.start()
    try:
        opener = urllib.request.build_opener(_NoRedirect)
        for path in ("", "recordings/x.csv"):
            with pytest.raises(urllib.error.HTTPError) as e:
                opener.open(ui.url + path, timeout=10)
            assert e.value.code == 302 and "/login" in e.value.headers["Location"]
        with pytest.raises(urllib.error.HTTPError) as e:
            urllib.request.urlopen(ui.url + "login", data=b"token=guess&next=%2F", timeout=10)
        assert e.value.code == 403
        browser.get(ui.url)
        assert "/login" in browser.current_url           # the page asks for the token
        browser.find_element(By.ID, "token").send_keys("not-the-token")
        browser.find_element(By.ID, "submit").click()
        wait_for(lambda: "Wrong token" in browser.find_element(By.ID, "message").text,
                 "the refusal")
        assert js(browser, "return window.Bokeh === undefined")
        assert ui.counts["refused_logins"] == 2
        browser.find_element(By.ID, "token").send_keys(TOKEN)
        browser.find_element(By.ID, "submit").click()
        wait_for(lambda: js(browser, "return window.Bokeh !== undefined && "
                                     "Bokeh.documents.length > 0"), "the page after the login")
        assert ui.counts["logins"] == 1
    finally:
        browser.delete_all_cookies()
        ui.stop()


def test_a_missing_browser_fails_with_how_to_install():
    with pytest.raises(pytest.fail.Exception) as e:
        require_browser(("/nonexistent/chromium",))
    assert "apt-get install chromium chromium-driver" in str(e.value)
