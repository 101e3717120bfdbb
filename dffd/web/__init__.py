"""The operator's web dashboard and Prometheus metrics (aiohttp, prometheus-client).

:class:`~dffd.web.server.DashboardServer` serves a daemon that implements
:class:`~dffd.web.interface.DashboardSource`; see those modules.
"""
