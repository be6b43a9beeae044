"""The one error every ingestion path raises on bad input."""

from __future__ import annotations


class IngestError(ValueError):
    """A scene source that cannot be read: missing, unknown format, corrupt or inconsistent."""
