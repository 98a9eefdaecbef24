"""Importing this package registers every evaluation method, one module per stage."""

from . import adapted, baselines, fusion, mapping, multi_view, recorded, single_view  # noqa: F401
