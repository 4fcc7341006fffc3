"""Sensor origins from the data: estimate a single station's, check a given one.

Data flows one way: :mod:`~app.core.origins.columns` (top-view centre) and
:mod:`~app.core.origins.rings` (height) feed :mod:`~app.core.origins.estimate`
(:func:`estimate_origin`), which :mod:`~app.core.origins.resolve` uses to pick and check the
origin a comparison uses.  :mod:`~app.core.origins.sharpen` and :mod:`~app.core.origins.apex`
sharpen or search an origin on the rings when the columns concur only roughly (real lidars);
:mod:`~app.core.origins.own_frame` resolves a moved cloud's origin in whichever of its two frames
its rings are level.  :mod:`~app.core.origins.station_recovery` recovers the stations of a
merged survey when no single origin explains it and :mod:`~app.core.origins.sampling` says it was
sampled by lidars (``recover_stations="auto"``).
"""

from app.core.origins.estimate import CONFIDENT, OriginEstimate, estimate_origin

__all__ = ["CONFIDENT", "OriginEstimate", "estimate_origin"]
