"""deliffas: deformable light-field human avatars (DELIFFAS, NeurIPS 2023) on DynaCap-style captures."""

__version__ = "0.1.0"
