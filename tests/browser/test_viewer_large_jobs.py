"""The 3D view of jobs too large to load (:mod:`app.viewer.large_scene`), on generated files.

Rules checked (with a lowered budget, on real files and a job's stored labels and distances):

* the view opens at the point budget, changed points first, with the same layer totals and
  per-layer counts as the whole-cloud builder; every drawn point is the file's point at its
  row (the scan moved into the reference frame) with that row's label;
* memory: the clouds are read a block at a time, never whole;
* the same through a stored job (its database row and result files) once its clouds are over
  ``viewer_stream_above_points``: the layers' totals of the whole-cloud view, the labels the
  worker wrote;
* "clip to a box" draws every point inside the box at full density while the box fits the
  budget; past it the budget holds, the box's changed points come first, and a warning says
  how many points the box holds; the view's "Full density in a box" panel (driven over
  viser's websocket) draws that box and goes back to the whole view.
"""

from __future__ import annotations

import tracemalloc
from functools import partial
from pathlib import Path

import msgspec.msgpack
import numpy as np
import pytest
import websockets.sync.client
from viser import _messages

from app.config import Settings
from app.core.registration import apply_transform
from app.db.migrate import upgrade_to_head
from app.db.models import Scan
from app.db.session import transaction
from app.testing.files import las_bytes, ply_bytes
from app.testing.waiting import wait_until
from app.viewer import large_scene
from app.viewer.large_scene import SceneContext, StoredSide, box_scene, budget_scene
from app.viewer.loading import ViewUnavailableError, load_job_box, load_job_scene
from app.viewer.manager import ViewerManager
from app.viewer.scene import CHANGED_SHARE_OF_BUDGET, build_scene_data
from app.viewer.stored_results import stored_distances, stored_labels
from app.viewer.viser_guard import VIEW_SECRET_HEADER
from tests.helpers.jobs import create_job, finish_job, load_job
from tests.helpers.server import ApiServer
from tests.helpers.viser_wire import VISER_SUBPROTOCOL, camera_message, receive_messages

N_POINTS = 20_000
CHANGE_LOW = np.array([2.0, 2.0, 0.0])
CHANGE_HIGH = np.array([2.6, 2.6, 1.0])


def _turn(angle: float, shift: tuple[float, float, float]) -> np.ndarray:
    matrix = np.eye(4)
    matrix[:2, :2] = [[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]]
    matrix[:3, 3] = shift
    return matrix


