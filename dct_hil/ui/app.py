"""The bench view's Bokeh document: one per browser session.

Panels:

1. traces: any traceable names (``rt_loop.measure.scope``: plant outputs, inputs,
   received values, CAN signals, the loop's times), each a band from min to
   max of every tick plus a line through the middle, 20 updates a second;
   pause (the data stays), zoom and pan (Bokeh's tools; the time axis
   follows the newest data until the user zooms, Reset follows again);
2. instruments: vehicle speed, gear, engine speed, clutch pressures, the
   TCU's phase (``TCU_Status.TcuPhase`` when the mapping has it), the
   maneuver and the loop's state;
3. timing: turnaround, execution and wake-up latency histograms (1 us bins
   of ``rt_stats``), p50/p99/p99.9/max, overruns, the latency against the
   period;
4. bus: a row per CAN message: rate against its cycle, accepted, rejected
   by reason, timeouts, timed out now;
5. controls: maneuver start/stop, sliders for the road grade and (while no
   maneuver plays) the pedals, any input by name, fault injection and
   clearing, a recording started and stopped here and offered for download.

The page reads the loop only through lock-free readers: a ``StatsReader``
of the UI's own (its one thread is the Bokeh server's), ``server.scope``
and ``server.faults``. Every write (set, inject, clear) goes through a
``rt_loop.control.ControlServer`` request handler without a socket, so the
page and the control channel refuse bad input with the same one line.

``Hub`` (one per ``UiServer``) reads the loop at most every 40 ms and
shapes what every session shows; each session's periodic callback (50 ms)
takes the hub's figures and streams only its traces' new buckets.
"""

from __future__ import annotations

import html
import math
import os
import time
from typing import Any

import numpy as np

from dct_hil.ui import figures as fg

#: each session's update period (ms): 20 updates a second
UPDATE_MS = 50
#: the hub reads the loop at most this often (s)
FAST_S = 0.04
#: timing, bus and fault tables (s)
SLOW_S = 0.5
#: the bus table's rates are measured over at least this long (s)
RATE_S = 1.0
#: a display bucket of the traces (plant s): min/max of the scope's buckets
DISPLAY_BUCKET_S = 0.02
#: plant seconds of traces kept in the browser and the part shown while following
KEEP_S = 120.0
FOLLOW_S = 30.0
DEFAULT_TRACES = ("vehicle_speed_kmh", "engine_speed_rpm", "clutch1_pressure_bar",
                  "clutch2_pressure_bar")
#: traces one session may show at once
MAX_SESSION_TRACES = 8
PLAYING = ("waiting for the TCU", "running")

#: the style sheet of the page's Divs (each Div renders in a shadow root of its own)
_CSS = """
.msg{font-family:sans-serif;font-size:13px;white-space:nowrap;overflow:hidden}
.msg .ok{color:#0a6b2d}.msg .err{color:#b00020;font-weight:600}
.head{font-family:sans-serif}
a.rec-link{font-family:monospace}
"""


