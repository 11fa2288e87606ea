"""Exceptions raised by :mod:`core`.

Every error that bad input can cause is an :class:`InputError`; the service maps it to an
HTTP 4xx problem document and the CLI to a non-zero exit with the message.
"""

from __future__ import annotations


class RegistrationError(Exception):
    """Base class of every error raised on purpose by :mod:`core`."""


class InputError(RegistrationError, ValueError):
    """The input (images, points or options) cannot be registered.

    Parameters
    ----------
    message : str
        Human-readable reason, naming what is wrong and what is expected.
    field : str, optional
        Name of the input the error is about (``reference``, ``moving``, ``points``,
        ``options.<name>``), so that an API can point at it.
    """

    def __init__(self, message: str, field: str | None = None) -> None:
        super().__init__(message)
        self.field = field


class NotEnoughPointsError(InputError):
    """Too few consistent conjugate point pairs to build a mesh.

    Parameters
    ----------
    found : int
        Number of usable pairs.
    needed : int
        Minimum number of pairs required.
    stage : str
        Stage at which the pairs ran out (e.g. ``"matching"``, ``"epipolar filter"``).
    """

    def __init__(self, found: int, needed: int, stage: str, field: str | None = "points") -> None:
        super().__init__(
            f"only {found} consistent conjugate point pairs after {stage}; at least {needed} "
            "are needed",
            field=field,
        )
        self.found = found
        self.needed = needed
        self.stage = stage


class UnsupportedMediaError(InputError):
    """The bytes are not an image in a supported format (PNG, JPEG, TIFF, PNM, BMP)."""


class ImageTooLargeError(InputError):
    """The image has more pixels (or a longer side) than allowed; refused before decoding."""


class UnreliableResultError(RegistrationError):
    """The registration ran but its quality verdict is ``unreliable`` and the caller asked for
    such a result to fail (option ``on_unreliable="fail"``).

    Parameters
    ----------
    quality : dict
        The verdict, its reasons and figures (:meth:`core.quality.Quality.to_dict`).
    """

    def __init__(self, quality: dict) -> None:
        reasons = "; ".join(quality.get("reasons", [])) or "no reason recorded"
        super().__init__(f"the registration is unreliable: {reasons}")
        self.quality = quality
