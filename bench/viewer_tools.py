"""What the 3D view's live tools cost on one scene (issue 19): build, relabel, redraw, pick.

    .venv/bin/python -m bench.viewer_tools --points 200000

Compares a ray-cast rescan of the two rooms (``--points`` rays per scan, a box added, one
removed, one moved) like the worker, builds the viewer's scene from the result, then times (the
best of ``--repeat``) what a reviewer's control does on the server: relabelling at the job's
settings and at twice its distance threshold, drawing every layer by label and by signed
distance, and picking a point.  Prints one line per step, in milliseconds.
"""

from __future__ import annotations

import argparse
import math
import time
from collections.abc import Callable

import numpy as np

from app.core.datasets.scenes import raycast_scene
from app.testing.viewer_scenes import compare_with_origins, scene_of
from app.viewer.regions_display import relabel
from app.viewer.rendering import ViewState, pick_point, render_layers


def best_of(repeat: int, action: Callable[[], object]) -> float:
    """The fastest of ``repeat`` runs of ``action``, in milliseconds."""
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        action()
        times.append(time.perf_counter() - start)
    return min(times) * 1000.0


def main() -> None:
    """Run the steps and print their times."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, default=200_000, help="rays per scan")
    parser.add_argument("--repeat", type=int, default=3)
    arguments = parser.parse_args()
    pair = raycast_scene(n_points=arguments.points, change="mixed", random_state=1)
    result = compare_with_origins(pair)
    start = time.perf_counter()
    data = scene_of(pair, result)
    build = (time.perf_counter() - start) * 1000.0
    pool = sum(len(p.indices) for p in data.pools.values())
    print(f"scene: {data.n_total:,} points, {len(data.regions)} regions, pool {pool:,} points")
    print(f"build scene (with candidate pools)   {build:8.1f} ms")
    threshold, size = data.change_threshold, data.min_region_points
    for title, distance in (
        ("the job's settings", threshold),
        ("twice the threshold", 2 * threshold),
    ):
        regions = len(relabel(data, distance, size).regions)
        elapsed = best_of(arguments.repeat, lambda d=distance: relabel(data, d, size))
        print(f"relabel at {title:<25} {elapsed:8.1f} ms ({regions} regions)")
    labels = {side: data.sides[side].labels for side in data.sides}
    for mode in ("label", "distance"):
        state = ViewState(colour_mode=mode)
        elapsed = best_of(arguments.repeat, lambda s=state: render_layers(data, s, labels))
        print(f"draw every layer, colour by {mode:<8} {elapsed:8.1f} ms")
    layers = render_layers(data, ViewState(), labels)
    target = layers["removed"].points[0].astype(float)
    camera = target + np.array([0.0, 0.0, 5.0])
    visible = {name: True for name in layers}
    elapsed = best_of(
        arguments.repeat,
        lambda: pick_point(
            data, layers, visible, labels, camera, target - camera, math.radians(0.06)
        ),
    )
    print(f"pick a point                         {elapsed:8.1f} ms")


if __name__ == "__main__":
    main()
