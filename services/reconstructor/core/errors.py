"""Typed errors of the reconstructor core; the bus adapter maps them to ``ErrorReply`` codes."""

from __future__ import annotations


class ReconstructorError(Exception):
    """Base of every reconstructor error."""


class InputError(ReconstructorError, ValueError):
    """The recordings cannot be reconstructed as given (bad request)."""


class EmptyRecordingError(InputError):
    """A region has no frames, or no frame holds a usable measurement."""


class InvalidFrameError(InputError):
    """A frame is malformed: non-finite pose, shapes that disagree with its camera."""


class MissingDepthError(InputError):
    """A backend needs metric depth that the frames do not carry."""


class BackendUnavailableError(ReconstructorError):
    """An optional backend (SLAM3R, Depth-Anything-V2) is not installed or not configured."""


class AlignmentError(ReconstructorError):
    """Cross-modal metric alignment failed (no candidate frame, too few valid pixels)."""


class MapStoreError(ReconstructorError):
    """The map store could not complete an operation."""


class MapNotFoundError(MapStoreError, KeyError):
    """No such map, or no such version of it."""

    def __str__(self) -> str:  # KeyError quotes its message
        return self.args[0] if self.args else ""


class InvalidMapIdError(MapStoreError, ValueError):
    """A map id that is not a single valid key segment."""


class MapFormatError(MapStoreError, ValueError):
    """An imported or stored cloud file cannot be read, or holds no usable points."""
