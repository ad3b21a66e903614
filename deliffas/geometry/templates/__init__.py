"""Deformable templates: the ``Template`` protocol, recorded specs, and the registry of template kinds.

Built-in kinds (each one module that registers its ``TemplateKind``): ``ddc`` (skeleton + skin, LBS/DQS),
``ddc_graph`` (DDC posing through the embedded graph) and ``smpl`` (a user's SMPL model file).
Build templates with ``build_template(spec)``; make specs with ``ddc_spec``, ``ddc_graph_spec`` or
``smpl_spec`` (docs/architecture.md: how to add a kind).
"""

from deliffas.geometry.templates.base import (
    Template,
    TemplateBuilder,
    TemplateKind,
    TemplateSourceError,
    TemplateSpec,
    build_template,
    make_spec,
    register_template_kind,
    template_kind,
    template_kinds,
)
from deliffas.geometry.templates.ddc import DDCTemplate, Skinning, ddc_sources, ddc_spec
from deliffas.geometry.templates.ddc_graph import Deformation, EmbeddedGraphTemplate, ddc_graph_spec
from deliffas.geometry.templates.smpl import SMPLTemplate, smpl_spec
from deliffas.geometry.templates.from_file import SMPL_MODEL_SUFFIXES, spec_from_file

__all__ = [
    "Template", "TemplateBuilder", "TemplateKind", "TemplateSourceError", "TemplateSpec", "build_template",
    "make_spec", "register_template_kind", "template_kind", "template_kinds",
    "DDCTemplate", "Skinning", "ddc_sources", "ddc_spec",
    "EmbeddedGraphTemplate", "Deformation", "ddc_graph_spec",
    "SMPLTemplate", "smpl_spec", "SMPL_MODEL_SUFFIXES", "spec_from_file",
]
