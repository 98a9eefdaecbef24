"""Evaluation methods of the single_view stage (registered on import)."""
