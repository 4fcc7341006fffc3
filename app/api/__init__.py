"""The HTTP layer: thin FastAPI routes (``routes/``), dependencies (settings, the request's
session, the principal), streamed upload bodies, error rendering and request logs."""
