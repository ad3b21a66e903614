"""``deliffas ingest``: a raw calibrated multi-view recording -> a subject with masks and a fitted body per frame.

:func:`ingest` with an :class:`IngestConfig` is the API the command calls (docs/own-recording.md):
``from deliffas.data.ingest import IngestConfig, ingest``. The config is light (the command line reads it
without torch); ``ingest`` and ``IngestResult`` are imported from :mod:`.pipeline` when first used.
"""

from deliffas.data.ingest.config import INGEST_MARKER, IngestConfig

__all__ = ["IngestConfig", "IngestResult", "ingest", "INGEST_MARKER"]


def __getattr__(name: str):
    if name in ("ingest", "IngestResult"):
        from deliffas.data.ingest import pipeline  # start-up time: the config must not import torch

        return getattr(pipeline, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
