"""Deformable templates, skinning, shells, UV atlases, normal maps and ray casting."""
