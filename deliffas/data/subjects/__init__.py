"""Captures as ``Subject`` records: the record, ``parse_subject``, and each built-in format's subject part.

Each module here registers the subject parser (and, for SMPL captures, the exporter) of one capture
format with ``deliffas.io.format_registry.register_capture_format``; importing this package imports
them. Parse a capture with ``parse_subject(folder, format="auto")`` (docs/architecture.md: how to add
a format).
"""

from deliffas.data.subjects.base import (
    FrameSourceSpec,
    Subject,
    SubjectOptions,
    SubjectSequence,
    parse_subject,
    subject_format_names,
)
from deliffas.data.subjects.dynacap import SEQUENCES, find_character, parse_dynacap
from deliffas.data.subjects.zju_mocap import parse_zju_mocap
from deliffas.data.subjects.easymocap import parse_easymocap
from deliffas.data.subjects.thuman4 import parse_thuman4
from deliffas.data.subjects.dna_rendering import parse_dna_rendering
from deliffas.data.subjects.actorshq import parse_actorshq

__all__ = [
    "FrameSourceSpec", "Subject", "SubjectOptions", "SubjectSequence", "parse_subject", "subject_format_names",
    "SEQUENCES", "find_character", "parse_dynacap",
    "parse_zju_mocap", "parse_easymocap", "parse_thuman4", "parse_dna_rendering", "parse_actorshq",
]
