"""Captures as ``Subject`` records: the record, the format registry, and the built-in formats.

Built-in formats (each one module that registers itself): ``dynacap``, ``zju`` (ZJU-MoCap), ``easymocap``,
``thuman4`` (THuman4.0 / AvatarReX), ``dna`` (DNA-Rendering ``.smc``) and ``actorshq``. Parse a capture with
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
from deliffas.data.subjects.zju_mocap import parse_zju_mocap
from deliffas.data.subjects.easymocap import parse_easymocap
from deliffas.data.subjects.thuman4 import parse_thuman4
from deliffas.data.subjects.dna_rendering import parse_dna_rendering
from deliffas.data.subjects.actorshq import parse_actorshq

__all__ = [
    "FrameSourceSpec", "Subject", "SubjectOptions", "SubjectParser", "SubjectSequence", "parse_subject",
    "register_subject_format", "subject_formats", "SEQUENCES", "find_character", "parse_dynacap",
    "parse_zju_mocap", "parse_easymocap", "parse_thuman4", "parse_dna_rendering", "parse_actorshq",
]