class Hub:
    """What every session shows, read from the loop once per ``FAST_S`` /
    ``SLOW_S`` (used only in the UI's thread)."""

    def __init__(self, ui: Any) -> None:
        from rt_loop.control import ControlServer
        from rt_loop.stats import StatsReader

        self.ui = ui
        s = self.server = ui.server
        self.reader = StatsReader(s._ffi, s._lib, s._l, s.channels)
        #: every write of the page goes through this handler (no socket)
        self.control = ControlServer(s, None)
        self.messages = fg.message_info(s.channels)
        self._hist = {key: np.frombuffer(s._ffi.buffer(getattr(self.reader.copy, field)),
                                         dtype=np.uint64)
                      for key, field in (("turnaround", "turnaround_hist"),
                                         ("execution", "exec_hist"),
                                         ("wakeup_latency", "latency_hist"))}
        names = s.faults.names
        key = next((k for k in names.signals if k.split(":")[-1] == "TCU_Status.TcuPhase"), None)
        self.phase_index = None if key is None else names.signals[key][2]
        sig = None if key is None else names.signals[key][3]
        self.phase_choices = ({int(k): str(v) for k, v in (sig.choices or {}).items()}
                              if sig is not None else {})
        self.writable = self.control.writable
        self.fast: dict = {}
        self.slow: dict = {}
        self._t_fast = self._t_slow = -math.inf
        self._frames: dict | None = None
        self._t_frames = 0.0
        self.reads = 0

    # ------------------------------------------------------------ reading
    def refresh(self) -> dict:
        """The fast figures (instruments, state), read again when older than FAST_S."""
        now = time.monotonic()
        if self.ui.frozen and self.fast:
            if self.fast["running"]:        # the last figures stay; the controls go off
                self.fast = {**self.fast, "running": False}
            return self.fast
        if now - self._t_fast < FAST_S and self.fast:
            return self.fast
        self._t_fast = now
        s = self.reader.read()
        self.reads += 1
        o = s.outputs
        state = self.reader.state
        mstate = {0: "none", 1: "waiting for the TCU", 2: "running", 3: "done"}.get(
            int(s.maneuver_state), "?")
        mt = float(s.maneuver_time_s)
        phase = None
        if self.phase_index is not None:
            phase = float(self.server._l.signal_values[self.phase_index])
            if not math.isfinite(phase):      # no TCU frame yet
                phase = None
        values = {
            "vehicle_speed_kmh": float(o.vehicle_speed_kmh), "gear": float(o.gear),
            "engine_speed_rpm": float(o.engine_speed_rpm),
            "clutch1_pressure_bar": float(o.clutch1_pressure_bar),
            "clutch2_pressure_bar": float(o.clutch2_pressure_bar),
            "tcu_phase": phase, "tcu_phase_known": self.phase_index is not None,
            "tcu_phase_choices": self.phase_choices,
            "maneuver": mstate, "maneuver_time_s": mt if mt >= 0 else None,
            "maneuver_name": getattr(self.server, "maneuver_name", None),
            "state": state if not self.ui.frozen else f"{state} (page frozen)",
            "sim_time_s": float(s.sim_time_s),
        }
        self.fast = {
            "items": fg.instrument_items(values),
            "values": values,
            "state": state,
            "running": bool(self.server.running) and not self.ui.frozen,
            "maneuver": mstate,
            "inputs": {"road_grade_pct": float(o.road_grade_pct),
                       "accel_pedal_pct": float(o.accel_pedal_pct),
                       "brake_pedal_pct": float(o.brake_pedal_pct)},
        }
        return self.fast

    def refresh_slow(self) -> dict:
        """Timing, bus and fault tables, read again when older than SLOW_S."""
        now = time.monotonic()
        if (self.ui.frozen and self.slow) or (now - self._t_slow < SLOW_S and self.slow):
            return self.slow
        self.refresh()
        self._t_slow = now
        s = self.reader.copy
        timing = self.reader.timing()
        counts = self.reader.counts()
        server = self.server
        if self._frames is None or now - self._t_frames >= RATE_S:
            cols, frames = fg.bus_rows(self.messages, counts, self._frames,
                                       now - self._t_frames, server.time_scale)
            self._frames, self._t_frames = frames, now
            self._bus = cols
        else:                           # counts now, the rates of the last interval
            cols, _ = fg.bus_rows(self.messages, counts, None, 0.0, server.time_scale)
            cols["rate_hz"] = self._bus["rate_hz"]
            cols["state"] = [old if new not in ("TIMED OUT", "none yet", "optional, none yet")
                             else new for old, new in zip(self._bus["state"], cols["state"])]
        faults = server.faults.status(s)
        rec = getattr(server, "recording", None)
        self.slow = {
            "timing": fg.timing_table(timing),
            "lines": fg.timing_lines(timing, counts, server.period_s * 1e6, server.spin_us),
            "hist": {k: fg.histogram_view(h) for k, h in self._hist.items()},
            "period_us": server.period_s * 1e6,
            "bus": cols,
            "faults": fg.fault_rows(faults),
            "recording": rec,
        }
        return self.slow

    # ------------------------------------------------------------ writing
    def request(self, request: dict) -> dict:
        """One write through the control channel's handler (refused while the
        loop does not run or the page is frozen)."""
        if self.ui.frozen:
            return {"ok": False, "error": "the loop has stopped: the page shows its last figures"}
        if not self.server.running:
            return {"ok": False, "error": "the loop is not running"}
        return self.control.handle(request)


# --------------------------------------------------------------------------
# one session
# --------------------------------------------------------------------------

def make_document(doc: Any, ui: Any) -> None:
    """Bokeh's application function: builds one session's page."""
    BenchView(doc, ui)


