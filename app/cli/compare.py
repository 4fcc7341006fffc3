"""``scandiff compare REFERENCE SCAN``: one comparison on the command line.

Exit status 0 on success, 2 on bad input (one line on stderr saying what is wrong).
"""

from __future__ import annotations

import argparse
import atexit
import gc
import importlib
import json
import os
import sys
import tempfile
import threading
import time
from contextlib import ExitStack
from pathlib import Path
from typing import TYPE_CHECKING, Any

from app.cli.compare_report import print_warnings, report
from app.cli.exit_status import EXIT_BAD_INPUT
from app.core.errors import InputError

if TYPE_CHECKING:  # the numeric stack is imported when the command runs, not to build the parser
    from app.core.cloud import PointCloud
    from app.core.pipeline import ComparisonResult
    from app.core.trajectory import Trajectory


BUDGET_NOT_GIVEN = object()
"""``--memory-budget`` left out: the setting's value applies."""
MEMORY_SUFFIXES = {"": 1, "K": 1024, "M": 1024**2, "G": 1024**3, "T": 1024**4}


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    """Register the ``compare`` subcommand."""
    parser = subparsers.add_parser(
        "compare",
        help="compare a scan against a reference scan",
        description="Align SCAN to REFERENCE, decide whether the place changed, and locate "
        "what was removed from the reference and what is new in the scan.",
    )
    parser.add_argument("reference", type=Path, help="reference scan file")
    parser.add_argument("scan", type=Path, help="new scan file")
    _add_detector_and_output_options(parser)
    _add_sensor_options(parser)
    _add_file_options(parser)
    parser.set_defaults(handler=run)


def _add_detector_and_output_options(parser: argparse.ArgumentParser) -> None:
    """The detector, its parameters, and what the command writes."""
    parser.add_argument(
        "--method",
        default="gmm",
        metavar="gmm|pca|planes",
        help="detector (default gmm); the paper's names pca-emd, gmm-emd, pe (pe-emd) work too",
    )
    parser.add_argument(
        "--variant",
        default="improved",
        metavar="improved|paper",
        help="the paper's exact method or the improved one (default)",
    )
    parser.add_argument("--no-align", action="store_true", help="skip registration")
    parser.add_argument("--seed", type=int, default=0, help="random seed (results replay)")
    parser.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    parser.add_argument("--labels", type=Path, metavar="OUT.npz", help="write per-point labels")
    parser.add_argument(
        "--export", type=Path, metavar="OUT.ply|OUT.las", help="write both clouds with labels"
    )
    parser.add_argument(
        "--param",
        action="append",
        default=[],
        metavar="KEY=JSON",
        help="detector parameter, e.g. --param n_components=8 (repeatable)",
    )


def _add_sensor_options(parser: argparse.ArgumentParser) -> None:
    """Where the sensor was: its frame, its origins (one per station), its trajectories."""
    parser.add_argument(
        "--sensor-frame",
        action="store_true",
        help="both files are in their sensor's frame (sensor at 0,0,0): enables the "
        "visibility test that tells occluded from removed",
    )
    parser.add_argument(
        "--sensor-origin",
        action="append",
        default=[],
        metavar="X,Y,Z",
        help="where the sensor stood for REFERENCE, in its file's frame; repeat once per "
        "station for a cloud merged from several stations (in the order of its per-point "
        "station index, if any). Default: the file's own (PCD VIEWPOINT, E57 scan poses, "
        "origin_x/y/z fields), else estimated from the points",
    )
    parser.add_argument(
        "--scan-origin",
        action="append",
        default=[],
        metavar="X,Y,Z",
        help="the same for SCAN (repeatable, one per station)",
    )
    for flag, whose in (("--trajectory", "REFERENCE"), ("--scan-trajectory", "SCAN")):
        parser.add_argument(
            flag,
            type=Path,
            metavar="FILE",
            help=f"the moving sensor's trajectory of {whose}: TUM, KITTI poses or CSV "
            "(time,x,y,z[,qx,qy,qz,qw]); per-point times (gps_time, time, timestamp, t) place "
            "each point's sensor on it, else each point takes its nearest pose in line of sight",
        )
        parser.add_argument(
            f"{flag}-times",
            type=Path,
            metavar="FILE",
            help=f"times of the KITTI poses of {flag} (one a line)",
        )
        parser.add_argument(
            f"{flag}-rate",
            type=float,
            metavar="HZ",
            help=f"constant rate of the KITTI poses of {flag} (poses a second)",
        )


