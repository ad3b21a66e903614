"""Training, evaluation, rendering and per-stage timing."""
