"""The dashboard page: one HTML template, its script and style (``assets/``), and plotly.js.

:func:`render` makes the page two ways:

* ``live=True``: served by :mod:`psdcal.report.dashboard.server`; plotly.js
  comes from the same server, the rows from its WebSocket;
* ``live=False``: the static export, one self-contained file: plotly.js, the
  script and every row are inlined (no server, no network: open it from disk).

plotly.js is the copy the ``plotly`` Python package ships, so the browser
never needs the internet.
"""
from __future__ import annotations

import functools
import html
import json
from pathlib import Path

ASSETS = Path(__file__).resolve().parent / "assets"


@functools.cache
def plotly_js() -> str:
    """The text of plotly.min.js shipped by the ``plotly`` package."""
    from importlib.resources import files

    from psdcal.errors import InputError

    try:
        return (files("plotly") / "package_data" / "plotly.min.js").read_text(encoding="utf-8")
    except (ModuleNotFoundError, FileNotFoundError) as exc:  # pragma: no cover - the extra is missing
        raise InputError("the dashboard needs plotly: pip install 'psdcal[dashboard]'") from exc


def _inline_script(text: str) -> str:
    """Script text safe inside ``<script>...</script>``."""
    return text.replace("</script", "<\\/script").replace("<!--", "<\\!--")


def render(*, live: bool, title: str, data: dict | None = None) -> str:
    """The page's HTML; ``data`` (a :meth:`Hub.snapshot`) is inlined for the static export."""
    tpl = (ASSETS / "dashboard.html").read_text(encoding="utf-8")
    config = {"mode": "live" if live else "static"}
    if live:
        plotly = '<script src="plotly.min.js"></script>'
        payload = ""
    else:
        plotly = "<script>" + _inline_script(plotly_js()) + "</script>"
        payload = ('<script id="psd-data" type="application/json">'
                   + _inline_script(json.dumps(data, allow_nan=False, separators=(",", ":"))) + "</script>")
    return (tpl.replace("{{TITLE}}", html.escape(title))
            .replace("{{STYLE}}", (ASSETS / "dashboard.css").read_text(encoding="utf-8"))
            .replace("{{CONFIG}}", _inline_script(json.dumps(config)))
            .replace("{{DATA}}", payload)
            .replace("{{PLOTLY}}", plotly)
            .replace("{{SCRIPT}}", _inline_script((ASSETS / "dashboard.js").read_text(encoding="utf-8"))))
