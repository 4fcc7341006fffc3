"""Schedules of a site: comparisons on a rhythm (``docs/schedules.md``).

* :mod:`~app.services.schedules.service`: create, read, change, delete, run now, history;
* :mod:`~app.services.schedules.runs`: the tick that runs each period once;
* :mod:`~app.services.schedules.times`: when periods start (cron or interval);
* :mod:`~app.services.schedules.sources`: where scans come from (uploads, directory, URL);
* :mod:`~app.services.schedules.ingest`: a fetched file stored as a scan;
* :mod:`~app.services.schedules.schemas`: request and response bodies.
"""
