"""Reusable computation units for dyknow, each with a transformation spec in ``specs/``."""
