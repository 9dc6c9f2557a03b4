"""Scenes and light: built-in and XML scenes, camera paths and viewer rigs, the G-buffer, light sampling."""
from slc.core import backend

backend.ensure()  # the modules of this package build Mitsuba types on import

