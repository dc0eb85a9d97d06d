"""pyrender's offscreen renderer as the cameras and the VR views drive it (EGL: Mesa llvmpipe on a CPU, the GPU's
driver where there is one): single-sampled and colour-only framebuffers, the lit shader's shadow bias, and freeing a
renderer's GL objects and EGL context (released first, the thread's binding given back) without ending the EGL
display every context of the process shares. Each
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


def _handle(ptr) -> int:
    """An EGL handle's address (PyOpenGL wraps each handle it returns in a new object, so ``==`` on two wrappers of
    the same context is False)."""
    import ctypes

    if ptr is None:
        return 0
    return ctypes.cast(ptr, ctypes.c_void_p).value or 0


def current_egl_context() -> int:
    """The address of the EGL context current on this thread (0: none)."""
    from OpenGL.EGL import eglGetCurrentContext

    return _handle(eglGetCurrentContext())


def _bound():
    """This thread's EGL binding: (display, draw surface, read surface, context), or None when none is current."""
    from OpenGL.EGL import EGL_DRAW, EGL_READ, eglGetCurrentContext, eglGetCurrentDisplay, eglGetCurrentSurface

    ctx = eglGetCurrentContext()
    if not _handle(ctx):
        return None
    return eglGetCurrentDisplay(), eglGetCurrentSurface(EGL_DRAW), eglGetCurrentSurface(EGL_READ), ctx


def _delete_context(self) -> None:
    """Destroy this platform's EGL context, not the display every context of the process shares; the context is
    released first: EGL only marks a context destroyed while current, and frees it inside whichever
    ``eglMakeCurrent`` comes next, in another renderer's set-up (the likely cause of ``bench camera``'s rare abort
    with a corrupted heap in a new camera's first frames; README, "A crash in native code")."""
    from OpenGL.EGL import EGL_NO_CONTEXT, EGL_NO_SURFACE, eglDestroyContext, eglMakeCurrent

    if self._egl_display is not None and self._egl_context is not None:
        if current_egl_context():
            eglMakeCurrent(self._egl_display, EGL_NO_SURFACE, EGL_NO_SURFACE, EGL_NO_CONTEXT)
        eglDestroyContext(self._egl_display, self._egl_context)
        self._egl_context = None
    self._egl_display = None


def _delete_offscreen(self) -> None:
    """``OffscreenRenderer.delete`` (also its ``__del__``, when the garbage collector takes a renderer nobody closed)
    that frees this renderer's GL objects in its own context, destroys that context only (:func:`_delete_context`)
    and then gives the thread back the context that was current before: the collector runs inside other renderers'
    frames, and pyrender's own ``delete`` left the collected renderer's context current there, so the rest of that
    frame drew into a destroyed context."""
    from OpenGL.EGL import eglMakeCurrent

    platform = self.__dict__.get("_platform")
    if platform is None:  # already deleted
        return
    saved = _bound()
    own = saved is not None and _handle(saved[3]) == _handle(platform._egl_context)
    try:
        platform.make_current()
        if self._renderer is not None:
            self._renderer.delete()
        platform.delete_context()
    finally:
        self._renderer = None
        self._platform = None
        if saved is not None and not own:
            eglMakeCurrent(*saved)


def keep_display_on_delete(renderer) -> None:
    """pyrender's EGL platform terminates the EGL display when its context is deleted, and the display is shared by
    every context of the process. That also happens when the garbage collector takes a renderer nobody closed (an
    env dropped without ``close()``, as in a notebook): every other env's camera then failed on its next frame
    (glBindFramebuffer: invalid operation). Here deleting a renderer frees its GL objects once
    (:func:`_delete_gl_objects_once`), destroys its own context only, released first (:func:`_delete_context`), and
    leaves current the context that was (:func:`_delete_offscreen`)."""
    import types

    inner = getattr(renderer, "_renderer", None)
    if inner is not None and "delete" not in inner.__dict__:
        inner.delete = types.MethodType(_delete_gl_objects_once, inner)
    platform = getattr(renderer, "_platform", None)
    if platform is None or not hasattr(platform, "_egl_display"):  # not EGL
        return
    platform.__class__ = _keeping_display(type(platform), "delete_context", _delete_context)
    renderer.__class__ = _keeping_display(type(renderer), "delete", _delete_offscreen)


_CLASSES: dict = {}


def _keeping_display(base, name: str, method):
    """``base`` (pyrender's EGLPlatform or OffscreenRenderer) with ``method`` as its ``name``: a subclass, so that no
    bound method kept in an instance makes a reference cycle (its clean-up then waits for the collector)."""
    if getattr(base, "_keeps_display", False):
        return base
    if base not in _CLASSES:
        _CLASSES[base] = type(base.__name__, (base,), {name: method, "_keeps_display": True, "__module__": __name__})
    return _CLASSES[base]


def release_offscreen(renderer) -> None:
    """Free a pyrender OffscreenRenderer's GL objects and destroy its own EGL context, leaving the EGL display
    initialised and this thread's binding as it was (:func:`keep_display_on_delete`: pyrender's ``delete()`` would
    terminate the display every context of the process shares, and its ``gc.collect()`` is not needed here)."""
    if getattr(renderer, "_platform", None) is None:  # already released
        return
    keep_display_on_delete(renderer)  # a stock renderer too
    renderer.delete()
