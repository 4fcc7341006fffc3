"""Fused indoor maps for tests: a room's surfaces sampled uniformly (as a fused, voxel-thinned
RGB-D or laser map is), with furniture boxes and coverage gaps, and no sensor position."""

from __future__ import annotations

import numpy as np

CHAIR = ([2.5, 1.5, 0.0], [3.0, 2.0, 0.9])
"""A chair-sized box standing on the floor (low and high corners)."""

SPACING = 0.03


def plane(rng, origin, first, second, spacing=SPACING, noise=0.002):
    """Points on a rectangle (origin + s * first + t * second), jittered, with noise."""
    first, second = np.asarray(first, float), np.asarray(second, float)
    n_s = max(2, int(np.linalg.norm(first) / spacing))
    n_t = max(2, int(np.linalg.norm(second) / spacing))
    s, t = np.meshgrid((np.arange(n_s) + 0.5) / n_s, (np.arange(n_t) + 0.5) / n_t)
    s = s.ravel() + rng.uniform(-0.3, 0.3, s.size) / n_s
    t = t.ravel() + rng.uniform(-0.3, 0.3, t.size) / n_t
    points = np.asarray(origin, float) + s[:, None] * first + t[:, None] * second
    normal = np.cross(first, second)
    normal /= np.linalg.norm(normal)
    return points + rng.normal(0.0, noise, (points.shape[0], 1)) * normal


def box_faces(rng, low, high):
    """The five visible faces of a box standing on the floor (no bottom)."""
    low, high = np.asarray(low, float), np.asarray(high, float)
    size = high - low
    x, y, z = np.diag(size)
    return np.vstack(
        [
            plane(rng, [low[0], low[1], high[2]], x, y),
            plane(rng, low, x, z),
            plane(rng, [low[0], high[1], low[2]], x, z),
            plane(rng, low, y, z),
            plane(rng, [high[0], low[1], low[2]], y, z),
        ]
    )


def box_sides(rng, low, high, faces="tnsew", spacing=SPACING):
    """Some faces of a box, sampled every ``spacing``: ``t`` its top, ``s`` / ``n`` its sides
    at low / high y, ``w`` / ``e`` its sides at low / high x (a path sees some faces only)."""
    low, high = np.asarray(low, float), np.asarray(high, float)
    x, y, z = np.diag(high - low)
    corners = {
        "t": ([low[0], low[1], high[2]], x, y),
        "s": (low, x, z),
        "n": ([low[0], high[1], low[2]], x, z),
        "w": (low, y, z),
        "e": ([high[0], low[1], low[2]], y, z),
    }
    return np.vstack([plane(rng, *corners[face], spacing=spacing) for face in faces])


def fused_room(rng, *, floor_hole=None, box=None, ceiling_to=6.0):
    """A 6 x 4 x 2.5 m room's floor, two walls and ceiling (to x = ``ceiling_to``), sampled
    as a fused map is: uniformly, with what a box hides of the floor missing."""
    floor = plane(rng, [0, 0, 0], [6, 0, 0], [0, 4, 0])
    keep = np.ones(floor.shape[0], bool)
    for hole in [h for h in (floor_hole, box) if h is not None]:
        low, high = hole
        keep &= ~(
            (floor[:, 0] > low[0])
            & (floor[:, 0] < high[0])
            & (floor[:, 1] > low[1])
            & (floor[:, 1] < high[1])
        )
    parts = [
        floor[keep],
        plane(rng, [0, 0, 0], [6, 0, 0], [0, 0, 2.5]),
        plane(rng, [0, 0, 0], [0, 4, 0], [0, 0, 2.5]),
        plane(rng, [0, 0, 2.5], [ceiling_to, 0, 0], [0, 4, 0]),
    ]
    if box is not None:
        parts.append(box_faces(rng, box[0], box[1]))
    return np.vstack(parts)


def box_removed_beside_a_band(rng, wall_room, spacing):
    """A 0.4 m box removed beside a wall the reference saw up to 2.4 m and the scan up to 1.4 m
    (``wall_room(rng, wall_top)`` builds the room), localised: the share of the box's points
    (those over the floor's change threshold) called changed, and the rest of the reference's
    changed points."""
    from app.core.labels import LABEL_CHANGED
    from app.core.localise import localise_changes

    box = box_sides(rng, [1.0, 0.6, 0.0], [1.4, 1.0, 0.4], spacing=spacing)
    box = box[box[:, 2] > 0.12]  # its foot is within the change threshold of the floor
    reference = np.vstack([wall_room(rng, 2.4), box])
    found = localise_changes(reference, wall_room(rng, 1.4), threads=1)
    changed = found.reference_label == LABEL_CHANGED
    return changed[-box.shape[0] :].mean(), int(np.count_nonzero(changed[: -box.shape[0]]))


def chair_before_wall(rng, *, gap, tilt=0.0):
    """A chair whose back stands ``gap`` metres before the room's wall y = 0 (``gap + tilt`` at
    its far end), and the room: the reference's room lacks the wall patch the back hid, the
    scan's (the chair removed) has it whole (robot warehouse 2804 of ``bench.moving_maps``).

    Returns
    -------
    reference, scan : ndarray, shape (n, 3)
        The reference ends with the back's then the seat's points.
    back, hidden : ndarray, bool
        The reference's back points, the scan's wall patch the back hid from the reference.
    """
    x0, x1, z0, z1 = 2.5, 3.0, 0.45, 0.95
    room = fused_room(rng)
    hidden = (np.abs(room[:, 1]) < 0.01) & (room[:, 2] > z0 + 0.03) & (room[:, 2] < z1 - 0.03)
    hidden &= (room[:, 0] > x0 + 0.03) & (room[:, 0] < x1 - 0.03)
    back = plane(rng, [x0, gap, z0], [x1 - x0, tilt, 0], [0, 0, z1 - z0])
    seat = box_sides(rng, [x0, gap + 0.02, 0.0], [x1, gap + 0.5, 0.45], faces="tew")
    reference = np.vstack([room[~hidden], back, seat])
    is_back = np.zeros(reference.shape[0], bool)
    is_back[-(back.shape[0] + seat.shape[0]) : -seat.shape[0]] = True
    return reference, room, is_back, hidden
