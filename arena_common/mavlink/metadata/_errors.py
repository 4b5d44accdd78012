"""Errors of the metadata fetch."""

from __future__ import annotations

from arena_common.core.errors import ArenaError


class MetadataError(ArenaError):
    """PX4's parameter metadata could not be obtained; the message names what failed and where."""


class MetadataTimeout(MetadataError):
    """The vehicle did not answer in time (after retries): names the request, the system and component."""


class MetadataFormatError(MetadataError, ValueError):
    """A metadata file that is not what PX4 publishes (not xz/JSON, no parameters, malformed entry)."""
