"""``psdcal dashboard``: a running room in the browser, and its static export.

- :mod:`~psdcal.report.dashboard.follow`: follow a file as it grows (``tail -F``).
- :mod:`~psdcal.report.dashboard.data`: rows, sensors, emitters and warnings as the page draws them.
- :mod:`~psdcal.report.dashboard.hub`: what is followed, what is kept, what changed (live or replay).
- :mod:`~psdcal.report.dashboard.server`: the aiohttp server (safety rules) and the static export.
- :mod:`~psdcal.report.dashboard.page`: the page (``assets/``) with plotly.js inlined or served.

The server and plotting libraries (``pip install 'psdcal[dashboard]'``) are
imported only when the dashboard runs. The positioning never imports this
package: the dashboard reads the files the commands write.
"""
