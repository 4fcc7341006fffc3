"""The error types of the numeric core.

Every problem with the *input* (a malformed file, a cloud with too few points, two scans that
do not overlap) raises a subclass of :class:`InputError` whose message says what is wrong and,
where possible, what to do about it.  Callers (the CLI, the service) turn these into exit
status 2 or an HTTP 4xx; anything else escaping the core is a bug.
"""


class InputError(ValueError):
    """Base class: the caller's input cannot be used; the message says why."""


class PointCloudError(InputError):
    """A point cloud file or array is malformed, empty or otherwise unusable.

    Raised by every reader in :mod:`app.core.formats` and by :class:`app.core.cloud.PointCloud`
    validation: truncated bodies, count mismatches, unknown field types, missing x/y/z, no finite
    points, too few points, unknown format.
    """


class PointLimitError(PointCloudError):
    """A cloud has more points than the caller's limit allows.

    ``limit_name`` names the limit as the core knows it (``"max_points"``); the interface that
    set the limit names its own knob for it (the service: ``SCANDIFF_MAX_POINTS``).
    """

    def __init__(self, message: str, *, limit_name: str = "max_points") -> None:
        super().__init__(message)
        self.limit_name = limit_name


class UnsupportedFormatError(PointCloudError):
    """The content is not any supported point-cloud format (the service answers 415)."""


class RegistrationError(InputError):
    """The scan cannot be aligned to the reference (e.g. the clouds do not overlap).

    ``how_to_fix`` names the fix without an interface's words (``"skip_alignment"``): the
    interface that reports the error names its own knob for it.
    """

    how_to_fix = "skip_alignment"
