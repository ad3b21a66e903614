"""Pipelines over captures: capture formats parsed into Subjects, synthetic captures, conversion to HDF5
shards and the streaming dataset (the layer above geometry; it never imports models)."""
