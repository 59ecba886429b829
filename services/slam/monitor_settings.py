"""Moved: :class:`MonitorSettings` lives in :mod:`services.slam.settings`.

Kept only for ``monitor_service.py``'s import until it imports from the new place.
"""

from services.slam.settings import MonitorSettings

__all__ = ["MonitorSettings"]
