"""Recipes: one script per ablation of the paper and the studies around it (``python -m recipes.<name>``)."""
