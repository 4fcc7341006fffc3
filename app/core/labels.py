"""The per-point change labels every result, viewer and test reads.

:func:`app.core.localise.localise_changes` gives each point of both clouds one of these
(``reference_label``, ``scan_label``, int8, shapes (n,) and (m,)); the viewer, the stored
labels file and the quality warnings read them back.  They are defined here only, so that a
reader needs no import of the localiser.
"""

from __future__ import annotations

LABEL_UNOBSERVED = -1
"""Not observed by the other scan (or dropped): no evidence either way."""

LABEL_UNCHANGED = 0
"""Observed by the other scan and unchanged."""

LABEL_CHANGED = 1
"""Changed: removed (a reference point) or added (a scan point)."""
