"""The live bench view in the browser (``dct-hil serve --ui``, ``dct-hil demo --ui``).

``server.py``: the embedded Bokeh server (its own tornado IOLoop in a
thread of its own), the token login, the downloads; ``app.py``: one Bokeh
document per browser session (traces, instruments, timing, bus, controls);
``figures.py``: what the panels show, as pure functions.
"""

from dct_hil.ui.server import DEFAULT_ADDRESS, UiError, UiServer, parse_address

__all__ = ["DEFAULT_ADDRESS", "UiError", "UiServer", "parse_address"]
