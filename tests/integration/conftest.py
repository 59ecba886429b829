"""The integration tests' shared fixtures: the viewer rig's (tests/integration/viewer_rig.py)."""

from tests.integration.viewer_rig import publisher, start_viewer, viewers  # noqa: F401
