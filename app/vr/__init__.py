"""VR frame loop and its backends (OpenVR, desktop, headless)."""
