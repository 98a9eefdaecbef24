"""Evaluation methods of the multi_view stage (registered on import)."""