def _add_file_options(parser: argparse.ArgumentParser) -> None:
    """How the files are read: the reference's geometry cache, a ROS bag's parameters."""
    parser.add_argument(
        "--memory-budget",
        type=_memory_size,
        default=BUDGET_NOT_GIVEN,
        metavar="BYTES",
        help="memory the comparison may use (bytes, or with a K/M/G suffix, e.g. 2.5G; "
        "default: SCANDIFF_WORKER_MEMORY_BUDGET_BYTES, else 2.5G; 0 or none: no limit): "
        "a pair that does not fit is compared in tiles; exit 2 when not even one tile fits",
    )
    parser.add_argument(
        "--geometry-cache",
        type=Path,
        metavar="DIR",
        help="keep the reference's neighbourhood geometry (k-NN, fitted surfaces, sensor "
        "origin) in DIR: comparing the same reference again skips that work (files are "
        "checked before use)",
    )
    parser.add_argument(
        "--bag-param",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="how to read a ROS bag (.bag, .db3, .mcap) given as REFERENCE or SCAN: "
        "cloud_topic, fixed_frame, pose_topic, voxel_size (metres, default 0.05), max_sweeps "
        "(repeatable; default: the bag's only PointCloud2 topic, placed by TF or its only "
        "odometry topic)",
    )
    parser.add_argument(
        "--scan-bag-param",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="the same for SCAN only, overriding --bag-param (repeatable)",
    )


def _read_trajectory(args: argparse.Namespace, name: str) -> Trajectory | None:
    """The trajectory of ``--trajectory``/``--scan-trajectory``, if given (read before the
    clouds: a bad trajectory file is refused at once)."""
    from app.core.formats.trajectory_files import read_trajectory

    path, times = getattr(args, name), getattr(args, f"{name}_times")
    rate = getattr(args, f"{name}_rate")
    flag = "--" + name.replace("_", "-")
    if path is None:
        if times is not None or rate is not None:
            raise InputError(f"{flag}-times/{flag}-rate need {flag} FILE (the poses)")
        return None
    for given in (path, times):
        if given is not None and not given.is_file():
            raise InputError(f"no such file: {given}")
    return read_trajectory(path, times=times, rate=rate)


def _with_trajectory(cloud: PointCloud, trajectory: Trajectory | None) -> PointCloud:
    """``cloud`` with ``trajectory`` checked against its per-point times, if one was given."""
    from app.core.trajectory_poses import with_trajectory

    return cloud if trajectory is None else with_trajectory(cloud, trajectory)


def _parse_origins(values: list[str], flag: str) -> list[list[float]] | None:
    """``--sensor-origin``/``--scan-origin`` values as (k, 3) nested lists (None: not given)."""
    import math

    origins = []
    for value in values:
        try:
            numbers = [float(part) for part in value.split(",")]
        except ValueError:
            numbers = []
        if len(numbers) != 3 or not all(math.isfinite(number) for number in numbers):
            raise InputError(
                f"{flag} takes three finite numbers X,Y,Z (e.g. {flag} 12.5,-3,1.4; repeat it "
                f"once per station), got {value!r}"
            )
        origins.append(numbers)
    return origins or None


def _parse_bag_params(pairs: list[str], flag: str) -> dict[str, str]:
    """``--bag-param``/``--scan-bag-param`` values as a dict of strings."""
    values: dict[str, str] = {}
    for pair in pairs:
        key, separator, value = pair.partition("=")
        if not separator or not key:
            raise InputError(
                f"{flag} takes KEY=VALUE (e.g. {flag} cloud_topic=/points), got {pair!r}"
            )
        values[key.strip()] = value.strip()
    return values


