"""Test and benchmark harness: real service processes, local receivers, file writers.

The public home of what both ``tests/`` and ``bench/`` run, in the spirit of ``django.test``:
a benchmark imports these instead of the test suite's helpers.  Nothing in the rest of ``app``
imports this package (``tests/test_import_graph.py`` puts it above every other layer), and it
imports no test framework: pytest's skip policy stays in ``tests/helpers``.  It needs the
``dev`` extra (``httpx``, and ``redis``/``psycopg`` for the topology) and a checkout (child
processes start in :data:`app.testing.paths.PROJECT_ROOT`; the webhook receiver executes the
signature check of ``docs/webhooks.md``).

Modules
-------
``service``
    :class:`~app.testing.service.ServiceProcess` (``scandiff serve`` in its own process group on
    a free port), :class:`~app.testing.service.ConsumerProcess`,
    :class:`~app.testing.service.ApiProcess`, process-group helpers.
``topology``
    :func:`~app.testing.topology.scaled_out`: PostgreSQL, a private Redis, N API processes and
    N workers on one data directory (the scaled-out deployment shape).
``redis``
    :class:`~app.testing.redis.RedisServer`, a private ``redis-server`` on a free port.
``fake_pipeline``
    A fast deterministic stand-in for the comparison, installed through ``app.jobs.hooks``.
``results``
    The typed reports of a comparison result (registration, calibration, sensor origins) built
    by hand with plausible defaults, for stand-ins and finished test jobs.
``webhooks``
    :class:`~app.testing.webhooks.WebhookReceiver`, a local HTTP receiver that checks every
    signature with the snippet of ``docs/webhooks.md``.
``files``, ``e57_times``, ``bags``
    Point-cloud files as bytes in every upload format (the reference libraries write them), E57
    files with per-point times, ROS 1/2 lidar bags.
``scenes``
    Small synthetic clouds (random grid points, a room, a corridor).
``viewer_scenes``
    A synthetic pair compared with its sensor origins given, and the 3D view's scene of it.
``network``, ``waiting``, ``paths``
    A free TCP port, polling until a condition holds, where the checkout and shared data are.
"""
