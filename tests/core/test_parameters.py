"""The core's one parameter validator, as the detectors, localisation and the pipeline use it."""

from __future__ import annotations

import re

import numpy as np
import pytest

from app.core.comparison_settings import parse_comparison_params
from app.core.detectors import make_detector
from app.core.errors import InputError
from app.core.localise.settings import resolve_parameters
from app.core.parameters import ParamSpec, validate_parameters


@pytest.mark.parametrize(
    ("call", "message"),
    [
        (
            lambda: make_detector("gmm", "paper", covariance_floor=0.1),
            "unknown parameter(s) ['covariance_floor'] for the 'gmm' detector (variant 'paper');"
            " valid: ['calibration', 'false_alarm_rate', 'max_iter', 'max_points', "
            "'n_components', 'n_resamples', 'random_state', 'variant', 'voxel_size']",
        ),
        (lambda: make_detector("gmm", n_components=0), "n_components must be >= 1, got 0"),
        (lambda: make_detector("pca", voxel_size="big"), "voxel_size must be a number, got 'big'"),
        (
            lambda: resolve_parameters({"n_neighbours": 5}),
            "unknown localisation parameter(s) ['n_neighbours']; valid: ['cluster_factor', "
            "'coverage_factor', 'min_change_distance', 'n_neighbors', 'origin_free_test', "
            "'support_factor', "
            "'threshold_factor', "
            "'visibility_angle_factor', 'visibility_beyond_fraction', "
            "'visibility_margin_factor', 'visibility_miss_factor']",
        ),
        (
            lambda: resolve_parameters({"threshold_factor": -1}),
            "threshold_factor must be a positive number, got -1",
        ),
        (
            lambda: resolve_parameters({"cluster_factor": True}),
            "cluster_factor must be a positive number, got True",
        ),
        (
            lambda: resolve_parameters({"n_neighbors": 2.0}),
            "n_neighbors must be an integer >= 3, got 2.0",
        ),
        (
            lambda: resolve_parameters({"visibility_beyond_fraction": 1.5}),
            "visibility_beyond_fraction must be in (0, 1], got 1.5",
        ),
        (
            lambda: parse_comparison_params("gmm", "improved", {"registration": {"voxel": 1}}),
            "unknown registration parameter(s) ['voxel']; valid: ['initial_transform', "
            "'max_correspondence_distance', 'min_fitness', 'num_threads', 'voxel_size']",
        ),
    ],
)
def test_each_user_of_the_validator_names_the_bad_parameter(call, message):
    with pytest.raises(InputError, match=re.escape(message) + "$"):
        call()


def test_values_are_normalised_and_defaults_checked():
    settings = resolve_parameters({"n_neighbors": 12.0, "threshold_factor": 3})
    assert settings["n_neighbors"] == 12 and isinstance(settings["n_neighbors"], int)
    assert settings["threshold_factor"] == 3.0 and isinstance(settings["threshold_factor"], float)
    assert settings["support_factor"] is None
    specs = {"size": ParamSpec("int", 1, 10), "anything": ParamSpec("any")}
    assert validate_parameters(specs, {"size": np.int64(3)}) == {"size": 3}
    assert validate_parameters(specs, {"anything": [1]}, defaults={"size": 2, "anything": 0}) == {
        "size": 2,
        "anything": [1],
    }
    with pytest.raises(InputError, match="size must be <= 10"):
        validate_parameters(specs, {}, defaults={"size": 11, "anything": None})
    with pytest.raises(ValueError, match="kind"):
        ParamSpec("integer")