def _memory_size(text: str) -> int | None:
    """``--memory-budget``'s value in bytes (``0`` or ``none``: no limit, None)."""
    value = text.strip().upper().removesuffix("B").removesuffix("I")
    if value in ("NONE", "0"):
        return None
    number, suffix = (value[:-1], value[-1]) if value[-1:].isalpha() else (value, "")
    try:
        size = float(number) * MEMORY_SUFFIXES[suffix]
    except (KeyError, ValueError):
        raise argparse.ArgumentTypeError(
            f"not a size in bytes: {text!r} (write e.g. 2684354560, 800M or 2.5G)"
        ) from None
    if not size > 0:
        raise argparse.ArgumentTypeError(f"the memory budget must be positive, got {text!r}")
    return int(size)


def _default_memory_budget() -> int | None:
    """The service's per-worker budget setting (its environment variable or default)."""
    from app.kit.memory_budget import DEFAULT_MEMORY_BUDGET_BYTES, SETTING_VARIABLES

    if not any(name.upper() in SETTING_VARIABLES for name in os.environ):
        # no setting given (another SCANDIFF_* variable, e.g. SCANDIFF_SHARED_DATA, is none):
        # the default, without pydantic's 0.15 CPU s import (Settings() reads nothing else, and
        # would reject none of its defaults)
        return DEFAULT_MEMORY_BUDGET_BYTES
    from app.config import Settings

    return Settings().worker_memory_budget_bytes


def _parse_params(pairs: list[str]) -> dict[str, Any]:
    params: dict[str, Any] = {}
    for pair in pairs:
        key, separator, raw_value = pair.partition("=")
        if not separator or not key:
            raise InputError(f"--param takes KEY=VALUE, got {pair!r}")
        try:
            params[key] = json.loads(raw_value)
        except json.JSONDecodeError:
            params[key] = raw_value
    return params


class _StageProgress:
    """Prints the current stage on stderr when stderr is a terminal."""

    def __init__(self) -> None:
        self.enabled = sys.stderr.isatty()
        self.started = time.perf_counter()

    def __call__(self, stage: str, fraction: float) -> None:
        if self.enabled:
            elapsed = time.perf_counter() - self.started
            print(f"\r[{fraction:4.0%}] {stage:<10} {elapsed:6.1f} s", end="", file=sys.stderr)
            if stage == "done":
                print(file=sys.stderr)


CLI_FIXES_OF_ERRORS = {"skip_alignment": " (--no-align)"}
"""The CLI's flag for each ``how_to_fix`` a core error names."""


def _pipeline_options(args: argparse.Namespace, params: dict[str, Any]) -> dict[str, Any]:
    """The comparison's options from the command line, the same for every path it takes."""
    return {
        "method": args.method,
        "variant": args.variant,
        "align": not args.no_align,
        "random_state": args.seed,
        "params": params,
        "progress": _StageProgress(),
    }


def _export(
    path: Path,
    reference: PointCloud,
    scan: PointCloud,
    result: ComparisonResult,
    frame_offset: Any = None,
) -> None:
    """Write both clouds (scan aligned into the reference frame) with per-point fields
    (clouds read lean are ``frame_offset`` from the files' frame)."""
    import numpy as np

    from app.core.formats import write_point_cloud
    from app.core.pair_export import both_clouds
    from app.core.registration import apply_transform

    transform = np.asarray(result.registration.transform, dtype=np.float64)
    offset = np.zeros(3) if frame_offset is None else frame_offset
    points, fields = both_clouds(
        reference.points + offset,
        apply_transform(scan.points + offset, transform),
        labels=(
            reference.from_source_order(result.reference_label),
            scan.from_source_order(result.scan_label),
        ),
        distances=(
            reference.from_source_order(result.reference_distance),
            scan.from_source_order(result.scan_distance),
        ),
        regions=(
            reference.from_source_order(result.reference_region),
            scan.from_source_order(result.scan_region),
        ),
    )
    write_point_cloud(path, points, fields)


def _geometry_cache(directory: Path | None, reference: Path, params: dict[str, Any]) -> Any:
    """The GeometryCache for ``reference`` in ``directory`` (keyed by the file's SHA-256 and
    the localisation parameters), or None without a directory."""
    if directory is None:
        return None
    import hashlib

    from app.core.cache.geometry import GeometryCache, cache_key

    digest = hashlib.sha256()
    with open(reference, "rb") as source:
        while block := source.read(1 << 20):
            digest.update(block)
    localisation = params.get("localisation")
    key = cache_key(digest.hexdigest(), localisation if isinstance(localisation, dict) else None)
    return GeometryCache(directory / f"{key[:32]}.geometry", key)


