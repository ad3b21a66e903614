"""File formats: every reader and writer of deliffas, returning plain records.

The bottom layer: modules here import no other deliffas layer (only the shared leaves
``deliffas.checks`` and ``deliffas.native``). Units stay as the files have them; each reader's
docstring states them.
"""
