"""Arrays in, arrays out: templates (registry), skinning, shells, UV atlases, normal maps, ray casting,
texture sampling and procedural bodies (the layer above io)."""
