"""VR frame loop and its backends (OpenVR, desktop, headless)."""


def open_backend(name: str, size=None, rate: float | None = None, realtime: bool = False, recording=None):
    """The backend ``name`` ('openvr', 'desktop' or 'headless'): eyes of ``size`` (W, H; default the headset's,
    else 512x512) at ``rate`` Hz (default the headset's / display's, headless 90); headless frames come from
    ``recording`` or the session's simulated user."""
    if name == "openvr":
        from app.vr.openvr_backend import OpenVRBackend

        return OpenVRBackend(size=size)
    w, h = size or (512, 512)
    if name == "desktop":
        from app.vr.desktop import DesktopBackend

        return DesktopBackend(w, h, target_hz=rate)
    from app.vr.headless import HeadlessBackend

    return HeadlessBackend(recording, target_hz=rate or 90.0, width=w, height=h, realtime=realtime)
