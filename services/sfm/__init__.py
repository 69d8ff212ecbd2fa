"""Aerial structure from motion: reconstruction (aerial.py), georeferencing, report and GeoJSON."""

from .aerial import SfmError, confs, main
from .georef import Georef, GeorefError

__all__ = ["Georef", "GeorefError", "SfmError", "confs", "main"]
