"""What the server has the loop play: maneuvers and the stimulus.

A maneuver is a pedal table (with a selector column and a fixed road grade
if it has them) the loop plays itself: one given at construction starts at
the first accepted TCU frame or at once, ``start_maneuver`` plays another
from the next tick while the loop runs, ``stop_maneuver`` ends it. The loop
takes a command at its next tick (``_maneuver_command``: publish, wait for
the acknowledgement). A stimulus (``rt_loop.measure.stimulus``) writes plant
inputs and parameters from a file on plant or maneuver time.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

from rt_loop.server.checks import (
    MAX_DRIVER_ROWS,
    STIMULUS_STARTS,
    _check_choice,
    _check_driver,
    _check_duration,
    _check_maneuver_inputs,
)
from rt_loop.server.errors import ServerError

__all__ = ["ManeuverMixin"]


class ManeuverMixin:
    """``Server``'s part that plays maneuvers and the stimulus in the loop.

    Reads the server's loop (``_ffi``, ``_lib``, ``_l``), the driver table
    checked at construction (``driver_rows``, ``driver_linear``,
    ``driver_selectors``, ``maneuver_inputs``, ``maneuver_start``,
    ``maneuver_end_s``) and ``running``; keeps the name of the maneuver
    started last (``_maneuver``) and the stimulus player (``player``).
    """

    def _configure_driver(self, d: Any) -> None:
        """The loop's driver (``rt_driver``) for the maneuver given at construction."""
        _fill_driver(d, self.driver_rows, self.driver_linear, self.driver_selectors,
                     self.maneuver_inputs)
        d.start_on_tcu = int(self.maneuver_start == "tcu")
        d.end_s = 0.0 if self.maneuver_end_s is None else self.maneuver_end_s
        if self.driver_rows:
            self._maneuver = "scripted"

    @staticmethod
    def loop_maneuvers() -> list[str]:
        """The shipped maneuvers the loop can play itself (pedal tables)."""
        from plant.driver import ScriptedDriver
        from plant.maneuvers import MANEUVERS, get_maneuver

        return [n for n in MANEUVERS if isinstance(get_maneuver(n).driver, ScriptedDriver)
                and len(get_maneuver(n).driver.table) <= MAX_DRIVER_ROWS]

    @property
    def maneuver_playing(self) -> bool:
        """A maneuver is waiting for the TCU or playing (the loop drives the pedals)."""
        state = int(self._l.stats.maneuver_state)
        return state in (int(self._lib.RT_MANEUVER_WAITING), int(self._lib.RT_MANEUVER_RUNNING))

    @property
    def maneuver_name(self) -> str | None:
        """The maneuver started last (``--maneuver`` or ``start_maneuver``), None: none."""
        return self._maneuver

    def _maneuver_command(self, op: int, fill: Callable[[Any], None] | None = None) -> None:
        lib, loop = self._lib, self._l
        if not self.running:
            raise ServerError("the loop is not running")
        seq = int(loop.maneuver_seq)
        deadline = time.monotonic() + 1.0
        while int(lib.rt_maneuver_acked(loop)) != seq:      # the last command not taken yet
            if time.monotonic() > deadline:
                raise ServerError("the loop did not take the last maneuver command (is it "
                                  "ticking?)")
            time.sleep(0.001)
        refused = int(loop.maneuver_refused)
        if fill is not None:
            fill(loop.maneuver_next)
        loop.maneuver_op = op
        seq = (seq + 1) & 0xFFFFFFFF
        lib.rt_maneuver_publish(loop, seq)
        deadline = time.monotonic() + 1.0
        while int(lib.rt_maneuver_acked(loop)) != seq and self.running:
            if time.monotonic() > deadline:
                return                    # queued: the loop takes it at its next tick
            time.sleep(0.0005)
        if int(loop.maneuver_refused) != refused:
            raise ServerError("the loop refused the maneuver command")

    def start_maneuver(self, maneuver: Any, end_s: float | None = None,
                       inputs: dict | None = None) -> None:
        """Plays a maneuver from the next tick while the loop runs: a shipped
        one by name (``loop_maneuvers``), a ``ScriptedDriver`` or rows
        (t_s, accel %, brake %[, selector]). It replaces one playing; at its end (``end_s``,
        by name its duration) the last row's pedals stay and the loop goes
        on. Pedal sets are refused while it plays. ``inputs``: its fixed plant
        inputs, set as it starts (``{"road_grade_pct": 20}``; by name the
        maneuver's own)."""
        name = None
        if isinstance(maneuver, str):
            from plant.maneuvers import get_maneuver

            if maneuver not in self.loop_maneuvers():
                raise ServerError(f"maneuver {maneuver!r}: the loop plays "
                                  + ", ".join(self.loop_maneuvers()))
            m = get_maneuver(maneuver)
            name, driver, end_s = maneuver, m.driver, (m.duration_s if end_s is None else end_s)
            inputs = m.inputs if inputs is None else inputs
        else:
            driver = maneuver
        rows, linear, selectors = _check_driver(driver)
        fixed = _check_maneuver_inputs(inputs)
        end = 0.0 if end_s is None else _check_duration(end_s)

        def fill(d: Any) -> None:
            _fill_driver(d, rows, linear, selectors, fixed)
            d.start_on_tcu = 0
            d.end_s = end
            d.keep_running = 1

        # named before it is published: a reader that sees it playing sees its name
        before, self._maneuver = self._maneuver, name or "table"
        try:
            self._maneuver_command(int(self._lib.RT_MCMD_START), fill)
        except BaseException:
            self._maneuver = before
            raise

    def reset_plant(self) -> None:
        """Puts the plant back at rest as it starts, at the next tick: standing,
        the engine idling (a stalled one runs again), every sleeve in neutral,
        the clutches open, the initial temperatures; plant time goes on and the
        inputs stay as they are. For a bench that stays up between tests
        (``dct_hil.bench.Bench.reset``), with the TCU's ignition cycled after."""
        self._maneuver_command(int(self._lib.RT_MCMD_RESET_PLANT))

    def stop_maneuver(self) -> None:
        """Ends the maneuver playing (the accelerator released, the brake as
        it was); nothing when none plays."""
        self._maneuver_command(int(self._lib.RT_MCMD_STOP))

    def _load_stimulus(self, path: Any, start: str) -> Any:
        if path is None:
            return None
        _check_choice(start, STIMULUS_STARTS, "stimulus start")
        if start == "maneuver" and not self.driver_rows:
            raise ServerError("a stimulus started with the maneuver needs a maneuver")
        from rt_loop.measure.stimulus import (
            StimulusError,
            load_stimulus,
            plant_inputs_writable,
            writable_of_regions,
        )
        from rt_loop.measure.xcp import a2l as _a2l

        ffi, lib = self._ffi, self._lib
        writable = {**writable_of_regions(_a2l.calibration_regions(ffi, lib)),
                    **plant_inputs_writable(ffi)}
        try:
            return load_stimulus(path, writable)
        except StimulusError as e:
            raise ServerError(str(e)) from None

    def _start_player(self) -> None:
        if self.stimulus is None:
            return
        from rt_loop.measure.stimulus import StimulusPlayer

        self.player = StimulusPlayer(self.stimulus, self._ffi, self._lib, self._l,
                                     start=self.stimulus_start,
                                     t0_s=0.0 if self.stimulus_start == "plant" else None)
        self.player.start()

    def _stop_player(self) -> None:
        if self.player is not None:
            self.player.stop()


def _fill_driver(d: Any, rows: list, linear: bool, selectors: list | None, inputs: dict) -> None:
    """An rt_driver's table, selector column and fixed grade (its timing fields stay)."""
    d.rows = len(rows)
    for i, (t, accel, brake) in enumerate(rows):
        d.t_s[i], d.accel_pedal_pct[i], d.brake_pedal_pct[i] = t, accel, brake
    d.linear = int(linear)
    d.has_selector = int(selectors is not None)
    for i, code in enumerate(selectors or ()):
        d.selector_lever[i] = code
    grade = inputs.get("road_grade_pct")
    d.has_grade = int(grade is not None)
    d.road_grade_pct = 0.0 if grade is None else grade

