"""What ``check_capture`` reads, scores and writes (:class:`CheckCaptureConfig`); light, so the CLI reads it
without torch."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from deliffas.data.check_config import CheckConfig
from deliffas.data.subject_options import SubjectOptions
from deliffas.options import opt

__all__ = ["CheckCaptureConfig"]


@dataclass(frozen=True)
class CheckCaptureConfig:
    """A capture folder's silhouette check with its report (:func:`deliffas.data.check_report.check_capture`)."""

    subject: Path = opt(help="capture folder (any supported format)", flag="")
    out: Path = opt(help="report folder (report.md, overlays/, summary.json)")
    format: str = opt("auto", help="capture format (auto = detected)", default_text="detected")
    check: CheckConfig = field(default_factory=CheckConfig)
    """What is sampled and how it is scored (its own options)."""
    subject_options: SubjectOptions = field(default_factory=SubjectOptions)
    """How the capture is read (its own options)."""
