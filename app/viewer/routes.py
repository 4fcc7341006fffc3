"""The browser router, where ``app.main`` looks for optional routers (``app.viewer.routes``).

The routes themselves live in :mod:`app.api.browser` (dashboard, sessions, view links, the 3D
view page and its websocket proxy).
"""

from __future__ import annotations

from app.api.browser import router

__all__ = ["router"]
