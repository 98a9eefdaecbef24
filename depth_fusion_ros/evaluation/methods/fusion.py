"""Evaluation methods of the fusion stage (registered on import)."""
