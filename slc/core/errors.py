"""The one-line errors of bad input that need no Mitsuba variant to be named: the command line
catches them before it has chosen one (exit status 2)."""
from __future__ import annotations


class SceneError(ValueError):
    """A scene cannot be loaded (one-line reason for the user)."""


class MethodError(ValueError):
    """Unknown method name or bad method settings (one-line message)."""
