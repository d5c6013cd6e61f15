"""MuJoCo's OpenGL platform (``MUJOCO_GL``), checked once when a command that renders starts.

MuJoCo reads ``MUJOCO_GL`` when it first builds a renderer, and a wrong one fails late and noisily:
a bad name is a RuntimeError from inside MuJoCo, a platform whose library is missing fails in
PyOpenGL's import, and each leaves a half-built ``mujoco.Renderer`` whose teardown prints more
tracebacks; some of these already fail MuJoCo's import. :func:`check_gl_platform` settles the
platform before a simulator that renders through OpenGL is imported (``get_simulator``: an unset
or empty ``MUJOCO_GL`` becomes ``egl``, the headless one), refuses what cannot work in one line
that lists the choices or names what to install, and, once at the start of a command that renders,
draws one tiny frame to prove the choice. :func:`quiet_teardown` keeps a renderer that fails later from printing its teardown.
"""

from __future__ import annotations

import contextlib
import ctypes.util
import gc
import os
import sys
import warnings
from dataclasses import dataclass


@dataclass(frozen=True)
class GLPlatform:
    """One value of ``MUJOCO_GL`` that renders without a window, or with one."""

    library: str | None
    """The shared library it loads (``ctypes.util.find_library`` name); None: bundled."""
    install: str
    """What provides it (Debian's packages)."""
    display: bool = False
    """Whether it opens a window (then it needs ``DISPLAY`` or ``WAYLAND_DISPLAY``)."""


GL_PLATFORMS = {
    "egl": GLPlatform("EGL", "apt-get install libegl1 libegl-mesa0 (scripts/bootstrap.sh does)"),
    "osmesa": GLPlatform("OSMesa", "apt-get install libosmesa6"),
    "glfw": GLPlatform(None, "a display (an X or Wayland session)", display=True),
}
"""The platforms stepnft renders with, the first the default: ``egl`` renders offscreen (Mesa's
CPU renderer here, a GPU's driver where there is one), ``osmesa`` offscreen in software, ``glfw``
through a window."""
DEFAULT_GL = "egl"


class GLPlatformError(ValueError):
    """A ``MUJOCO_GL`` (or ``PYOPENGL_PLATFORM``) that cannot render here: one line, exit 2."""


def check_gl_platform(renders: bool = True) -> str:
    """The GL platform this process will render with, set in ``MUJOCO_GL`` for it and its
    children; :class:`GLPlatformError` naming the choices or what to install when it cannot
    work. Without ``renders``, only what importing MuJoCo needs (a known name, its library, a
    consistent ``PYOPENGL_PLATFORM``: MuJoCo's import fails without them); with it, also a
    display for ``glfw`` and one test frame, the proof that rendering works."""
    value = os.environ.get("MUJOCO_GL", "")
    if not value.strip():
        os.environ["MUJOCO_GL"] = value = DEFAULT_GL
    name = value.strip().lower()
    choices = ", ".join(GL_PLATFORMS)
    if name not in GL_PLATFORMS:
        raise GLPlatformError(f"MUJOCO_GL={value!r} is not a GL platform stepnft renders with: choose one of {choices} "
                              f"(unset means {DEFAULT_GL}, offscreen)")
    platform = GL_PLATFORMS[name]
    pyopengl = os.environ.get("PYOPENGL_PLATFORM", "").strip().lower()
    if pyopengl and not platform.display and pyopengl != name:
        raise GLPlatformError(f"PYOPENGL_PLATFORM={pyopengl!r} contradicts MUJOCO_GL={name!r}: unset "
                              f"PYOPENGL_PLATFORM or set it to {name}")
    if platform.library and ctypes.util.find_library(platform.library) is None:
        other = f", or use MUJOCO_GL={DEFAULT_GL}" if name != DEFAULT_GL else ""
        raise GLPlatformError(f"MUJOCO_GL={name} needs lib{platform.library}, which is not installed: "
                              f"{platform.install}{other}")
    os.environ["MUJOCO_GL"] = name
    if renders:
        if platform.display and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
            raise GLPlatformError(f"MUJOCO_GL={name} renders through a window and no display is set (DISPLAY): use "
                                  f"MUJOCO_GL={DEFAULT_GL} to render offscreen")
        _probe_context(name)
    return name


def _probe_context(name: str) -> None:
    """Render one 16 x 16 frame of an empty MuJoCo scene on platform ``name`` (a context alone is
    no proof: GLFW without a display makes one that fails only when drawn into)."""
    with quiet_teardown(), warnings.catch_warnings():
        warnings.simplefilter("ignore")  # GLFW reports each failure as a warning before it raises
        try:
            import mujoco

            renderer = mujoco.Renderer(mujoco.MjModel.from_xml_string("<mujoco/>"), 16, 16)
            renderer.render()
            renderer.close()
            return
        except Exception as err:  # noqa: BLE001 - each platform fails in its own error types
            reason = str(err).splitlines()[0] if str(err) else type(err).__name__
    # Raised outside the block: the half-built renderer is freed (quietly) before the message.
    raise GLPlatformError(f"MUJOCO_GL={name} cannot render here ({reason[:200]}): {GL_PLATFORMS[name].install}")


@contextlib.contextmanager
def quiet_teardown():
    """Within the block, the teardown of renderers that failed to build prints nothing: a
    ``mujoco.Renderer`` whose constructor raised still runs ``__del__``, which fails again on the
    context it never made. Catch the error inside the block: a traceback carried out of it keeps
    the renderer alive past the block."""
    hook = sys.unraisablehook

    def ignore_renderer_teardown(unraisable) -> None:
        where = getattr(unraisable.object, "__qualname__", "") or type(unraisable.object).__name__
        if "Renderer" not in where and "GLContext" not in where:
            hook(unraisable)

    sys.unraisablehook = ignore_renderer_teardown
    try:
        yield
    finally:
        gc.collect()  # the half-built renderer's __del__ runs now, while the hook is ours
        sys.unraisablehook = hook
