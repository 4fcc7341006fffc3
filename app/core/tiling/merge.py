"""Join the tiles of a comparison into one localisation in the clouds' order.

Each point's label and distance come from the tile whose core holds it.  A region cut by a
tile border is found, in each tile it touches, with members in that tile's margin that are
core members of a region of the neighbouring tile: those regions are one (a graph of tile
regions joined by shared points, connected components).  A joined region is made of its
parts' core points; it is kept when it has at least the whole pair's minimum region size
(else its points are unchanged, as a small cluster is in one process), takes its parts'
most common evidence and their mean confidence, and moved surfaces are marked on the joined
regions.  Uncertain regions (no coverage) are joined the same way.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from app.core.errors import InputError
from app.core.labels import LABEL_CHANGED, LABEL_UNCHANGED, LABEL_UNOBSERVED
from app.core.localise import ChangedRegion, Localisation
from app.core.localise.regions import EVIDENCE_NAMES, mark_moved_surfaces
from app.core.tiling.plan import TilePlan
from app.core.tiling.tile import TileResult

__all__ = [
    "MergedLocalisation",
    "join_regions",
    "label_counts",
    "merge_tiles",
    "merged_parameters",
]

MergedLocalisation = Localisation
"""The merged result has the shape of a one-process :class:`~app.core.localise.Localisation`
(its ``parameters`` add ``tiles``: the plan and each tile's figures)."""

NODE_FIELDS = (
    "cloud",
    "uncertain",
    "evidence",
    "confidence",
    "core_count",
    "distance_sum",
    "distance_max",
)
"""The per-region scalars of a tile's region table that the merge joins."""
PER_TILE_FIGURES = (
    "alignment_residual",
    "reference_noise",
    "scan_noise",
    "threshold",
    "support_factor",
    "crop_reference_points",
    "crop_scan_points",
    "core_reference_points",
    "core_scan_points",
    "thinning_cell_m",
    "thinned_reference_points",
    "thinned_scan_points",
)


def merge_tiles(
    plan: TilePlan,
    results: Sequence[TileResult],
    n_reference: int,
    n_scan: int,
    min_region_points: int,
) -> Localisation:
    """One localisation of the whole pair from its tiles' results.

    Parameters
    ----------
    plan : TilePlan
    results : sequence of TileResult
        One per tile of ``plan``, any order.
    n_reference, n_scan : int
        Points of each cloud.
    min_region_points : int
        The whole pair's minimum region size.

    Returns
    -------
    Localisation
        Labels, distances and region indices in the clouds' order; regions and uncertain
        regions joined across tile borders.

    Raises
    ------
    InputError
        A tile is missing or twice, or a point is in no core or in two.
    """
    found = sorted(result.tile_index for result in results)
    if found != list(range(plan.n_tiles)):
        raise InputError(f"merge needs each of the plan's {plan.n_tiles} tiles once, got {found}")
    labels = [np.full(n, LABEL_UNOBSERVED, dtype=np.int8) for n in (n_reference, n_scan)]
    distances = [np.full(n, np.nan, dtype=np.float32) for n in (n_reference, n_scan)]
    covered = [np.zeros(n, dtype=np.int32) for n in (n_reference, n_scan)]
    for result in results:
        for cloud, index, label, distance in (
            (0, result.reference_index, result.reference_label, result.reference_distance),
            (1, result.scan_index, result.scan_label, result.scan_distance),
        ):
            labels[cloud][index] = label
            distances[cloud][index] = distance
            covered[cloud][index] += 1
    if any(np.any(count != 1) for count in covered):
        raise InputError("the tiles' cores do not cover every point exactly once")
    del covered

    regions, uncertain, region_of = _joined_regions(results, labels, min_region_points)
    parameters = _merged_parameters(plan, results, labels, len(uncertain))
    return Localisation(
        reference_label=labels[0],
        scan_label=labels[1],
        reference_distance=distances[0],
        scan_distance=distances[1],
        reference_region=region_of[0],
        scan_region=region_of[1],
        regions=regions,
        parameters=parameters,
        uncertain_regions=uncertain,
    )


def _joined_regions(
    results: Sequence[TileResult], labels: list[NDArray[np.int8]], min_region_points: int
) -> tuple[list[ChangedRegion], list[ChangedRegion], list[NDArray[np.int32]]]:
    """Regions joined across borders; changed points of dropped ones relabelled unchanged."""

    def unchange(cloud: int, points: NDArray[np.int64]) -> None:
        label = labels[cloud]
        label[points[label[points] == LABEL_CHANGED]] = LABEL_UNCHANGED

    regions, uncertain_regions = join_regions(
        [result.regions for result in results], min_region_points, unchange
    )
    region_of = [np.full(len(label), -1, dtype=np.int32) for label in labels]
    for number, region in enumerate(regions):
        region_of[1 if region.kind == "added" else 0][region.point_indices] = number
    return regions, uncertain_regions, region_of


def join_regions(
    tables: Sequence[dict[str, NDArray]],
    min_region_points: int,
    unchange: Callable[[int, NDArray[np.int64]], None],
) -> tuple[list[ChangedRegion], list[ChangedRegion]]:
    """The tiles' region tables joined across borders (see the module).

    Parameters
    ----------
    tables : sequence of dict
        Each tile's :attr:`~app.core.tiling.tile.TileResult.regions`.
    min_region_points : int
        Joined changed regions smaller than this are dropped.
    unchange : callable
        ``unchange(cloud, points)``: called with each dropped changed region's points (0
        reference, 1 scan; sorted indices): their changed labels become unchanged.

    Returns
    -------
    regions, uncertain_regions : list of ChangedRegion
        In the one-process order (largest first), moved surfaces marked.
    """
    sizes = [len(table["cloud"]) for table in tables]
    n_nodes = int(sum(sizes))
    column = {
        name: np.concatenate([table[name] for table in tables]) if tables else np.zeros(0)
        for name in NODE_FIELDS
    }
    boxes = {
        name: np.concatenate([table[name] for table in tables]).reshape(-1, 3)
        if n_nodes
        else np.zeros((0, 3))
        for name in ("core_sum", "core_min", "core_max")
    }
    members, in_core, node_of_member = [], [], []
    first = 0
    for table, size in zip(tables, sizes, strict=True):
        members.append(table["members"])
        in_core.append(table["member_in_core"])
        node_of_member.append(first + np.repeat(np.arange(size), np.diff(table["member_bounds"])))
        first += size
    member = np.concatenate(members) if members else np.zeros(0, dtype=np.int64)
    core = np.concatenate(in_core) if in_core else np.zeros(0, dtype=bool)
    node = np.concatenate(node_of_member) if node_of_member else np.zeros(0, dtype=np.int64)
    category = column["cloud"].astype(np.int64) * 2 + column["uncertain"].astype(np.int64)
    member_category = category[node] if n_nodes else np.zeros(0, dtype=np.int64)

    component = _linked_components(n_nodes, member, core, node, member_category)

    joined: list[tuple[ChangedRegion, bool]] = []
    core_member, core_node = member[core], node[core]
    order = np.argsort(component[core_node], kind="stable")
    core_member, core_node = core_member[order], core_node[order]
    starts = np.searchsorted(component[core_node], np.arange(component.max(initial=-1) + 2))
    for number in range(component.max(initial=-1) + 1):
        parts = np.flatnonzero(component == number)
        count = int(column["core_count"][parts].sum())
        cloud, uncertain = int(column["cloud"][parts[0]]), bool(column["uncertain"][parts[0]])
        points = np.sort(core_member[starts[number] : starts[number + 1]])
        if count < min_region_points:
            if not uncertain:
                unchange(cloud, points)
            continue
        weights = column["core_count"][parts].astype(np.float64)
        votes = np.bincount(
            column["evidence"][parts].astype(np.int64), weights=weights, minlength=4
        )
        votes[0] = 0.0
        joined.append(
            (
                ChangedRegion(
                    kind="added" if cloud else "removed",
                    point_indices=points.astype(np.int64),
                    centroid=boxes["core_sum"][parts].sum(axis=0) / count,
                    bbox_min=boxes["core_min"][parts].min(axis=0),
                    bbox_max=boxes["core_max"][parts].max(axis=0),
                    mean_distance=float(column["distance_sum"][parts].sum() / count),
                    max_distance=float(column["distance_max"][parts].max()),
                    evidence=EVIDENCE_NAMES.get(int(np.argmax(votes)), "seen_empty"),
                    confidence=float(np.average(column["confidence"][parts], weights=weights)),
                ),
                uncertain,
            )
        )
    regions = [region for region, uncertain in joined if not uncertain]
    regions.sort(key=lambda region: (-region.n_points, region.kind, int(region.point_indices[0])))
    regions = mark_moved_surfaces(regions)
    uncertain_regions = [region for region, uncertain in joined if uncertain]
    uncertain_regions.sort(key=lambda region: (-region.n_points, region.kind))
    return regions, uncertain_regions


def _linked_components(
    n_nodes: int,
    member: NDArray[np.int64],
    core: NDArray[np.bool_],
    node: NDArray[np.int64],
    member_category: NDArray[np.int64],
) -> NDArray[np.int64]:
    """The joined region of each tile region: a margin member joins its region to the region
    (of the same cloud and kind) whose core holds the same point.

    Parameters
    ----------
    n_nodes : int
        Tile regions of all tiles.
    member, core, node, member_category : ndarray, shape (p,)
        Every region member: its point, whether in its tile's core, its tile region, and that
        region's cloud and kind (``2 * cloud + uncertain``).

    Returns
    -------
    ndarray, shape (n_nodes,)
        Connected component of each tile region.
    """
    rows, columns = [np.arange(n_nodes)], [np.arange(n_nodes)]
    for kind in range(4):
        owned = core & (member_category == kind)
        owner_points, owner_nodes = member[owned], node[owned]
        order = np.argsort(owner_points, kind="stable")
        owner_points, owner_nodes = owner_points[order], owner_nodes[order]
        visiting = ~core & (member_category == kind)
        if not len(owner_points) or not visiting.any():
            continue
        position = np.minimum(np.searchsorted(owner_points, member[visiting]), len(order) - 1)
        same = owner_points[position] == member[visiting]
        rows.append(node[visiting][same])
        columns.append(owner_nodes[position[same]])
    row, col = np.concatenate(rows), np.concatenate(columns)
    # on first use: an untiled comparison imports this module but never merges, and scipy.sparse
    # at start-up was ~0.18 CPU s of its serial start (the detectors' warm-up imports it beside)
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    graph = coo_matrix((np.ones(len(row), dtype=np.int8), (row, col)), (n_nodes, n_nodes))
    _, component = connected_components(graph, directed=True, connection="weak")
    return component


def _merged_parameters(
    plan: TilePlan,
    results: Sequence[TileResult],
    labels: list[NDArray[np.int8]],
    n_uncertain: int,
) -> dict[str, Any]:
    """The largest localised tile's parameters, the whole pair's counts, and ``tiles``."""
    return merged_parameters(
        plan,
        [
            (
                result.tile_index,
                len(result.reference_index) + len(result.scan_index),
                result.figures,
            )
            for result in results
        ],
        label_counts(labels[0], labels[1]),
        n_uncertain,
    )


def label_counts(reference_label: NDArray[np.int8], scan_label: NDArray[np.int8]) -> dict[str, int]:
    """The changed and unobserved points of each cloud (:func:`merged_parameters`'s counts)."""
    return {
        "n_reference_changed": int(np.count_nonzero(reference_label == LABEL_CHANGED)),
        "n_reference_unobserved": int(np.count_nonzero(reference_label == LABEL_UNOBSERVED)),
        "n_scan_changed": int(np.count_nonzero(scan_label == LABEL_CHANGED)),
        "n_scan_unobserved": int(np.count_nonzero(scan_label == LABEL_UNOBSERVED)),
    }


def merged_parameters(
    plan: TilePlan,
    tiles: Sequence[tuple[int, int, dict[str, Any]]],
    counts: dict[str, int],
    n_uncertain: int,
) -> dict[str, Any]:
    """The merged localisation's parameters.

    Parameters
    ----------
    plan : TilePlan
    tiles : sequence of (int, int, dict)
        Each tile's index, core points and :attr:`~app.core.tiling.tile.TileResult.figures`.
    counts : dict
        The whole pair's :func:`label_counts`.
    n_uncertain : int
        Joined uncertain regions.

    Returns
    -------
    dict
        The largest localised tile's parameters, ``counts``, and ``tiles``: the plan and
        each tile's figures.
    """
    localised = [tile for tile in tiles if tile[2].get("localised")]
    base = dict(max(localised or tiles, key=lambda tile: tile[1])[2])
    for name in (*PER_TILE_FIGURES, "localised"):
        base.pop(name, None)
    ordered = sorted(tiles, key=lambda tile: tile[0])
    residuals = [float(figures.get("alignment_residual", np.nan)) for _, _, figures in ordered]
    base.update(
        {
            **counts,
            "n_uncertain_regions": n_uncertain,
            "tiles": {
                "count": plan.n_tiles,
                "margin_m": plan.margin,
                "max_crop_points": plan.max_crop_points,
                "thinned_tiles": plan.thinned_tiles,
                "alignment_residual_max": float(np.nanmax(residuals))
                if np.isfinite(residuals).any()
                else None,
                "per_tile": [
                    {
                        "tile": tile_index,
                        "core_min": plan.lower[tile_index].tolist(),
                        "core_max": plan.upper[tile_index].tolist(),
                        **{name: figures[name] for name in PER_TILE_FIGURES if name in figures},
                    }
                    for tile_index, _, figures in ordered
                ],
            },
        }
    )
    return base
