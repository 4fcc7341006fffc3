"""Who may see a job's 3D view: the answer an authoriser gives the viewer's routes.

The viewer does not authenticate anyone itself: :func:`app.viewer.routes.build_viewer_router`
takes a :data:`ViewAuthoriser` (the API passes one that checks the session cookie or the view
link), so nothing here imports the API.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from starlette.requests import HTTPConnection

VIEW_COOKIE = "scandiff_view"
"""Holds a view link for its view's path (the viser client drops the query string when it opens
its websocket)."""


@dataclass(frozen=True)
class ViewGrant:
    """Why a connection may see a job's 3D view."""

    job_id: str
    token_id: str
    via: str  # "session" or "link"
    expires_at: float


@dataclass(frozen=True)
class ViewRefusal:
    """Why a connection may not see a job's 3D view: an HTTP status and words for a person."""

    status: int
    title: str
    message: str


ViewAuthoriser = Callable[[HTTPConnection, str, str | None], ViewGrant | ViewRefusal]
"""``authorise(connection, job_id, link)``: a grant or a refusal (blocking: run in a thread).

``link`` is the view link of the page's query string; None for the websocket (the viser client
drops the query string), whose authoriser reads the view-link cookie instead and must check
that the ``Origin`` is this server.
"""
