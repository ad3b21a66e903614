"""deliffas: deformable light-field human avatars (DELIFFAS, NeurIPS 2023): templates, captures, models, engine."""

__version__ = "0.2.0"
