"""Scenes and light: built-in and XML scenes, camera paths and viewer rigs, the G-buffer, light sampling."""
