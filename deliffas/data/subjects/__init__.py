"""Captures as ``Subject`` records: the record, the format registry, and the built-in formats.

Built-in formats (each one module that registers itself): ``dynacap``. Parse a capture with
``parse_subject(folder, format="auto")`` (docs/architecture.md: how to add a format).
"""

from deliffas.data.subjects.base import (
    FrameSourceSpec,
    Subject,
    SubjectOptions,
    SubjectParser,
    SubjectSequence,
    parse_subject,
    register_subject_format,
    subject_formats,
)
from deliffas.data.subjects.dynacap import SEQUENCES, find_character, parse_dynacap

__all__ = [
    "FrameSourceSpec", "Subject", "SubjectOptions", "SubjectParser", "SubjectSequence", "parse_subject",
    "register_subject_format", "subject_formats", "SEQUENCES", "find_character", "parse_dynacap",
]