def _side(points: np.ndarray, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Labels (changed inside the change box, a few unobserved) and distances of a side."""
    rng = np.random.default_rng(seed)
    inside = ((points >= CHANGE_LOW) & (points <= CHANGE_HIGH)).all(axis=1)
    labels = np.zeros(len(points), np.int8)
    labels[rng.random(len(points)) < 0.05] = -1
    labels[inside] = 1
    distances = np.where(inside, 0.3, rng.random(len(points)) * 0.1).astype(np.float32)
    distances[labels == -1] = np.nan
    return labels, distances


@pytest.fixture(scope="module")
def job(tmp_path_factory):
    """A reference (PLY) and a scan (LAS, in its own frame) with stored labels and distances."""
    folder: Path = tmp_path_factory.mktemp("large-job")
    rng = np.random.default_rng(7)
    reference = rng.random((N_POINTS, 3)) * [8.0, 6.0, 3.0]
    scan_in_reference = rng.random((N_POINTS, 3)) * [8.0, 6.0, 3.0]
    transform = _turn(0.3, (1.5, -2.0, 0.25))  # scan file frame -> reference frame
    scan_file = apply_transform(scan_in_reference, np.linalg.inv(transform))
    (folder / "reference.ply").write_bytes(ply_bytes(reference, coordinate_type="f8"))
    (folder / "scan.las").write_bytes(las_bytes(scan_file, scale=1e-4))
    reference_labels, reference_distances = _side(reference, 1)
    scan_labels, scan_distances = _side(scan_in_reference, 2)
    np.savez_compressed(
        folder / "labels.npz", reference_label=reference_labels, scan_label=scan_labels
    )
    np.savez(
        folder / "details.npz", reference_distance=reference_distances, scan_distance=scan_distances
    )
    labels = stored_labels(folder / "labels.npz")
    distances = stored_distances(folder / "details.npz", {k: len(v) for k, v in labels.items()})
    paths = {"reference": folder / "reference.ply", "scan": folder / "scan.las"}
    sides = {side: StoredSide(paths[side], labels[side], distances[side]) for side in paths}
    files = {"reference": reference, "scan": apply_transform(scan_file, transform)}
    return sides, SceneContext(transform), files


def _check_drawn_points_are_the_files(data, sides, files) -> None:
    for side, cloud in data.sides.items():
        np.testing.assert_allclose(
            cloud.points + data.origin, files[side][cloud.indices], atol=1e-3
        )
        np.testing.assert_array_equal(cloud.labels, sides[side].labels[cloud.indices])


def test_opens_at_the_budget_changed_first(job):
    sides, context, files = job
    budget = 1500
    data = budget_scene(sides, context, budget)
    assert data.n_shown <= budget
    for name, side in (("removed", "reference"), ("added", "scan")):
        changed = int((sides[side].labels == 1).sum())
        assert 0 < changed < budget / 2
        assert data.layer(name).n_shown == data.layer(name).n_total == changed
    whole = build_scene_data(
        files["reference"],
        apply_transform(files["scan"], np.linalg.inv(context.transform)),
        reference_labels=sides["reference"].labels,
        scan_labels=sides["scan"].labels,
        transform=context.transform,
        point_budget=budget,
    )
    for layer in whole.layers:
        assert data.layer(layer.name).n_total == layer.n_total
        assert abs(data.layer(layer.name).n_shown - layer.n_shown) <= 1  # rounding per side
    _check_drawn_points_are_the_files(data, sides, files)
    assert data.change_threshold == pytest.approx(0.3)
    for side, pool in data.pools.items():
        np.testing.assert_array_equal(pool.indices, np.flatnonzero(sides[side].labels == 1))


def test_reads_the_clouds_a_block_at_a_time(job, monkeypatch):
    sides, context, files = job
    monkeypatch.setattr(large_scene, "READ_BLOCK_POINTS", N_POINTS // 20)
    monkeypatch.setattr(large_scene, "CHUNK_ROWS", N_POINTS // 20)
    tracemalloc.start()
    try:
        data = budget_scene(sides, context, 1000)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert data.n_shown <= 1000
    assert peak < files["reference"].nbytes  # less than one whole cloud in float64


def test_a_box_is_drawn_at_full_density(job):
    sides, context, files = job
    low, high = CHANGE_LOW - 0.5, CHANGE_HIGH + 0.5
    inside = {
        side: np.flatnonzero(((points >= low) & (points <= high)).all(axis=1))
        for side, points in files.items()
    }
    n_inside = sum(len(rows) for rows in inside.values())
    data = box_scene(sides, context, low, high, point_budget=n_inside)
    assert data.n_shown == data.n_total == n_inside
    for side, rows in inside.items():
        np.testing.assert_array_equal(data.sides[side].indices, rows)
    _check_drawn_points_are_the_files(data, sides, files)
    assert not [w for w in data.warnings if w["code"] == "box_capped"]


@pytest.mark.parametrize("keep_budgets", [4, 1])  # kept then strided / counted then read again
def test_a_box_over_the_budget_is_capped_changed_first_and_says_so(job, keep_budgets, monkeypatch):
    sides, context, files = job
    monkeypatch.setattr(large_scene, "BOX_KEEP_BUDGETS", keep_budgets)
    low, high = CHANGE_LOW - 1.0, CHANGE_HIGH + 1.0
    n_inside = sum(
        int(((points >= low) & (points <= high)).all(axis=1).sum()) for points in files.values()
    )
    n_changed = sum(int((side.labels == 1).sum()) for side in sides.values())
    budget = n_inside // 3
    assert n_changed < budget / 2
    data = box_scene(sides, context, low, high, point_budget=budget)
    assert data.n_total == n_inside
    assert data.n_shown <= budget
    assert data.layer("removed").n_shown + data.layer("added").n_shown == n_changed
    _check_drawn_points_are_the_files(data, sides, files)
    (capped,) = [w for w in data.warnings if w["code"] == "box_capped"]
    assert f"{n_inside:,}" in capped["message"]
    shown = {side: cloud.indices for side, cloud in data.sides.items()}
    monkeypatch.setattr(large_scene, "BOX_KEEP_BUDGETS", 5 - keep_budgets)  # the other way
    again = box_scene(sides, context, low, high, point_budget=budget)
    for side, cloud in again.sides.items():
        np.testing.assert_array_equal(cloud.indices, shown[side])


def test_a_malformed_box_is_refused(job):
    sides, context, _ = job
    with pytest.raises(ValueError, match="above its high corner"):
        box_scene(sides, context, [1, 1, 1], [0, 2, 2])


@pytest.fixture(scope="module")
def stored_job(tmp_path_factory):
    """A succeeded job in a migrated data directory (the real result files and rows)."""
    settings = Settings(data_dir=tmp_path_factory.mktemp("large-view") / "data")
    settings.data_dir.mkdir()
    upgrade_to_head(settings.sqlalchemy_url)
    job_id = create_job(settings, n_points=3000)
    job = load_job(settings, job_id)
    with transaction(settings.sqlalchemy_url) as session:
        sizes = [
            session.get_one(Scan, scan_id).n_points
            for scan_id in (job.reference_scan_id, job.scan_id)
        ]
    written = finish_job(ApiServer(settings=settings, base_url=""), job_id, *sizes)
    return settings, job_id, written


def test_a_job_over_the_setting_opens_from_its_files(stored_job):
    settings, job_id, written = stored_job
    budget = 900
    whole, title = load_job_scene(settings, job_id, point_budget=budget)
    streamed, streamed_title = load_job_scene(
        settings, job_id, point_budget=budget, stream_above_points=0
    )
    assert streamed_title == title
    assert streamed.n_shown <= budget
    for layer in whole.layers:  # the same allocation of the budget, changed points first
        assert streamed.layer(layer.name).n_total == layer.n_total
        assert abs(streamed.layer(layer.name).n_shown - layer.n_shown) <= 1
    changed = streamed.layer("removed").n_shown + streamed.layer("added").n_shown
    assert changed >= budget * CHANGED_SHARE_OF_BUDGET - 2
    for side, cloud in streamed.sides.items():
        np.testing.assert_array_equal(cloud.labels, written[f"{side}_label"][cloud.indices])
    np.testing.assert_allclose(streamed.origin, whole.origin)


def test_a_box_of_a_stored_job(stored_job):
    settings, job_id, _ = stored_job
    whole, _ = load_job_scene(settings, job_id)
    low, high = whole.bounds_min + whole.origin, whole.bounds_max + whole.origin
    box = load_job_box(settings, job_id, low, high, point_budget=50, origin=whole.origin)
    assert box.n_shown <= 50 < box.n_total
    assert [w["code"] for w in box.warnings if w["code"] == "box_capped"] == ["box_capped"]
    np.testing.assert_array_equal(box.origin, whole.origin)
    with pytest.raises(ViewUnavailableError) as refused:
        load_job_box(settings, job_id, high, low)
    assert refused.value.status == 422


def _button_uuid(messages: list[dict], label: str) -> str | None:
    """The uuid of the viser button labelled ``label`` among ``messages``."""
    for message in messages:
        if message["type"] == "GuiButtonMessage" and message["props"]["label"] == label:
            return message["uuid"]
    return None


def _drawn(viewer) -> tuple[int, dict]:
    """Points drawn over the layers for the one browser, and its record (0 and an empty
    record until the viewer has recorded the browser, once its scene is built)."""
    clients = viewer.to_json_dict()["clients"]
    if not clients:
        return 0, {}
    (client,) = clients
    return sum(layer["n_points"] for layer in client["layers"].values()), client


def test_the_box_panel_draws_the_box_and_goes_back(stored_job):
    settings, job_id, _ = stored_job
    manager = ViewerManager(
        partial(load_job_scene, settings),
        box_loader=lambda job, low, high, origin: load_job_box(
            settings, job, low, high, origin=origin
        ),
    )
    try:
        viewer = manager.get(job_id)
        with websockets.sync.client.connect(
            f"ws://127.0.0.1:{viewer.port}",
            subprotocols=[VISER_SUBPROTOCOL],  # type: ignore[list-item]
            additional_headers={VIEW_SECRET_HEADER: viewer.secret},
            max_size=None,
        ) as connection:
            connection.send(camera_message())
            messages = receive_messages(
                connection, lambda got: _button_uuid(got, "Back to the whole view") is not None
            )
            whole_drawn = wait_until(lambda: _drawn(viewer)[0], 30, "nothing drawn")
            _, client = _drawn(viewer)
            low, high = client["controls"]["box_low"], client["controls"]["box_high"]
            box = load_job_box(settings, job_id, low, high, origin=viewer.data.origin)
            assert 0 < box.n_shown < whole_drawn

            def click(label: str) -> None:
                update = _messages.GuiUpdateMessage(_button_uuid(messages, label), {"value": True})
                connection.send(msgspec.msgpack.encode(update.as_serializable_dict()))

            click("Load the box at full density")
            wait_until(lambda: _drawn(viewer)[0] == box.n_shown, 30, "the box was not drawn")
            # the status is set after the points, on the click's thread: wait for it too
            loaded = f"All **{box.n_total:,}** points in the box"
            wait_until(
                lambda: loaded in _drawn(viewer)[1]["controls"]["box_status"],
                10,
                "the box's status does not say it is loaded",
            )
            click("Back to the whole view")
            wait_until(lambda: _drawn(viewer)[0] == whole_drawn, 30, "the whole view is not back")
    finally:
        manager.stop_all()
