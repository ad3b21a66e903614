"""Capture formats: each format's readers and writers, one module (or, for DynaCap, one sub-package) per format."""