def _read_clouds(
    args: argparse.Namespace, budget: int | None
) -> tuple[PointCloud, PointCloud, Any]:
    """Both clouds with their trajectories, read lean when the pair will be tiled
    (:func:`app.core.tiling.lean.read_pair`), and the lean clouds' offset (or None)."""
    from app.core.formats import read_point_cloud
    from app.core.formats.rosbag import bag_options_from_strings
    from app.core.tiling.lean import read_pair

    bag_values = _parse_bag_params(args.bag_param, "--bag-param")
    bags = {
        "reference": bag_options_from_strings(bag_values),
        "scan": bag_options_from_strings(
            {**bag_values, **_parse_bag_params(args.scan_bag_param, "--scan-bag-param")}
        ),
    }
    trajectories = [_read_trajectory(args, name) for name in ("trajectory", "scan_trajectory")]
    paths = {"reference": args.reference, "scan": args.scan}
    importer = _import_ahead(COMPARISON_STACK)
    try:
        reference, scan, frame_offset = read_pair(
            args.reference,
            args.scan,
            lambda side: read_point_cloud(paths[side], bag_options=bags[side]),
            budget,
            allowed=trajectories == [None, None],
        )
    except BaseException:
        if importer is not None:  # an interpreter that exits mid-import can crash (SIGSEGV)
            importer.join()
        raise
    reference = _with_trajectory(reference, trajectories[0])
    return reference, _with_trajectory(scan, trajectories[1]), frame_offset


COMPARISON_STACK = "app.core.tiling.compare"
"""The module whose imports bring in the comparison's stack (the localiser, scipy, small_gicp:
~0.2 CPU s): imported on a thread of its own while the clouds are read (:func:`_import_ahead`)."""


def _import_ahead(module: str) -> threading.Thread | None:
    """Import ``module`` on a daemon thread and return it (None when none can start).

    Reading a pair is mostly numpy copies and file reads, which release the GIL; importing is
    Python, which holds it: the two share the process's first second instead of following each
    other.  The later ``import`` of the module waits for this one (imports hold a lock per
    module); an error is left to that import to raise.  A caller that fails before using it
    joins the thread first: an interpreter finalised while a daemon thread is inside an
    extension module's import can die of SIGSEGV (seen on a refused garbage file).
    """

    def load() -> None:
        try:
            importlib.import_module(module)
        except Exception:  # raised again where the module is used
            return

    thread = threading.Thread(target=load, name="comparison-imports", daemon=True)
    try:
        thread.start()
    except RuntimeError:  # no thread to be had (an address-space cap): imported when used
        return None
    return thread


