"""The server's doors for other programs while the loop runs: the XCP slave
and the control socket.

The XCP slave (``rt_loop.measure.xcp``) serves the loop's memory to an XCP
master: measurement (DAQ), calibration of the writable regions, and the A2L
of this loop on GET_ID. The control socket (``rt_loop.control``) serves
JSON-line requests: read values, set plant inputs, inject and clear faults,
watch conditions, stop. Both push calibration writes under ``cal_lock``.
"""

from __future__ import annotations

from rt_loop.drain import one_line as _one_line
from rt_loop.server.errors import ServerError

__all__ = ["RemoteAccessMixin"]


class RemoteAccessMixin:
    """``Server``'s part that opens and closes the XCP slave (``xcp``) and the
    control socket (``control``).

    Reads the server's loop (``_ffi``, ``_lib``, ``_l``), its ``channels``,
    the calibration regions set at start (``_regions``), ``cal_lock``, the
    settings checked at construction (``xcp_address``, ``xcp_protocol``,
    ``xcp_key``, ``control_path``, ``rate_hz``, ``time_scale``) and
    ``warnings``, which it adds to.
    """

    def _start_xcp(self) -> None:
        from rt_loop.measure.xcp import XcpServer, a2l

        host, port = self.xcp_address
        ffi, lib = self._ffi, self._lib

        def a2l_text() -> str:        # the address bound (a port 0 asked for is chosen then)
            bound_host, bound_port = self.xcp.address
            settings = {"transport": self.xcp_protocol, "address": bound_host, "port": bound_port,
                        "rate_hz": self.rate_hz, "time_scale": self.time_scale}
            return a2l.generate(ffi, lib, channels=self.channels, xcp=settings)

        try:
            self.xcp = XcpServer(
                ffi, lib, self._l, host=host, port=port, protocol=self.xcp_protocol,
                a2l_text=a2l_text,
                a2l_name="dct_hil", epk=a2l.epk(ffi, lib, channels=self.channels),
                key_file=self.xcp_key, ranges=self._regions)
            if self.xcp.backend is not None:
                self.xcp.backend.cal_lock = self.cal_lock
            self.xcp.start()
        except OSError as e:
            self.xcp = None
            raise ServerError(f"XCP on {self.xcp_protocol.upper()} {host}:{port}: "
                              f"{e.strerror or _one_line(e)}") from None
        if self.xcp_key is None and host not in ("127.0.0.1", "::1", "localhost"):
            self.warnings.append(f"XCP on {host}:{port} is open beyond loopback without "
                                 "--xcp-key: anyone who reaches it can calibrate the plant")

    def _start_control(self) -> None:
        from rt_loop.control import ControlError, ControlServer

        where = " and ".join(
            w for w in (self.control_path and f"socket {self.control_path}",
                        self.control_tcp and f"on {self.control_tcp[0]}:{self.control_tcp[1]}")
            if w)
        try:
            self.control = ControlServer(self, self.control_path, tcp=self.control_tcp,
                                         token=self.control_token, tls=self.control_tls)
            self.control.start()
        except (OSError, ControlError) as e:
            self.control = None
            why = e.strerror if isinstance(e, OSError) and e.strerror else _one_line(e)
            raise ServerError(f"control {where}: {why}") from None

    def _stop_control(self) -> None:
        if self.control is not None:
            self.control.stop()

    def _stop_xcp(self) -> None:
        if self.xcp is not None:
            self.xcp.stop()
