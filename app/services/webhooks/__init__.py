"""Webhooks of an organisation (``docs/webhooks.md``).

* :mod:`~app.services.webhooks.service`: create (secret shown once), list, delete, deliveries,
  test;
* :mod:`~app.services.webhooks.schemas`: request and response bodies of ``/api/v1/webhooks``.

Sending is the job layer's: :mod:`app.jobs.alerts.deliveries`.
"""