def run(args: argparse.Namespace) -> int:
    """Run one comparison; exit status 0, or 2 on bad input."""
    from app.kit.allocator import keep_heap_headroom, release_freed_memory_promptly

    release_freed_memory_promptly()
    keep_heap_headroom()
    _skip_the_final_collections()
    cleanup = ExitStack()  # a streamed comparison's work files, removed when it is reported
    try:
        for path in (args.reference, args.scan):
            if not path.is_file():
                raise InputError(f"no such file: {path}")
        for path, allowed in ((args.labels, {".npz"}), (args.export, {".ply", ".las", ".laz"})):
            if path is not None and path.suffix.lower() not in allowed:
                raise InputError(f"{path} must end in one of {', '.join(sorted(allowed))}")
        params = _parse_params(args.param)
        for flag, values, key in (
            ("--sensor-origin", args.sensor_origin, "reference_origin"),
            ("--scan-origin", args.scan_origin, "scan_origin"),
        ):
            origins = _parse_origins(values, flag)
            if origins is None:
                continue
            if key in params or args.sensor_frame:
                given = f"--param {key}" if key in params else "--sensor-frame"
                raise InputError(f"give either {flag} or {given}, not both")
            params[key] = origins[0] if len(origins) == 1 else origins
        if args.sensor_frame:
            params.setdefault("reference_origin", [0.0, 0.0, 0.0])
            params.setdefault("scan_origin", [0.0, 0.0, 0.0])
        budget = (
            _default_memory_budget()
            if args.memory_budget is BUDGET_NOT_GIVEN
            else args.memory_budget
        )
        started = time.perf_counter()
        if _streamed(args, budget):  # the files read in chunks: the pair is never held whole
            work_dir = Path(cleanup.enter_context(tempfile.TemporaryDirectory(prefix="scandiff-")))
            result = _compare_streamed(args, budget, params, work_dir)  # type: ignore[arg-type]
            print_warnings(result)
            report(args, result)
            return 0
        reference, scan, frame_offset = _read_clouds(args, budget)
        load_seconds = time.perf_counter() - started
        # the comparison's stack (scipy, small_gicp: ~0.5 CPU s) once the input is known good
        from app.core.tiling.compare import compare_within_budget

        result = compare_within_budget(
            reference,
            scan,
            budget_bytes=budget,
            frame_offset=frame_offset,
            **_pipeline_options(args, params),
            geometry_cache=_geometry_cache(args.geometry_cache, args.reference, params),
        )
        result.timings["load"] = load_seconds
        if args.labels is not None:
            result.write_labels_npz(args.labels)
        if args.export is not None:
            _export(args.export, reference, scan, result, frame_offset)
    except InputError as exc:
        flag = CLI_FIXES_OF_ERRORS.get(getattr(exc, "how_to_fix", None) or "", "")
        print(f"scandiff: error: {exc}{flag}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except OSError as exc:
        print(f"scandiff: error: {exc.strerror or exc}: {exc.filename or ''}", file=sys.stderr)
        return EXIT_BAD_INPUT
    finally:
        cleanup.close()
    print_warnings(result)
    report(args, result)
    return 0


def _skip_the_final_collections() -> None:
    """Freeze the garbage collector's objects as the process exits (registered once).

    The interpreter's shutdown collects every generation a few times, tracing the numeric
    stack's objects (numpy, scipy, the app's modules): ~0.08 CPU s at the end of a command,
    alone on one core.  Frozen objects are skipped by those collections; they are freed by
    their reference counts all the same, and a cycle among them is left to the process's end.
    """
    atexit.unregister(gc.freeze)
    atexit.register(gc.freeze)


def _streamed(args: argparse.Namespace, budget: int | None) -> bool:
    """Whether the pair is compared streamed (:mod:`app.core.tiling.streamed`): it will be
    tiled under ``budget``, both files carry coordinates only, and nothing needs the clouds
    whole (no trajectory, bag parameters or export)."""
    from app.core.formats.streamed import declared_rows
    from app.core.tiling.pair_files import coordinates_only
    from app.core.tiling.plan import LEAN_RESIDENT_BYTES_PER_POINT, crop_point_limit

    if budget is None or args.export is not None or args.bag_param or args.scan_bag_param:
        return False
    if args.trajectory is not None or args.scan_trajectory is not None:
        return False
    if not all(coordinates_only(path) for path in (args.reference, args.scan)):
        return False
    rows = [declared_rows(path) for path in (args.reference, args.scan)]
    if None in rows:
        return False
    total = sum(rows)  # type: ignore[arg-type]
    return crop_point_limit(budget, total, LEAN_RESIDENT_BYTES_PER_POINT) < total


def _compare_streamed(
    args: argparse.Namespace, budget: int, params: dict[str, Any], work_dir: Path
) -> ComparisonResult:
    """:func:`~app.core.tiling.streamed.compare_streamed` of the command's files; the labels
    written from its output files."""
    from app.core.tiling.pair_files import streamed_outputs, write_labels_npz
    from app.core.tiling.streamed import compare_streamed

    started = time.perf_counter()
    result = compare_streamed(
        args.reference,
        args.scan,
        budget_bytes=budget,
        work_dir=work_dir,
        **_pipeline_options(args, params),
    )
    result.timings["streamed"] = time.perf_counter() - started
    outputs = streamed_outputs(result)
    if args.labels is not None and outputs is not None:
        write_labels_npz(args.labels, outputs)
    return result