class BenchView:
    """One browser session's document and its periodic update."""

    def __init__(self, doc: Any, ui: Any) -> None:
        from bokeh.layouts import column, row
        from bokeh.models import (
            Button,
            ColumnDataSource,
            DataRange1d,
            DataTable,
            InlineStyleSheet,
            MultiChoice,
            Range1d,
            Select,
            Slider,
            Span,
            TableColumn,
            TextInput,
            Toggle,
        )
        from bokeh.models import Div as _Div
        from bokeh.plotting import figure

        from rt_loop.faults import KINDS

        self.doc, self.ui, self.hub = doc, ui, ui.hub
        self.server = ui.server
        self._figure, self._CDS = figure, ColumnDataSource
        self._closed = False
        self._syncing = False
        self._n = 0
        self._table_seq = 0
        self.updates = 0
        ui.counts["sessions"] += 1
        ui.counts["sessions_open"] += 1
        ui.views.add(self)
        doc.title = ui.title
        sheet = InlineStyleSheet(css=_CSS)

        def Div(**kw: Any) -> Any:  # every Div with the page's style sheet
            return _Div(stylesheets=[sheet], **kw)

        # ---- header and the one-line message
        s = self.server
        where = f"{s.channel}" + (f" ({s.transport.interface})" if s.transport is not None else "")
        self.header = Div(text=f'<h3 class="head" style="margin:2px 0">{html.escape(ui.title)}'
                          f' <small style="color:#667">{html.escape(where)}, '
                          f'{s.rate_hz:g} Hz</small></h3>', name="header")
        self.message = Div(text='<div class="msg"><span class="ok">ready</span></div>',
                           name="message", sizing_mode="stretch_width")

        # ---- instruments
        fast = self.hub.refresh()
        self.instruments = self._instrument_panel(fast["items"])

        # ---- traces
        self.scope = None
        self.traced: list[str] = []
        self.last_tick: int | None = None
        self.merger: fg.MinMaxMerger | None = None
        self.trace_figs: dict[str, Any] = {}
        #: every trace's columns in one source (one stream per update)
        self.trace_src = ColumnDataSource({"t": []}, name="traces")
        self.streams = 0
        self.x_range = DataRange1d(follow="end", follow_interval=FOLLOW_S, range_padding=0,
                                   name="trace_x")
        self.picker = MultiChoice(title="traces (plant outputs, inputs.*, cmd.*, Message.Signal, "
                                  "loop times)", options=[], value=[], name="picker",
                                  sizing_mode="stretch_width", disabled=True,
                                  placeholder="waiting for the loop to start")
        self.pause = Toggle(label="Pause", name="pause", width=90, button_type="default")
        self.pause.on_change("active", self._on_pause)
        self.picker.on_change("value", self._on_pick)
        self.traces_box = column(sizing_mode="stretch_width", name="trace_box")
        traces_panel = column(row(self.picker, self.pause, sizing_mode="stretch_width"),
                              self.traces_box, sizing_mode="stretch_width")

        # ---- controls
        names = s.loop_maneuvers() if hasattr(s, "loop_maneuvers") else []
        self.maneuver = Select(title="maneuver", options=names, value=names[0] if names else "",
                               name="maneuver", width=150)
        self.m_start = Button(label="Start", name="maneuver_start", button_type="success",
                              width=70)
        self.m_stop = Button(label="Stop", name="maneuver_stop", width=70)
        self.m_start.on_click(self._start_maneuver)
        self.m_stop.on_click(self._stop_maneuver)
        w = self.hub.writable
        grade_lo, grade_hi = w.get("override.road_grade_pct", (0, 8, -40.0, 40.0))[2:]
        self.grade = Slider(title="road grade (%)", start=max(grade_lo, -20.0),
                            end=min(grade_hi, 20.0), step=0.5,
                            value=round(fast["inputs"]["road_grade_pct"] * 2) / 2,
                            name="grade", width=330)
        self.accel = Slider(title="accelerator pedal (%)", start=0, end=100, step=1,
                            value=fast["inputs"]["accel_pedal_pct"], name="accel", width=330)
        self.brake = Slider(title="brake pedal (%)", start=0, end=100, step=1,
                            value=fast["inputs"]["brake_pedal_pct"], name="brake", width=330)
        for slider, input_name in ((self.grade, "road_grade_pct"),
                                   (self.accel, "accel_pedal_pct"),
                                   (self.brake, "brake_pedal_pct")):
            slider.on_change("value", self._slider_handler(input_name))
        self.set_name = TextInput(title="set an input", placeholder="engine_on, params.<name>",
                                  name="set_name", width=150)
        self.set_value = TextInput(title="value", name="set_value", width=90)
        self.set_button = Button(label="Set", name="set_button", width=60)
        self.set_button.on_click(self._set_any)
        kinds = list(KINDS)
        self.fault_kind = Select(title="fault", options=kinds, value="can.omit",
                                 name="fault_kind", width=200)
        self.fault_params = TextInput(title="target, parameters, schedule (NAME=VALUE ... or JSON)",
                                      placeholder="message=VEH_Driver duration_s=2",
                                      name="fault_params", width=330)
        self.fault_help = Div(text=self._kind_help("can.omit"), name="fault_help", width=330)
        self.fault_kind.on_change("value", lambda _a, _o, new: setattr(
            self.fault_help, "text", self._kind_help(new)))
        self.inject = Button(label="Inject", name="inject", button_type="warning", width=80)
        self.inject.on_click(self._inject)
        self.fault_src = ColumnDataSource(fg.fault_rows([]), name="fault_rows")
        self.fault_table = DataTable(
            source=self.fault_src, name="faults", width=330, height=120, index_position=None,
            columns=[TableColumn(field="id", title="id", width=30),
                     TableColumn(field="kind", title="kind", width=110),
                     TableColumn(field="target", title="target", width=110),
                     TableColumn(field="state", title="state", width=50),
                     TableColumn(field="started_s", title="start", width=50),
                     TableColumn(field="hits", title="hits", width=40)])
        self.clear = Button(label="Clear selected", name="clear", width=110)
        self.clear_all = Button(label="Clear all", name="clear_all", width=80)
        self.clear.on_click(self._clear)
        self.clear_all.on_click(self._clear_all)
        self.rec_format = Select(title="recording", options=["mf4", "csv"], value="mf4",
                                 name="rec_format", width=80)
        self.rec_start = Button(label="Start recording", name="rec_start", button_type="success",
                                width=120)
        self.rec_stop = Button(label="Stop", name="rec_stop", width=60)
        self.rec_start.on_click(self._start_recording)
        self.rec_stop.on_click(self._stop_recording)
        self.rec_status = Div(text="", name="rec_status", width=330)
        controls = column(
            Div(text="<b>Controls</b>"),
            row(self.maneuver, column(Div(text=""), row(self.m_start, self.m_stop))),
            self.grade, self.accel, self.brake,
            row(self.set_name, self.set_value, column(Div(text=""), self.set_button)),
            self.fault_kind, self.fault_params, self.fault_help,
            row(self.inject, self.clear, self.clear_all),
            self.fault_table,
            row(self.rec_format, column(Div(text=""), row(self.rec_start, self.rec_stop))),
            self.rec_status, width=350, name="controls")

        # ---- timing
        self.hist_src: dict[str, Any] = {}
        self.hist_x: dict[str, Any] = {}
        hist_figs = []
        for key, label in (("turnaround", "turnaround (us)"), ("execution", "execution (us)"),
                           ("wakeup_latency", "wake-up latency (us)")):
            src = ColumnDataSource({"left": [], "right": [], "count": [], "bottom": []},
                                   name=f"hist:{key}")
            p = figure(height=180, width=300, title=label, y_axis_type="log",
                       tools="xpan,xwheel_zoom,box_zoom,reset", toolbar_location="above",
                       y_range=DataRange1d(start=0.5), x_range=Range1d(0, 20),
                       name=f"hist_fig:{key}")
            p.quad(left="left", right="right", top="count", bottom="bottom", source=src,
                   fill_color="#4a78b5", line_color=None)
            if key != "execution":
                p.add_layout(Span(location=s.period_s * 1e6, dimension="height",
                                  line_color="#b00020", line_dash="dashed", line_width=1))
            p.yaxis.axis_label = "ticks"
            p.toolbar.logo = None
            self.hist_src[key] = src
            self.hist_x[key] = p.x_range
            hist_figs.append(p)
        self.timing_src = ColumnDataSource(fg.timing_table({}), name="timing_rows")
        self.timing_table = DataTable(
            source=self.timing_src, name="timing", width=480, height=110, index_position=None,
            columns=[TableColumn(field="time", title="us", width=120),
                     TableColumn(field="p50", title="p50", width=60),
                     TableColumn(field="p99", title="p99", width=60),
                     TableColumn(field="p99_9", title="p99.9", width=60),
                     TableColumn(field="max", title="max", width=70),
                     TableColumn(field="samples", title="ticks", width=80)])
        self.notes_src = ColumnDataSource({"text": []}, name="timing_notes")
        self.timing_lines = DataTable(source=self.notes_src, name="timing_lines", width=560,
                                      height=110, index_position=None, header_row=False,
                                      columns=[TableColumn(field="text", title="", width=560)])
        timing_panel = column(Div(text="<b>Timing</b> (1 us bins; dashed: the period)"),
                              row(*hist_figs), row(self.timing_table, self.timing_lines),
                              name="timing_panel")

        # ---- bus
        self.bus_src = ColumnDataSource(fg.bus_rows(self.hub.messages, {}, None, 0.0)[0],
                                        name="bus_rows")
        bus_cols = [("message", "message", 130), ("dir", "dir", 70), ("cycle_ms", "cycle ms", 60),
                    ("expected_hz", "cycle Hz", 60), ("rate_hz", "rate Hz", 60),
                    ("frames", "accepted/sent", 90), ("bad_length", "bad len", 55),
                    ("bad_crc", "bad CRC", 55), ("bad_counter", "bad ctr", 55),
                    ("timeouts", "timeouts", 60), ("timed_out", "timed out", 65),
                    ("dropped", "dropped", 55), ("state", "state", 90)]
        if len(s.channels.buses) > 1:
            bus_cols.insert(1, ("bus", "bus", 70))
        self.bus_table = DataTable(
            source=self.bus_src, name="bus", index_position=None, width=1000,
            height=32 + 25 * max(2, len(self.hub.messages)),
            columns=[TableColumn(field=f, title=t, width=wd) for f, t, wd in bus_cols])
        bus_panel = column(Div(text="<b>Bus</b> (rates over the last second)"), self.bus_table,
                           name="bus_panel")

        layout = column(
            row(self.header, self.message, sizing_mode="stretch_width"),
            self.instruments,
            row(traces_panel, controls, sizing_mode="stretch_width"),
            timing_panel, bus_panel, sizing_mode="stretch_width", name="page")
        doc.add_root(layout)
        self._update_slow()
        self._setup_scope()
        doc.add_periodic_callback(self.update, UPDATE_MS)
        doc.on_session_destroyed(self._destroyed)

    # ------------------------------------------------------------ helpers
    def say(self, text: str, ok: bool = True) -> None:
        cls = "ok" if ok else "err"
        self.message.text = (f'<div class="msg"><span class="{cls}">'
                             f"{html.escape(' '.join(str(text).split()))}</span></div>")

    def _kind_help(self, kind: str) -> str:
        from rt_loop.faults import KINDS

        k = KINDS.get(kind)
        if k is None:
            return ""
        target = {"message": "message=<a message the plant sends>",
                  "signal": "signal=Message.Signal", "bus": "bus=<name> (optional)",
                  "clutch": "clutch=1|2", "sleeve": "sleeve=1-3|2-4|5-R|6-N"}.get(k.needs, "")
        params = " ".join(f"{p.name}=<{p.unit}>" for p in k.params)
        return (f'<small>{html.escape(k.text)}<br><code>{html.escape((target + " " + params).strip())}'
                "</code> [start_s= when= duration_s=]</small>")

    def _reply(self, reply: dict, done: str) -> bool:
        if reply.get("ok"):
            self.say(done)
            return True
        self.say(reply.get("error", "refused"), ok=False)
        return False

    def _instrument_panel(self, items: list) -> Any:
        """The instrument row: one canvas of boxes whose values are a source's
        column (a Div's new text would lay the whole page out again, 20 times a
        second; a source's new values redraw only this canvas)."""
        from bokeh.models import Range1d

        weights = {"gear": 0.6, "maneuver": 1.7, "loop": 1.6, "phase": 1.3}
        x, w = [], []
        left = 0.0
        for key, _, _ in items:
            width = weights.get(key, 1.0)
            x.append(left)
            w.append(width)
            left += width
        self.inst_src = self._CDS({
            "key": [k for k, _, _ in items], "label": [lab for _, lab, _ in items],
            "value": [v for _, _, v in items], "left": x,
            "right": [a + b - 0.06 for a, b in zip(x, w)],
            "lx": [a + 0.06 for a in x]}, name="instruments")
        p = self._figure(height=62, sizing_mode="stretch_width", x_range=Range1d(0, left),
                         y_range=Range1d(0, 1), toolbar_location=None, tools="",
                         name="instrument_panel", min_border=0, outline_line_color=None)
        p.quad(left="left", right="right", bottom=0.04, top=0.96, source=self.inst_src,
               fill_color="#f7f8fb", line_color="#ccccdd")
        p.text(x="lx", y=0.86, text="label", source=self.inst_src, text_font_size="11px",
               text_color="#666677", text_baseline="top")
        p.text(x="lx", y=0.12, text="value", source=self.inst_src, text_font_size="18px",
               text_font_style="bold", text_color="#112233", text_baseline="bottom")
        p.axis.visible = False
        p.grid.visible = False
        return p

    # ------------------------------------------------------------ traces
    def _setup_scope(self) -> None:
        """Once the loop's scope exists: the picker's names and the default traces."""
        scope = getattr(self.server, "scope", None)
        if scope is None or self.scope is not None:
            return
        self.scope = scope
        names = scope.traceable()
        self.group_ticks = max(1, int(round(DISPLAY_BUCKET_S / scope.bucket_s))) * \
            int(scope.bucket_ticks)
        self.rollover = int(KEEP_S / (self.group_ticks * self.server.step_s))
        self._syncing = True
        try:
            self.picker.options = names
            self.picker.disabled = False
            self.picker.placeholder = "add a trace"
            wanted = [n for n in DEFAULT_TRACES if n in names]
            self.picker.value = wanted
        finally:
            self._syncing = False
        try:
            self._retrace(wanted)
        except Exception as e:  # e.g. 32 values traced by other pages
            self.say(str(e), ok=False)
            self._set_picker([])

    def _on_pick(self, _attr: str, old: list, new: list) -> None:
        if self._syncing or self.scope is None:
            return
        if len(new) > MAX_SESSION_TRACES:
            self.say(f"at most {MAX_SESSION_TRACES} traces on one page", ok=False)
            self._set_picker(old)
            return
        try:
            self._retrace(list(new))
        except Exception as e:  # ScopeError and the like: one line, old set kept
            self.say(str(e), ok=False)
            self._set_picker(self.traced)

    def _set_picker(self, value: list) -> None:
        self._syncing = True
        try:
            self.picker.value = list(value)
        finally:
            self._syncing = False

    def _retrace(self, names: list[str]) -> None:
        """Traces ``names``: the scope's counts, one figure each over one source
        (one stream per update, whatever the number of traces), the history kept."""
        scope = self.scope
        added = [n for n in names if n not in self.traced]
        removed = [n for n in self.traced if n not in names]
        if added:
            scope.add(added)                       # ScopeError: nothing changed
        if removed:
            scope.remove(removed)
        self.traced = list(names)
        for n in removed:
            self.trace_figs.pop(n, None)
        # the history of every trace again, then new buckets only
        self.merger = fg.MinMaxMerger(self.group_ticks)
        self.last_tick = None
        self._stream(replace=True)
        for n in added:
            self.trace_figs[n] = self._trace_figure(n)
        self.traces_box.children = [self.trace_figs[n] for n in self.traced]

    def _trace_figure(self, name: str) -> Any:
        src = self.trace_src
        p = self._figure(height=150, sizing_mode="stretch_width", x_range=self.x_range,
                         title=name, tools="xpan,xwheel_zoom,box_zoom,reset,save",
                         active_scroll=None, toolbar_location="right", name=f"trace_fig:{name}",
                         min_border_left=60)
        p.varea(x="t", y1=f"{name}|lo", y2=f"{name}|hi", source=src, fill_color="#4a78b5",
                fill_alpha=0.35)
        p.line(x="t", y=f"{name}|mid", source=src, line_color="#1b3d6e", line_width=1)
        p.toolbar.logo = None
        p.xaxis.axis_label = "plant time (s)"
        return p

    def _stream(self, replace: bool = False) -> None:
        """The new buckets of every trace (``replace``: the whole history) into
        the traces' one source: columns t and <name>|lo, <name>|hi, <name>|mid."""
        if self.scope is None:
            return
        if not self.traced:
            if replace:
                self.trace_src.data = {"t": []}
            return
        d = self.scope.read(self.traced, since_tick=self.last_tick)
        if len(d["tick"]) == 0 and not replace:
            return
        if len(d["tick"]):
            self.last_tick = int(d["tick"][-1])
        out = self.merger.feed(d["tick"], d["time_s"], d["min"], d["max"])
        t = out["t"]
        data = {"t": t}
        for name in self.traced:
            lo, hi = out["min"][name], out["max"][name]
            data[f"{name}|lo"], data[f"{name}|hi"] = lo, hi
            data[f"{name}|mid"] = (lo + hi) / 2.0
        if replace:                        # from the first bucket any trace has a value in
            seen = np.zeros(len(t), dtype=bool)
            for name in self.traced:
                seen |= np.isfinite(out["min"][name])
            first = int(np.argmax(seen)) if seen.any() else len(t)
            self.trace_src.data = {k: v[first:][-self.rollover:] for k, v in data.items()}
        elif len(t):
            self.trace_src.stream(data, rollover=self.rollover)
        self.streams += 1

    def _on_pause(self, _attr: str, _old: bool, new: bool) -> None:
        self.pause.label = "Paused: resume" if new else "Pause"
        self.pause.button_type = "warning" if new else "default"

    # ------------------------------------------------------------ update
    def update(self) -> None:
        """Every UPDATE_MS: instruments, new trace buckets; every SLOW_S the tables."""
        if self._closed:
            return
        self._n += 1
        self.updates += 1
        fast = self.hub.refresh()
        values = [text for _, _, text in fast["items"]]
        if list(self.inst_src.data["value"]) != values:
            self.inst_src.data["value"] = values
        if self.scope is None:
            self._setup_scope()
        elif not self.pause.active and not self.ui.frozen:
            self._stream()
        if self._n % max(1, int(SLOW_S * 1000 / UPDATE_MS)) == 0:
            self._update_slow()

    def _update_slow(self) -> None:
        slow = self.hub.refresh_slow()
        fast = self.hub.fast
        for key, src in self.hist_src.items():
            h = slow["hist"][key]
            if list(src.data["left"]) != h["left"] or list(src.data["count"]) != h["count"]:
                src.data = {"left": h["left"], "right": h["right"], "count": h["count"],
                            "bottom": [0.5] * len(h["left"])}
                end = max([20.0, *h["right"]]) * 1.02
                if self.hist_x[key].end != end:      # the x axis follows the extent of the data
                    self.hist_x[key].end = end
        self._table(self.timing_table, slow["timing"])
        self._table(self.timing_lines, {"text": slow["lines"]})
        self._table(self.bus_table, slow["bus"])
        self._table(self.fault_table, slow["faults"])
        running = fast["running"]
        playing = fast["maneuver"] in PLAYING
        self._syncing = True
        try:
            for slider, key in ((self.accel, "accel_pedal_pct"), (self.brake, "brake_pedal_pct")):
                slider.disabled = playing or not running
                if playing:                   # show what the maneuver plays
                    slider.value = round(fast["inputs"][key])
            self.grade.disabled = not running
        finally:
            self._syncing = False
        for w in (self.m_start, self.maneuver, self.set_button, self.inject, self.clear,
                  self.clear_all):
            w.disabled = not running
        self.m_stop.disabled = not (running and playing)
        rec = slow["recording"]
        ours = self.ui.recording_path
        self.rec_start.disabled = not running or rec is not None
        self.rec_stop.disabled = ours is None
        text = ""
        if rec is not None:
            text = (f"recording {html.escape(os.path.basename(rec['path']))} since "
                    f"{float(rec.get('started_s') or 0):.2f} s"
                    + ("" if ours else " (not started on this page)"))
        done = list(self.ui.recorded)[-3:]
        if done:
            links = ", ".join(f'<a href="/recordings/{html.escape(n)}" download '
                              f'class="rec-link">{html.escape(n)}</a>' for n in reversed(done))
            text = (text + "<br>" if text else "") + f"download: {links}"
        if self.rec_status.text != text:
            self.rec_status.text = text

    def _table(self, table: Any, data: dict) -> None:
        """New rows for a table. BokehJS redraws a DataTable when its view's
        indices change, not when as many rows get new values: the view's tags
        are touched too (a change event of a few bytes)."""
        src = table.source
        if {k: list(v) for k, v in src.data.items()} == data:
            return
        src.data = data
        self._table_seq += 1
        table.view.tags = [self._table_seq]

    # ------------------------------------------------------------ controls
    def _slider_handler(self, name: str) -> Any:
        def changed(_attr: str, old: float, new: float) -> None:
            if self._syncing:
                return
            reply = self.hub.request({"op": "set", "name": name, "value": float(new)})
            if not self._reply(reply, f"{name} = {new:g}"):
                self._syncing = True
                try:
                    getattr(self, {"road_grade_pct": "grade", "accel_pedal_pct": "accel",
                                   "brake_pedal_pct": "brake"}[name]).value = old
                finally:
                    self._syncing = False
        return changed

    def _set_any(self) -> None:
        name = self.set_name.value.strip()
        raw = self.set_value.value.strip()
        value = fg.parse_value(raw) if raw else None
        request = {"op": "set", "name": name}
        if value is not None:
            request["value"] = value
        self._reply(self.hub.request(request), f"{name} = {raw}")

    def _inject(self) -> None:
        try:
            spec = fg.fault_spec(self.fault_kind.value, self.fault_params.value)
        except ValueError as e:
            self.say(str(e), ok=False)
            return
        reply = self.hub.request({"op": "inject", "spec": spec})
        if self._reply(reply, f"fault {reply.get('id')}: {spec['kind']} injected"):
            self.hub._t_slow = -math.inf
            self._update_slow()

    def _clear(self) -> None:
        rows = list(self.fault_src.selected.indices)
        ids = [self.fault_src.data["id"][i] for i in rows if i < len(self.fault_src.data["id"])]
        if not ids:
            self.say("select the faults to clear in the table", ok=False)
            return
        for fid in ids:
            if not self._reply(self.hub.request({"op": "clear", "id": int(fid)}),
                               f"fault {fid} cleared"):
                break
        self.fault_src.selected.indices = []
        self.hub._t_slow = -math.inf
        self._update_slow()

    def _clear_all(self) -> None:
        if self._reply(self.hub.request({"op": "clear_all"}), "every fault cleared"):
            self.hub._t_slow = -math.inf
            self._update_slow()

    def _guarded(self, what: str, fn: Any) -> tuple[bool, Any]:
        """(True, fn()) or (False, None) with the one line shown."""
        if self.ui.frozen or not self.server.running:
            self.say(f"{what}: the loop is not running", ok=False)
            return False, None
        try:
            return True, fn()
        except Exception as e:  # ServerError and the like: one line
            self.say(f"{what}: {e}", ok=False)
            return False, None

    def _start_maneuver(self) -> None:
        name = self.maneuver.value
        if self._guarded("maneuver", lambda: self.server.start_maneuver(name))[0]:
            self.say(f"maneuver {name} started")

    def _stop_maneuver(self) -> None:
        if self._guarded("maneuver", self.server.stop_maneuver)[0]:
            self.say("maneuver stopped")

    def _start_recording(self) -> None:
        if self.ui.recording_path is not None:
            self.say("a recording of this page runs already", ok=False)
            return
        folder = self.ui.recordings_dir
        path = os.path.join(folder, f"bench-{time.strftime('%Y%m%d-%H%M%S')}."
                                    f"{self.rec_format.value}")

        def start() -> str:
            os.makedirs(folder, exist_ok=True)
            return self.server.start_recording(path, every_s=0.01)

        if self._guarded("recording", start)[0]:
            self.ui.recording_path = path
            self.say(f"recording {os.path.basename(path)}")
            self.hub._t_slow = -math.inf
            self._update_slow()

    def _stop_recording(self) -> None:
        if self.ui.recording_path is None:
            self.say("no recording of this page runs", ok=False)
            return
        path = self.ui.finish_recording()
        if path is None:
            self.say("the recording could not be finalised", ok=False)
        else:
            self.say(f"recording {os.path.basename(path)} written")
        self.hub._t_slow = -math.inf
        self._update_slow()

    # ------------------------------------------------------------ end
    def _destroyed(self, _ctx: Any) -> None:
        """The session ends (its browser went away, or the UI stops): its traces released."""
        if self._closed:
            return
        self._closed = True
        self.ui.views.discard(self)
        self.ui.counts["sessions_open"] -= 1
        if self.scope is not None and self.traced:
            try:
                self.scope.remove(self.traced)
            except Exception:  # the scope may be stopped already
                pass
        self.traced = []
