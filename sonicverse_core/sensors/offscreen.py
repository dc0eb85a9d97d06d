"""pyrender's offscreen renderer as the cameras and the VR views drive it (EGL: Mesa llvmpipe on a CPU, the GPU's
driver where there is one): single-sampled and colour-only framebuffers, the lit shader's shadow bias, and freeing a
renderer's GL objects and EGL context without ending the EGL display every context of the process shares. Each
adapts a private part of pyrender 0.1.45, pinned in requirements.txt; tests cover them (``tests/test_look.py``,
``tests/test_vr.py``, ``tests/test_world.py``)."""
from __future__ import annotations

import os

import numpy as np

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

from sonicverse_core.errors import ConfigError  # noqa: E402


def _colour_only_reader(self, scene, flags):
    """pyrender's read-back without the depth image (a display needs none): resolve, read RGB, flip."""
    from OpenGL import GL

    w, h = self._main_fb_dims
    if self._ms:
        GL.glBindFramebuffer(GL.GL_READ_FRAMEBUFFER, self._main_fb_ms)
        GL.glBindFramebuffer(GL.GL_DRAW_FRAMEBUFFER, self._main_fb)
        GL.glBlitFramebuffer(0, 0, w, h, 0, 0, w, h, GL.GL_COLOR_BUFFER_BIT, GL.GL_NEAREST)
        GL.glBindFramebuffer(GL.GL_READ_FRAMEBUFFER, self._main_fb)
    else:
        GL.glBindFramebuffer(GL.GL_READ_FRAMEBUFFER, self._main_fb_ms)
    buf = GL.glReadPixels(0, 0, w, h, GL.GL_RGB, GL.GL_UNSIGNED_BYTE)
    return np.flip(np.frombuffer(buf, np.uint8).reshape(h, w, 3), 0), None


def _single_sample_framebuffer(self):
    """pyrender's framebuffer set-up with plain (single-sample) storage under the multisample names: the draw and
    the read target are then the same."""
    import pyrender.renderer as _pr
    from OpenGL import GL

    orig = _pr.glRenderbufferStorageMultisample
    _pr.glRenderbufferStorageMultisample = lambda tgt, n, fmt, w, h: GL.glRenderbufferStorage(tgt, fmt, w, h)
    try:
        return _pr.Renderer._configure_main_framebuffer(self)
    finally:
        _pr.glRenderbufferStorageMultisample = orig


def offscreen_renderer(width: int, height: int, msaa: bool = True, colour_only: bool = False):
    """A pyrender OffscreenRenderer; ``msaa=False`` draws single-sampled, ``colour_only`` skips the depth read-back.
    (Both adapt pyrender 0.1.45's private framebuffer methods, pinned in requirements.txt; tests cover them.)"""
    import types

    import pyrender

    r = pyrender.OffscreenRenderer(width, height)
    keep_display_on_delete(r)
    inner = r._renderer
    inner._ms = msaa
    if not msaa:
        inner._configure_main_framebuffer = types.MethodType(_single_sample_framebuffer, inner)
    if colour_only:
        inner._read_main_framebuffer = types.MethodType(_colour_only_reader, inner)
    return r


#: the lit path's shadow bias (pyrender 0.1.45's mesh.frag: 0.001 x (1 - n.l), min 0.0001, which shows shadow acne as
#: stripes on walls a lamp grazes)
SHADOW_BIAS = (0.012, 0.0015)


