"""The typed errors of the core; each message is meant for the user who sent the input."""

from collections.abc import Callable

# A function the core polls during long work; when it returns True the work raises Cancelled.
CancelCheck = Callable[[], bool]


class EdgereconError(Exception):
    """Base class of every error the core raises on purpose."""


class PointCloudError(EdgereconError, ValueError):
    """The input is not a usable point cloud (bad PLY, non-finite values, too few points...)."""


class EmptySurfaceError(EdgereconError):
    """The fitted function has no zero level set inside the shape's box: there is no mesh."""


class Cancelled(EdgereconError):
    """The caller asked the fit to stop (the cancel check returned True)."""


def check_cancel(should_cancel: CancelCheck | None) -> None:
    """Raise ``Cancelled`` if ``should_cancel`` is given and returns True."""
    if should_cancel is not None and should_cancel():
        raise Cancelled("the reconstruction was cancelled")
