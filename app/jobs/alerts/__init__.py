"""What the world hears of a finished job: events, webhook deliveries, e-mail, site history.

* :mod:`~app.jobs.alerts.events`: the ``job.changed`` / ``job.unchanged`` / ``job.failed``
  events, written in the transaction that finishes the job;
* :mod:`~app.jobs.alerts.deliveries`: webhook deliveries, at least once, claimed with a lease;
* :mod:`~app.jobs.alerts.mail`: a ``mailto:`` webhook's events sent by SMTP;
* :mod:`~app.jobs.alerts.site_history`: warnings that need the site's history.
"""