def pbr_shader_dir() -> str:
    """pyrender's shaders with the lit shader's shadow bias raised (:data:`SHADOW_BIAS`), written once to the cache
    folder; everything else as pyrender ships it."""
    import hashlib
    from pathlib import Path

    import pyrender

    from assets_manifest import cache_dir

    src = Path(pyrender.__file__).parent / "shaders"
    frag = (src / "mesh.frag").read_text()
    old = "float bias = max(0.001 * (1.0 - nl), 0.0001) / proj_coords.w;"
    if old not in frag:
        raise ConfigError("this pyrender's mesh.frag has no shadow bias line to raise (pyrender 0.1.45 is pinned)")
    frag = frag.replace(old, f"float bias = max({SHADOW_BIAS[0]} * (1.0 - nl), {SHADOW_BIAS[1]}) / proj_coords.w;")
    out = cache_dir() / "shaders" / hashlib.sha256(frag.encode()).hexdigest()[:16]
    if not (out / "mesh.frag").exists():
        out.mkdir(parents=True, exist_ok=True)
        from sonicverse_core.storage import write_text_atomic

        for f in src.iterdir():
            if f.name != "mesh.frag" and f.is_file():
                write_text_atomic(out / f.name, f.read_text())
        write_text_atomic(out / "mesh.frag", frag)
    return str(out)


def use_pbr_shaders(renderer) -> None:
    """Make a pyrender OffscreenRenderer compile its programs from :func:`pbr_shader_dir` (before its first
    render)."""
    renderer._renderer._program_cache.shader_dir = pbr_shader_dir()


def _delete_gl_objects_once(self) -> None:
    """pyrender 0.1.45's ``Renderer.delete`` frees the GL objects and forgets them, but for the shadow framebuffer,
    whose id it keeps; and ``Renderer.__del__`` calls ``delete`` again. When the garbage collector takes a renderer
    that was deleted (a closed camera's, in a reference cycle), that second call deleted framebuffer 1 in whichever
    context was current: inside another lit camera's frame, that camera's shadow framebuffer, so its frames failed
    (glBindFramebuffer: invalid operation; invalid framebuffer operation where it was bound at the time). Here the
    first call frees everything and later ones do nothing."""
    if self.__dict__.get("_gl_deleted"):
        return
    self._gl_deleted = True
    import pyrender.renderer as _pr

    _pr.Renderer.delete(self)
    self._shadow_fb = None


def keep_display_on_delete(renderer) -> None:
    """pyrender's EGL platform terminates the EGL display when its context is deleted, and the display is shared by
    every context of the process. That also happens when the garbage collector takes a renderer nobody closed (an
    env dropped without ``close()``, as in a notebook): every other env's camera then failed on its next frame
    (glBindFramebuffer: invalid operation). Here deleting a renderer's context destroys that context only, and its
    GL objects are freed once (:func:`_delete_gl_objects_once`)."""
    import types

    inner = getattr(renderer, "_renderer", None)
    if inner is not None and "delete" not in inner.__dict__:
        inner.delete = types.MethodType(_delete_gl_objects_once, inner)
    platform = getattr(renderer, "_platform", None)
    if platform is None or not hasattr(platform, "_egl_display"):  # not EGL
        return

    def delete_context(self):
        from OpenGL.EGL import (EGL_NO_CONTEXT, EGL_NO_SURFACE, eglDestroyContext, eglGetCurrentContext,
                                eglMakeCurrent)

        if self._egl_display is not None and self._egl_context is not None:
            if eglGetCurrentContext() == self._egl_context:
                eglMakeCurrent(self._egl_display, EGL_NO_SURFACE, EGL_NO_SURFACE, EGL_NO_CONTEXT)
            eglDestroyContext(self._egl_display, self._egl_context)
            self._egl_context = None
        self._egl_display = None

    platform.delete_context = types.MethodType(delete_context, platform)


def release_offscreen(renderer) -> None:
    """Free a pyrender OffscreenRenderer's GL objects and destroy its own EGL context, leaving the EGL display
    initialised (:func:`keep_display_on_delete`: pyrender's ``delete()`` would terminate the display every context
    of the process shares, and its ``gc.collect()`` is not needed here)."""
    platform = getattr(renderer, "_platform", None)
    if platform is None:  # already released
        return
    keep_display_on_delete(renderer)  # a stock renderer too
    if not hasattr(platform, "_egl_display"):  # not EGL
        renderer.delete()
        return
    platform.make_current()
    renderer._renderer.delete()
    platform.delete_context()
    renderer._renderer = None
    renderer._platform = None
