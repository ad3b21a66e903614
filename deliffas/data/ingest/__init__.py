"""``deliffas ingest``: a raw calibrated multi-view recording -> a subject with masks and a fitted body per frame.

:func:`ingest` with an :class:`IngestConfig` is the API the command calls (docs/own-recording.md):
``from deliffas.data.ingest import IngestConfig, ingest``. The config is light (the command line reads it
without torch); ``ingest`` and ``IngestResult`` are imported from :mod:`.pipeline` when first used.
"""

from deliffas.data.ingest.config import INGEST_MARKER, IngestConfig
from deliffas.optional import lazy_exports

__all__ = ["IngestConfig", "IngestResult", "ingest", "INGEST_MARKER"]


# start-up time: the config must not import torch; the pipeline is imported when first used
__getattr__, _ = lazy_exports(__name__, {"ingest": "deliffas.data.ingest.pipeline",
                                          "IngestResult": "deliffas.data.ingest.pipeline"})
